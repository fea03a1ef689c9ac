"""Policy commands: `label` (expert labels: every primitive from every scene's settled state) and
`success-table` (success per tag x primitive from those labels)."""

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

    tab = sub.add_parser(
        "success-table",
        help="success of each primitive per rare tag (and tag x category) from expert labels",
        description="Markdown table of success rate, 95 %% Wilson interval and scenes per tag x primitive "
        "(best per tag in bold) and per (tag, target category) cell with enough scenes, then the cells "
        "whose best primitive beats nominal's best of the same category by 15 points or more.",
    )
    tab.add_argument("labels", type=Path, help="labels Parquet file written by `scenegen label`")
    tab.add_argument("--min-cell", type=int, default=30, help="scenes a (tag, category) cell needs (30)")
    tab.set_defaults(run=success_table)


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


def success_table(args: argparse.Namespace) -> int:
    import pyarrow.parquet as pq

    from scenegen.policy.success_table import differs_from_nominal, markdown_table

    try:
        rows = pq.read_table(args.labels).to_pylist()
    except (OSError, ValueError) as exc:
        return fail(f"{args.labels}: not a labels Parquet file ({first_line(exc)})")
    print(markdown_table(rows, args.min_cell))
    found = differs_from_nominal(rows, args.min_cell)
    print(f"{len(found)} (tag, category) cells whose best primitive beats nominal's best by >= 15 points:")
    for f in found:
        print(
            f"  {f['tag']} / {f['category']}: {f['best']} {f['best_rate']:.2f} vs "
            f"{f['nominal_best']} {f['nominal_best_rate_here']:.2f} (n={f['scenes']})"
        )
    return 0
