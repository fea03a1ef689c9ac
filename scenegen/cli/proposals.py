"""Proposal model commands (issue 63): `proposals label` (every candidate the generic sampler
proposes, executed and measured; the sequence store the model learns from)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import fail, first_line, physics_from


def add_commands(sub) -> None:
    from scenegen.experiment.proposal_labels import LABEL_SETS

    top = sub.add_parser(
        "proposals",
        help="the learned recovery proposal model: label candidates by simulation",
        description="The proposal model ranks actions sampled from what the robot sees (grasps from "
        "above or the side, pushes, pulls: scenegen/manipulation/proposals.py) by a quality learned from "
        "simulated outcomes (docs/policy.md).",
    )
    cmds = top.add_subparsers(dest="proposals_command", metavar="COMMAND", required=True)
    label = cmds.add_parser(
        "label",
        help="execute every candidate of each layout's first decision and store its outcome",
        description="For each layout: the sampler's candidates at the settled state (seen through the "
        "simulator's masks), each executed through the controller and measured by the task's rule; where "
        "no grasp lifts the target, each push and pull is followed by the grasps proposed after it. "
        "Outcomes go to OUT/paths.jsonl (the sequence store, keyed by the candidates executed), what was "
        "proposed to OUT/views. Resumable: rerun the same command after an interruption; a rerun "
        "simulates only what the store lacks.",
    )
    label.add_argument(
        "--layouts",
        nargs="+",
        default=list(LABEL_SETS),
        metavar="SET",
        help="natural:N, rare_rich:N (the learning curves' training sets), curve (their curve set), "
        f"validation (the version 2 validation panel); default: {' '.join(LABEL_SETS)}",
    )
    label.add_argument("--limit", type=int, help="only the first N layouts of each set (a pilot)")
    label.add_argument(
        "--out", type=Path, default=Path("runs/proposals"), help="folder (default runs/proposals)"
    )
    label.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    label.add_argument("--seed", type=int, default=0, help="the sampler's seed (default 0)")
    label.add_argument(
        "--sampler",
        type=int,
        nargs=4,
        metavar=("TOP", "SIDE", "PUSH", "PULL"),
        help="candidates per first decision: grasps from above, from the side, pushes, pulls "
        "(default: SamplerConfig's)",
    )
    label.add_argument(
        "--physics", metavar="NAME", help="what the attempts are simulated under (default dt5)"
    )
    label.add_argument("--quiet", action="store_true", help="no progress bar")
    label.set_defaults(run=proposals_label)


def proposals_label(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from scenegen.env.scenes import scene_sha256
    from scenegen.experiment.proposal_labels import LabelConfig, label_layouts, label_proposals
    from scenegen.experiment.sequences import ObservationStore, PathStore
    from scenegen.manipulation.proposals import SamplerConfig

    if args.workers < 1 or (args.limit is not None and args.limit < 1):
        return fail("--workers and --limit must be at least 1")
    sampler = SamplerConfig() if args.sampler is None else SamplerConfig(*args.sampler)
    if min(sampler.top, sampler.side, sampler.push, sampler.pull) < 0 or sampler.total < 1:
        return fail("--sampler: four counts, none negative, at least one candidate")
    try:
        physics = physics_from(args)
    except ValueError as exc:
        return fail(f"--physics {first_line(exc)}")
    try:
        sets = label_layouts(args.layouts, args.limit)
    except (OSError, ValueError, KeyError) as exc:
        return fail(f"--layouts: {first_line(exc)}")
    scenes = list({scene_sha256(s): s for ss in sets.values() for s in ss}.values())
    config = LabelConfig(sampler=sampler, seed=args.seed)
    store = PathStore(args.out / "paths.jsonl")
    views = ObservationStore(args.out / "views")
    known = len(store.entries)
    print(
        f"{len(scenes)} layouts ({', '.join(f'{k} {len(v)}' for k, v in sets.items())}), store {known} rows"
    )
    with tqdm(desc="label", unit=" jobs", disable=args.quiet) as bar:
        cost = label_proposals(scenes, store, views, config, args.workers, physics, lambda _: bar.update())
    per = cost.per_candidate()
    print(
        f"simulated {cost.simulated} candidates ({'-' if per is None else f'{per:.2f}'} CPU-s each, "
        f"{cost.cpu['simulate'] / 3600:.2f} CPU-h; proposing {cost.cpu['propose']:.0f} CPU-s), "
        f"{cost.stored} from the store; store {len(store.entries)} rows, mismatches {store.mismatches}"
    )
    print(f"-> {args.out}")
    return 0
