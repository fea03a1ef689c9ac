"""Pipeline throughput: per-stage time, accepted scenes per second with 1 and 2 workers, acceptance
by label, and wall time per accepted scene against that scene's own settle + render time.

    .venv/bin/python benchmarks/pipeline_throughput.py [--pipeline pipelines/demo.yaml] [--n 48]
        [--workers 1 2] [--no-render]

Every configuration runs the same recipe and seed in the same invocation (the 1-worker run is the
baseline the others are compared with) into a temporary directory, through `run_batch`, start-up of
the worker processes included. Stage seconds are measured inside the stage (time.perf_counter) and
summed over workers; "build" includes MuJoCo's compile. Prints a table and saves JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import STAGES, run_batch


def measure(config, workers: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_batch(config, Path(tmp) / "batch", workers=workers, progress=False)
    n = max(summary.accepted, 1)
    own = (summary.accepted_seconds["settle"] + summary.accepted_seconds["render"]) / n
    return {
        "workers": workers,
        "accepted": summary.accepted,
        "proposals": summary.proposals,
        "wall_s": round(summary.wall, 3),
        "accepted_per_s": round(summary.accepted / summary.wall, 3),
        "wall_per_accepted_s": round(summary.wall / n, 4),
        "own_settle_render_s": round(own, 4),
        "wall_over_own": round(summary.wall / n / own, 3) if own else None,
        "stage_s": {k: round(v, 3) for k, v in summary.seconds.items()},
        "stage_s_per_accepted": {k: round(v / n, 4) for k, v in summary.seconds.items()},
        "share_of_proposals": {
            "accepted": round(summary.accepted / summary.proposals, 4),
            **{k: round(v / summary.proposals, 4) for k, v in summary.rejections.most_common()},
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", type=Path, default=Path("pipelines/demo.yaml"))
    parser.add_argument("--n", type=int, default=48)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--no-render", action="store_true")
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/pipeline_throughput.json"))
    args = parser.parse_args()

    overrides = {"n": args.n, "seed": args.seed, "render": False if args.no_render else None}
    config = load_pipeline(args.pipeline, overrides)
    cams = ", ".join(f"{c.name} {c.width}x{c.height}" for c in config.proposer.cameras)
    print(f"{config.name}: n={config.n} seed={config.seed} render={config.render} cameras: {cams}")
    runs = [measure(config, w) for w in args.workers]
    base = runs[0]

    columns = (("workers", 8), ("wall s", 9), ("scenes/s", 10), ("speed-up", 10), ("wall/scene", 12))
    print("\n" + "".join(f"{h:>{w}}" for h, w in (*columns, ("own s+r", 9), ("ratio", 7))))
    for r in runs:
        speedup = r["accepted_per_s"] / base["accepted_per_s"]
        print(
            f"{r['workers']:>8}{r['wall_s']:>9.1f}{r['accepted_per_s']:>10.2f}{speedup:>10.2f}"
            f"{r['wall_per_accepted_s']:>12.3f}{r['own_settle_render_s']:>9.3f}{r['wall_over_own']:>7.2f}"
        )
    print("\nstage seconds per accepted scene (all proposals, summed over workers):")
    print(f"{'stage':<10}" + "".join(f"{'w=' + str(r['workers']):>10}" for r in runs))
    for stage in STAGES:
        print(f"{stage:<10}" + "".join(f"{r['stage_s_per_accepted'][stage]:>10.3f}" for r in runs))
    print("\nshare of proposals: " + ", ".join(f"{k} {v:.1%}" for k, v in base["share_of_proposals"].items()))

    args.json.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "pipeline": str(args.pipeline),
        "n": args.n,
        "seed": args.seed,
        "render": config.render,
        "cameras": cams,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "runs": runs,
    }
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"saved {args.json}")


if __name__ == "__main__":
    main()
