"""The batch report at scale: a 1,000-scene rendered batch's report.html, how large it is and how soon
its first screen shows in a real browser, against a 30-scene batch of the same recipe and seed (its
first 30 scenes) measured in the same run.

    .venv/bin/python benchmarks/report_scale.py [--n 1000] [--baseline 30] [--workers 2]

Generates (or resumes) runs/report_scale/batch_N (pipelines/procedural.yaml, seed 0, rendered), writes
each report (thumbnails, the audit recomputed: CPU and wall), then opens each page in Debian's
chromium through Playwright five times: first contentful paint, DOMContentLoaded and load, median of
the five. Writes benchmarks/results/report_scale.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "pipelines" / "procedural.yaml"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
LOADS = 5


def generate(out: Path, n: int, workers: int) -> None:
    command = [sys.executable, "-m", "scenegen.cli", "generate", str(RECIPE), "--n", str(n), "--seed", "0"]
    command += ["--out", str(out), "--workers", str(workers), "--quiet"]
    subprocess.run(command, check=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})


def make_report(batch: Path, workers: int) -> dict:
    from scenegen.report.page import batch_report

    wall, cpu = time.perf_counter(), time.process_time()
    page = batch_report(batch, audit=True, workers=workers)
    files = list((batch / "report_files").iterdir())
    return {
        "report_wall_s": round(time.perf_counter() - wall, 2),
        "report_cpu_s_this_process": round(time.process_time() - cpu, 2),
        "html_bytes": page.stat().st_size,
        "thumbnail_files": len(files),
        "thumbnail_bytes": sum(f.stat().st_size for f in files),
    }


def first_screen(html: Path) -> dict:
    """Median over LOADS fresh pages: first contentful paint, DOMContentLoaded, load (ms)."""
    from playwright.sync_api import sync_playwright

    times = {"first_contentful_paint_ms": [], "dom_content_loaded_ms": [], "load_ms": []}
    with sync_playwright() as playwright:
        args = ["--no-sandbox"] if os.geteuid() == 0 else []
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=args)
        for _ in range(LOADS):
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(html.as_uri(), wait_until="load")
            for _ in range(100):  # the paint entry can be recorded after the load event (the page's CSP
                # forbids string evaluation, so no wait_for_function)
                if page.evaluate("() => performance.getEntriesByName('first-contentful-paint').length"):
                    break
                page.wait_for_timeout(50)
            entry = page.evaluate(
                """() => {
                  const nav = performance.getEntriesByType('navigation')[0];
                  const fcp = performance.getEntriesByName('first-contentful-paint')[0];
                  return {fcp: fcp ? fcp.startTime : null,
                          dcl: nav.domContentLoadedEventEnd, load: nav.loadEventEnd};
                }"""
            )
            times["first_contentful_paint_ms"].append(entry["fcp"])
            times["dom_content_loaded_ms"].append(entry["dcl"])
            times["load_ms"].append(entry["load"])
            page.close()
        browser.close()
    return {k: round(statistics.median(v), 1) for k, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n", type=int, default=1000, help="scenes of the large batch (default 1000)")
    parser.add_argument("--baseline", type=int, default=30, help="scenes of the baseline batch (default 30)")
    parser.add_argument("--workers", type=int, default=2, help="generation and audit processes (default 2)")
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "report_scale")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "report_scale.json")
    args = parser.parse_args()
    results = {}
    for n in (args.baseline, args.n):
        batch = args.runs / f"batch_{n}"
        generate(batch, n, args.workers)
        row = make_report(batch, args.workers)
        row |= first_screen(batch / "report.html")
        results[str(n)] = row
        print(n, row, flush=True)
    base, big = results[str(args.baseline)], results[str(args.n)]
    results["ratios"] = {
        k: round(big[k] / base[k], 2)
        for k in ("html_bytes", "thumbnail_bytes", "report_wall_s", "first_contentful_paint_ms", "load_ms")
        if base[k]
    }
    results["machine"] = f"{os.cpu_count()} cores; chromium {CHROMIUM}"
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps(results["ratios"]))


if __name__ == "__main__":
    main()
