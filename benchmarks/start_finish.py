"""Start and finish: the whole `scenegen generate` process for the demo batch against the baseline
commit's batch loop, in the same run.

    .venv/bin/python benchmarks/start_finish.py [--n 48] [--workers 2] [--repeats 2]
        [--pipeline pipelines/demo.yaml] [--baseline 9430f21]

Each run is `python -m scenegen.cli generate PIPELINE --n N --seed 0 --workers W --quiet` in a fresh
process, from the baseline's files (`git archive`, this virtual environment) or this checkout,
alternated ``--repeats`` times on the same machine. Per run: the process's wall seconds (imports,
recipe and catalog, the proposer's model, the workers' start, the loop, the batch manifest and its
realism checks, exit) and the batch loop's wall seconds as the batch's timings.json records them.
Reported: the medians, and the goal's ratio, this checkout's whole process over the baseline's loop
(issue 44: at most 1.2). The two versions' batches must agree byte for byte (index.jsonl,
rejections.jsonl, and every scene file's checksum through them) and in the realism checks their
manifests record, else the benchmark fails.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from baseline import ROOT, baseline_tree


def generate(code: Path, pipeline: str, n: int, workers: int, out: Path) -> dict:
    """One whole `scenegen generate` process from the files under ``code``."""
    env = {**os.environ, "PYTHONPATH": str(code), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", pipeline, "--n", str(n), "--seed", "0"]
    cmd += ["--workers", str(workers), "--out", str(out), "--quiet"]
    began = time.perf_counter()
    result = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - began
    if result.returncode != 0:
        raise SystemExit(f"{code}: exited {result.returncode}\n{result.stderr[-3000:]}")
    timings = json.loads((out / "timings.json").read_text())
    logs = {
        name: hashlib.sha256((out / name).read_bytes()).hexdigest()
        for name in ("index.jsonl", "rejections.jsonl")
    }
    realism = yaml.safe_load((out / "manifest.yaml").read_text())["sources"][0]["realism"]
    logs["realism"] = hashlib.sha256(json.dumps(realism, sort_keys=True).encode()).hexdigest()
    return {"process_s": round(wall, 2), "loop_s": timings["wall"], "logs": logs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", default="pipelines/demo.yaml")
    parser.add_argument("--n", type=int, default=48, help="accepted scenes (default 48)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2, help="runs of each version, alternated")
    parser.add_argument("--baseline", default="9430f21", help="commit whose code is the baseline")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/start_finish.json"))
    args = parser.parse_args()
    runs: dict[str, list[dict]] = {"baseline": [], "current": []}
    with tempfile.TemporaryDirectory() as tmp:
        code = {"baseline": baseline_tree(args.baseline, Path(tmp) / "baseline"), "current": ROOT}
        for repeat in range(args.repeats):
            for version in code if repeat % 2 == 0 else reversed(list(code)):
                print(f"{version} (run {repeat + 1}) ...", flush=True)
                out = Path(tmp) / f"{version}_{repeat}"
                runs[version].append(generate(code[version], args.pipeline, args.n, args.workers, out))
                print(f"  {runs[version][-1]}", flush=True)
    same = len({json.dumps(r["logs"], sort_keys=True) for rs in runs.values() for r in rs}) == 1
    median = {
        v: {k: round(statistics.median(r[k] for r in rs), 2) for k in ("process_s", "loop_s")}
        for v, rs in runs.items()
    }
    ratio = round(median["current"]["process_s"] / median["baseline"]["loop_s"], 3)
    print(f"\n{args.n} scenes of {args.pipeline}, {args.workers} workers, medians of {args.repeats} runs")
    print("| code | whole process s | batch loop s | outside the loop s |")
    print("|---|---|---|---|")
    for v, m in median.items():
        print(f"| {v} | {m['process_s']} | {m['loop_s']} | {m['process_s'] - m['loop_s']:.2f} |")
    print(f"this checkout's whole process / the baseline's loop: {ratio} (goal: at most 1.2)")
    print(f"same batches (index.jsonl, rejections.jsonl, the manifest's realism checks): {same}")
    payload = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "pipeline": args.pipeline,
        "n": args.n,
        "workers": args.workers,
        "baseline": args.baseline,
        "runs": runs,
        "median": median,
        "process_over_baseline_loop": ratio,
        "same_batches": same,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(payload, indent=1) + "\n")
    print(f"-> {args.json}")
    if not same:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
