"""Multi-tag requests with repairs: accepted scenes, tries (first-pass proposals + repairs) per
accepted scene and the proposer's own CPU, for the code at a baseline commit (no repairs) and this
checkout (``--repairs``), in the same invocation.

    .venv/bin/python benchmarks/repair_yield.py [--n 20] [--baseline-n 10] [--baseline bf81ff9]
        [--repairs 4] [--width 1] [--requests "retrieve the mug toppled occluded low_light" ...]

Each run is `scenegen generate pipelines/demo.yaml --request R --no-render --workers 1` in a fresh
process (one process, so the coordinator's ``propose`` seconds in timings.json are the proposer's
own time on one core, sampling + decoding + separating + repairing); the baseline runs from that
commit's code (`git archive`) with its own recipe and checkpoint, this checkout with the recipe's
``proposer.repairs`` / ``repair_width`` set. CPU-s: the child process's user + system time. Prints a
table and writes benchmarks/results/repair_yield.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proposer_cpu import ROOT, extract  # noqa: E402

REQUESTS = (
    "retrieve the mug toppled occluded low_light",
    "retrieve the spoon under_overhang clutter occluded",
    "retrieve the box on_floor toppled low_light",
)


def generate(code: Path, recipe: Path, request: str, n: int, out: Path) -> dict:
    """One batch in a child process; its counts, the proposer's seconds and the child's CPU-s."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(recipe), "--request", request]
    cmd += ["--n", str(n), "--no-render", "--workers", "1", "--quiet", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(code), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 1):
        raise SystemExit(f"{request}: {done.stderr.strip().splitlines()[-1]}")
    rows = [json.loads(line) for line in (out / "rejections.jsonl").read_text().splitlines()]
    accepted = len((out / "index.jsonl").read_text().splitlines())
    first = accepted + sum(1 for r in rows if not r.get("repaired"))
    tries = accepted + len(rows)
    propose = json.loads((out / "timings.json").read_text())["stages"]["propose"]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "accepted": accepted,
        "first_pass": first,
        "tries": tries,
        "tries_per_accepted": tries / max(accepted, 1),
        "propose_s": propose,
        "propose_s_per_first_pass": propose / max(first, 1),
        "propose_s_per_accepted": propose / max(accepted, 1),
        "cpu_s": cpu,
        "cpu_s_per_accepted": cpu / max(accepted, 1),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=20, help="accepted scenes per request with repairs")
    parser.add_argument("--baseline-n", type=int, default=10, help="accepted scenes per request, baseline")
    parser.add_argument("--baseline", default="bf81ff9", help="commit without repairs (default bf81ff9)")
    parser.add_argument("--repairs", type=int, default=4, help="repairs per proposal (default 4)")
    parser.add_argument("--width", type=int, default=1, help="repairs per expansion (default 1: a chain)")
    parser.add_argument("--requests", nargs="+", default=list(REQUESTS), help="request texts")
    args = parser.parse_args(argv)
    raw = yaml.safe_load((ROOT / "pipelines" / "demo.yaml").read_text())
    raw["proposer"].update(repairs=args.repairs, repair_width=args.width)
    results: dict = {"baseline": {}, "current": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        recipe = tmp / "repairs.yaml"
        recipe.write_text(yaml.safe_dump(raw, sort_keys=False))
        code = extract(args.baseline, tmp)
        for k, request in enumerate(args.requests):
            base = generate(code, code / "pipelines" / "demo.yaml", request, args.baseline_n, tmp / f"b{k}")
            results["baseline"][request] = base
            results["current"][request] = generate(ROOT, recipe, request, args.n, tmp / f"c{k}")
            print(request, json.dumps({s: results[s][request] for s in results}), flush=True)
    print(f"\nrepairs {args.repairs}, width {args.width}; baseline {args.baseline} without repairs")
    print(
        "| request | baseline accepted / tries | tries per accepted | with repairs accepted / tries "
        "| tries per accepted | proposer ms per first-pass proposal: baseline | with repairs "
        "| proposer CPU-s per accepted: baseline | with repairs "
        "| CPU-s per accepted: baseline | with repairs |"
    )
    print("|---" * 11 + "|")
    for request in args.requests:
        b, c = results["baseline"][request], results["current"][request]
        print(
            f"| {request} | {b['accepted']} / {b['tries']} | {b['tries_per_accepted']:.1f} | "
            f"{c['accepted']} / {c['tries']} | {c['tries_per_accepted']:.1f} | "
            f"{1e3 * b['propose_s_per_first_pass']:.0f} | {1e3 * c['propose_s_per_first_pass']:.0f} | "
            f"{b['propose_s_per_accepted']:.2f} | {c['propose_s_per_accepted']:.2f} | "
            f"{b['cpu_s_per_accepted']:.1f} | {c['cpu_s_per_accepted']:.1f} |"
        )
    out = ROOT / "benchmarks" / "results" / "repair_yield.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), **results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
