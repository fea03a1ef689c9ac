"""The proposal model's learning curves (issue 63, point 5; scenegen/experiment/proposal_curves.py):
for each training-set size and seed, a model trained on the natural-rate set and one on the
rare-rich set of that size, scored by its first-ranked candidate's label on the curve set's rare
layouts, through the simulator's masks (oracle) and through the default retrieval head, beside the
hand chooser's first attempt (assets/policy/baseline, simulated once into MODELS/chooser). Reads the
labels of `scenegen proposals label` (all of its default sets); resumable: a model whose scores
exist is not trained again.

    .venv/bin/scenegen proposals label --workers 2          # the labels first (resumable)
    .venv/bin/python benchmarks/proposal_curves.py --workers 2
    .venv/bin/python benchmarks/proposal_curves.py --sizes 100 --seeds 0   # one size, one seed

Writes results.json, curves.md and curves.png under --out, and prints per sight and rare tag the
sizes where the rare-rich set leads beyond its interval.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from scenegen.experiment.proposal_curves import (
    SIGHTS,
    SIZES,
    STEPS,
    STYLES,
    chooser_results,
    chooser_rows,
    prepare,
    proposal_jobs,
    run_job,
)
from scenegen.experiment.proposal_labels import LABELS_FOLDER
from scenegen.experiment.retrieval_curves import SEEDS, curve_results, curve_table, leads, plot_curves
from scenegen.perception.retrieval import DEFAULT_HEAD
from scenegen.store.batch import atomic_write


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--labels", type=Path, default=LABELS_FOLDER, help=f"label folder (default {LABELS_FOLDER})"
    )
    parser.add_argument("--head", type=Path, default=DEFAULT_HEAD, help="the head of the 'head' sight")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--steps", type=int, default=STEPS, help="training steps per model")
    parser.add_argument("--models", type=Path, default=Path("runs/proposal_curves"), help="models, scores")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/proposal_curves"))
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    started = time.monotonic()
    try:
        prepare(args.labels, args.head, args.sizes, args.workers, progress=None)
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    jobs = proposal_jobs(args.sizes, args.seeds)
    context = multiprocessing.get_context("spawn")
    records = []
    with ProcessPoolExecutor(args.workers, mp_context=context) as pool:
        futures = [
            pool.submit(run_job, job, args.models, args.labels, args.head, steps=args.steps) for job in jobs
        ]
        for job, future in zip(jobs, futures, strict=True):
            records += future.result()
            print(f"{job.name}: {records[-1]['training_cpu_s']} CPU-s", flush=True)
    results = curve_results(records, scored_sets=("curve",), designs=SIGHTS, value="success")
    results["leads"] = {"curve": leads(results, "curve")}
    results["steps"] = args.steps
    results["chooser"] = chooser_results(
        chooser_rows(args.models / "chooser", args.head, workers=args.workers)
    )
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "results.json", json.dumps(results, indent=1) + "\n")
    table = curve_table(results, "curve").replace("| design |", "| sight |")
    chooser = ["| sight | tag | layouts | first-attempt success |", "|---|---|---|---|"]
    for sight, tags in results["chooser"].items():
        chooser += [f"| {sight} | {t} | {c['scenes']} | {c['mean']:.3f} [{c['low']:.3f}, {c['high']:.3f}] |"
                    for t, c in tags.items()]  # fmt: skip
    text = (
        f"## curve set: first-ranked candidate's success\n\n{table}\n## the hand chooser, first attempt\n\n"
    )
    atomic_write(args.out / "curves.md", text + "\n".join(chooser) + "\n")
    title = "proposal model: first-ranked candidate's success"
    atomic_write(args.out / "curves.png", plot_curves(results, "curve", title=title, styles=STYLES))
    print(table)
    for sight, per_tag in results["leads"]["curve"].items():
        print(f"{sight}: rare-rich leads beyond its interval at {per_tag}")
    print(f"{len(jobs)} models, {time.monotonic() - started:.0f} s wall -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
