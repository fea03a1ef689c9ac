"""Per-stage time and acceptance by label of a pipeline run (default: the demo recipe).

    python benchmarks/pipeline_stages.py [--pipeline pipelines/demo.yaml] [--n 24] [--seed 0]

Prints a table (seconds per stage, share of wall time, seconds per accepted scene) and the
acceptance rate by rejection label, and saves both as JSON (default benchmarks/results/). The
stage times are measured inside the run (time.perf_counter around each stage); "build" includes
MuJoCo's compile of every scene, and the first compile of the process (~1.5 s) is counted in it.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from scenegen.config import load_pipeline
from scenegen.pipeline import STAGES, run_batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", type=Path, default=Path("pipelines/demo.yaml"))
    parser.add_argument("--n", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/pipeline_stages.json"))
    args = parser.parse_args()

    config = load_pipeline(args.pipeline, {"n": args.n, "seed": args.seed})
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = run_batch(config, Path(tmp) / "batch", progress=False)
        wall = time.perf_counter() - t0

    per_scene = {s: summary.seconds[s] / max(summary.accepted, 1) for s in STAGES}
    print(f"{config.name}: {summary.accepted} accepted of {summary.proposals} proposals, wall {wall:.1f} s")
    print(f"{'stage':<10}{'seconds':>10}{'share':>8}{'s/accepted':>12}")
    for stage in STAGES:
        s = summary.seconds[stage]
        print(f"{stage:<10}{s:>10.2f}{s / wall:>8.1%}{per_scene[stage]:>12.3f}")
    other = wall - sum(summary.seconds.values())
    print(f"{'other':<10}{other:>10.2f}{other / wall:>8.1%}")
    print(f"{'total':<10}{wall:>10.2f}{1:>8.0%}{wall / max(summary.accepted, 1):>12.3f}")
    rates = {"accepted": summary.accepted / summary.proposals}
    rates.update({label: count / summary.proposals for label, count in summary.rejections.most_common()})
    print("share of proposals: " + ", ".join(f"{k} {v:.1%}" for k, v in rates.items()))

    args.json.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "pipeline": str(args.pipeline),
        "n": args.n,
        "seed": args.seed,
        "machine": {"cpus": __import__("os").cpu_count(), "platform": platform.platform()},
        "accepted": summary.accepted,
        "proposals": summary.proposals,
        "wall_s": round(wall, 3),
        "stage_s": {k: round(v, 3) for k, v in summary.seconds.items()},
        "share_of_proposals": {k: round(v, 4) for k, v in rates.items()},
    }
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"saved {args.json}")


if __name__ == "__main__":
    main()
