"""The retrieval head's learning curves (issue 43; scenegen/experiment/retrieval_curves.py): for each
design, training-set size and seed, a head trained on the natural-rate set and one on the rare-rich
set of that size, scored per tag by the overlap rule on the curve set (rare unique-category layouts
of the seed-1 reference table on no panel) and on the validation panel. Resumable: a head whose
scores exist is not trained again.

    .venv/bin/python benchmarks/retrieval_curves.py --workers 2     # ~2 h on 2 cores
    .venv/bin/python benchmarks/retrieval_curves.py --sizes 30 100 --seeds 0 --designs instances
    .venv/bin/python benchmarks/retrieval_curves.py --sensor active_stereo --designs instances \
        --sizes 100 300 1000

Writes results.json, curves.md (both tables) and curves.png (the curve set) under --out, and prints
per design and rare tag the sizes where the rare-rich set leads beyond its interval.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from scenegen.experiment.retrieval_curves import (
    DESIGNS,
    PANEL,
    SEEDS,
    SIZES,
    curve_jobs,
    curve_results,
    curve_table,
    leads,
    plot_curves,
    run_job,
    scoring_scenes,
    training_sets,
)
from scenegen.perception.retrieval.frames import frames_key, render_missing
from scenegen.render.sensor import SENSOR_NAMES
from scenegen.store.batch import atomic_write


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--designs", nargs="+", choices=DESIGNS, default=list(DESIGNS))
    parser.add_argument("--cache", type=Path, default=Path("runs/cache/frames"))
    parser.add_argument(
        "--heads", type=Path, help="trained heads and their scores (default runs/curves[_SENSOR])"
    )
    parser.add_argument("--out", type=Path, help="default benchmarks/results/retrieval_curves[_SENSOR]")
    parser.add_argument(
        "--sensor",
        choices=SENSOR_NAMES,
        default="exact",
        help="the frames' depth at training and scoring (docs/sensor.md); a head through a sensor is "
        "trained under its depth rule (regions.rule_name_for)",
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--smallest-first",
        action="store_true",
        help="train the smallest sets first (a second run beside one going largest first shares its heads)",
    )
    args = parser.parse_args()
    suffix = "" if args.sensor == "exact" else f"_{args.sensor}"
    args.heads = args.heads or Path(f"runs/curves{suffix}")
    args.out = args.out or Path(f"benchmarks/results/retrieval_curves{suffix}")

    started = time.monotonic()
    wanted = {}
    for group in (*scoring_scenes().values(), *(s for n in args.sizes for s in training_sets(n).values())):
        wanted.update({frames_key(s, sensor=args.sensor): s for s in group})
    render_missing(list(wanted.values()), args.cache, args.workers, progress=True, sensor=args.sensor)

    jobs = curve_jobs(args.sizes, args.seeds, args.designs)
    jobs = jobs[::-1] if args.smallest_first else jobs
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, mp_context=context) as pool:
        futures = [pool.submit(run_job, job, args.heads, args.cache, sensor=args.sensor) for job in jobs]
        records = []
        for job, future in zip(jobs, futures, strict=True):
            records.append(future.result())
            print(f"{job.name}: {records[-1]['training_cpu_s']} CPU-s", flush=True)
    results = curve_results(records)
    results["leads"] = {scored: leads(results, scored) for scored in ("curve", PANEL)}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "results.json", json.dumps(results, indent=1) + "\n")
    tables = [f"## {scored} set\n\n{curve_table(results, scored)}" for scored in ("curve", PANEL)]
    atomic_write(args.out / "curves.md", "\n".join(tables))
    atomic_write(args.out / "curves.png", plot_curves(results))
    print("\n".join(tables))
    for design, per_tag in results["leads"]["curve"].items():
        print(f"{design}: rare-rich leads beyond its interval at {per_tag}")
    print(f"{len(jobs)} heads, {time.monotonic() - started:.0f} s wall -> {args.out}")


if __name__ == "__main__":
    main()
