"""Policy commands: `label` (expert labels: every primitive from every scene's settled state)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import fail, first_line


def add_commands(sub) -> None:
    lab = sub.add_parser(
        "label",
        help="execute every grasp primitive from every scene's settled state; one row per (scene, primitive)",
        description="Expert labels for the retrieve task: each primitive runs from each scene's settled "
        "state through robosuite's controller and the simulator measures success, lift, duration and the "
        "failure event. SCENES: a batch directory, a scene folder or a reference Parquet table (its "
        "layouts built into scenes). Targets on the floor are left out (out of reach). Resumable: rows "
        "already labelled (same scene sha256, primitive and version) are reused.",
    )
    lab.add_argument("scenes", type=Path, help="batch directory, scene folder or reference Parquet table")
    lab.add_argument("--out", type=Path, required=True, help="labels Parquet file to write")
    lab.add_argument("--primitives", nargs="+", help="primitives to run (default: all)")
    lab.add_argument("--split", default="train", help="a table's split: train (default), heldout or all")
    lab.add_argument("--limit", type=int, help="label only the first N scenes")
    lab.add_argument(
        "--per-tag", type=int, help="only the first N scenes holding each rare tag and N nominal ones"
    )
    lab.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    lab.add_argument("--quiet", action="store_true", help="no progress bar")
    lab.set_defaults(run=label)


def label(args: argparse.Namespace) -> int:
    from scenegen.policy.labels import LabelError, label

    if args.workers < 1 or any(v is not None and v < 1 for v in (args.limit, args.per_tag)):
        return fail("--workers, --limit and --per-tag must be at least 1")
    try:
        stats = label(
            args.scenes,
            args.out,
            primitives=args.primitives,
            split=None if args.split == "all" else args.split,
            limit=args.limit,
            workers=args.workers,
            progress=not args.quiet,
            per_tag=args.per_tag,
        )
    except (LabelError, OSError) as exc:
        return fail(first_line(exc))
    print(f"{stats['rows']} rows ({stats['ran']} run, {stats['reused']} reused) -> {stats['out']}")
    return 0
