"""Proposal model commands (issue 63): `proposals label` (every candidate the generic sampler
proposes, executed and measured; the sequence store the model learns from), `proposals train` (the
quality model on labelled layouts), `proposals eval` (its first-ranked candidate's success, a
lookup in the labels) and `proposals compare` (two closed-loop runs' episodes, paired by layout)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import add_device_argument, device_error, fail, first_line, physics_from

LABELS_FOLDER = Path("runs/proposal_labels")  # proposal_labels.LABELS_FOLDER (its import is slow)


def add_commands(sub) -> None:
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
        metavar="SET",
        help="natural:N, rare_rich:N (the learning curves' training sets), curve (their curve set), "
        "validation (the version 2 validation panel); default: every set issue 63 labels "
        "(natural:600 rare_rich:100 rare_rich:300 rare_rich:600 curve validation)",
    )
    label.add_argument("--limit", type=int, help="only the first N layouts of each set (a pilot)")
    label.add_argument(
        "--out",
        type=Path,
        default=LABELS_FOLDER,
        help=f"folder (default {LABELS_FOLDER}; resumable)",
    )
    label.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    label.add_argument("--seed", type=int, default=0, help="the sampler's seed (default 0)")
    label.add_argument(
        "--sampler",
        type=int,
        nargs=4,
        metavar=("TOP", "SIDE", "PUSH", "PULL"),
        help="candidates per first decision: grasps from above, from the side, pushes, pulls "
        "(default 6 1 1 1: the labels issue 63 declares, sized to its budget)",
    )
    label.add_argument(
        "--physics", metavar="NAME", help="what the attempts are simulated under (default dt5)"
    )
    label.add_argument("--quiet", action="store_true", help="no progress bar")
    label.set_defaults(run=proposals_label)
    _add_train(cmds)
    _add_eval(cmds)
    _add_compare(cmds)


def _add_compare(cmds) -> None:
    co = cmds.add_parser(
        "compare",
        help="two closed-loop runs' episodes paired by layout: first attempt and whole episode",
        description="Reads two episodes files of `scenegen experiment perception-gap` on the same layouts "
        "(e.g. the proposal model's and the chooser's episodes_oracle.jsonl) and writes, per measure "
        "(first-attempt success, whole-episode success) and group (all, each rare tag, nominal), both "
        "rates and the first minus the second with its 95 %% bootstrap interval over layouts "
        "(compare.json, compare.md under --out).",
    )
    co.add_argument("first", type=Path, help="episodes file (e.g. the proposal model's)")
    co.add_argument("second", type=Path, help="episodes file to compare against (e.g. the chooser's)")
    co.add_argument("--out", type=Path, required=True, help="folder for compare.json and compare.md")
    co.set_defaults(run=proposals_compare)


def _shared(parser, layouts: list[str]) -> None:
    parser.add_argument(
        "--layouts",
        nargs="+",
        default=layouts,
        metavar="SET",
        help=f"as for label (default {' '.join(layouts)})",
    )
    parser.add_argument(
        "--labels",
        type=Path,
        default=LABELS_FOLDER,
        help=f"the label folder (default {LABELS_FOLDER}; resumable)",
    )
    parser.add_argument(
        "--retrieval",
        type=Path,
        help="see the target through this retrieval head's mask (default: the simulator's masks)",
    )
    parser.add_argument("--limit", type=int, help="only the first N layouts of each set")
    parser.add_argument("--workers", type=int, default=1, help="rendering processes (default 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_train(cmds) -> None:
    train = cmds.add_parser(
        "train",
        help="train the proposal model on labelled layouts (safetensors checkpoint folder)",
        description="Each labelled candidate of the layouts' first decisions, seen as an oriented crop of "
        "both cameras (RGB, depth, the target's mask) with its parameters, teaches the model its label: "
        "the attempt lifted the target (a push or pull: a grasp after it did). Crops are cached under "
        "LABELS/crops.",
    )
    _shared(train, ["natural:600"])
    train.add_argument("--out", type=Path, required=True, help="checkpoint folder")
    train.add_argument("--steps", type=int, default=3000, help="batches of 64 (default 3000)")
    train.add_argument("--width", type=int, default=16, help="channels of the first layer (default 16)")
    train.add_argument("--seed", type=int, default=0)
    add_device_argument(train)
    train.set_defaults(run=proposals_train)


def _add_eval(cmds) -> None:
    ev = cmds.add_parser(
        "eval",
        help="the first-ranked candidate's success per tag, looked up in the labels",
        description="For each labelled layout the model ranks the candidates labelled there; its figure is "
        "the label of the one it ranks first (no simulation), per rare tag, pooled rare, nominal and all, "
        "beside the ceiling (any candidate worked). Writes summary.json and summary.md under --out.",
    )
    _shared(ev, ["validation"])
    ev.add_argument("--model", type=Path, required=True, help="a proposal model folder")
    ev.add_argument("--out", type=Path, required=True, help="folder for the summary")
    ev.set_defaults(run=proposals_eval)


def proposals_label(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from scenegen.env.scenes import scene_sha256
    from scenegen.experiment.proposal_labels import (
        DEFAULT_LABELS,
        LABEL_SETS,
        LabelConfig,
        label_layouts,
        label_proposals,
        open_labels,
    )
    from scenegen.manipulation.proposals import SamplerConfig

    if args.workers < 1 or (args.limit is not None and args.limit < 1):
        return fail("--workers and --limit must be at least 1")
    sampler = DEFAULT_LABELS.sampler if args.sampler is None else SamplerConfig(*args.sampler)
    if min(sampler.top, sampler.side, sampler.push, sampler.pull) < 0 or sampler.total < 1:
        return fail("--sampler: four counts, none negative, at least one candidate")
    try:
        physics = physics_from(args)
    except ValueError as exc:
        return fail(f"--physics {first_line(exc)}")
    try:
        sets = label_layouts(args.layouts or LABEL_SETS, args.limit)
    except (OSError, ValueError, KeyError) as exc:
        return fail(f"--layouts: {first_line(exc)}")
    scenes = list({scene_sha256(s): s for ss in sets.values() for s in ss}.values())
    try:
        config, store, views = open_labels(
            args.out, LabelConfig(sampler=sampler, seed=args.seed, physics=physics)
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return fail(first_line(exc))
    known = len(store.entries)
    print(
        f"{len(scenes)} layouts ({', '.join(f'{k} {len(v)}' for k, v in sets.items())}), store {known} rows"
    )
    with tqdm(desc="label", unit=" jobs", disable=args.quiet) as bar:

        def progress(kind: str) -> None:  # the phase (propose, simulate) beside the count
            bar.set_description(f"label: {kind}", refresh=False)
            bar.update()

        cost = label_proposals(scenes, store, views, config, args.workers, progress)
    per = cost.per_candidate()
    print(
        f"simulated {cost.simulated} candidates ({'-' if per is None else f'{per:.2f}'} CPU-s each, "
        f"{cost.cpu['simulate'] / 3600:.2f} CPU-h; proposing {cost.cpu['propose']:.0f} CPU-s), "
        f"{cost.stored} from the store; store {len(store.entries)} rows, mismatches {store.mismatches}"
    )
    print(f"-> {args.out}")
    return 0


def _examples(args):
    """(scenes, examples) of ``args.layouts`` through ``args.retrieval``; ValueError names the input."""
    from tqdm import tqdm

    from scenegen.env.scenes import scene_sha256
    from scenegen.experiment.proposal_data import examples
    from scenegen.experiment.proposal_labels import label_layouts, open_labels

    if args.workers < 1 or (args.limit is not None and args.limit < 1):
        raise ValueError("--workers and --limit must be at least 1")
    config, store, views = open_labels(args.labels)
    sets = label_layouts(args.layouts, args.limit)
    scenes = list({scene_sha256(s): s for ss in sets.values() for s in ss}.values())
    with tqdm(desc="crops", unit=" layouts", disable=args.quiet) as bar:
        data = examples(scenes, store, views, args.labels / "crops", config, retrieval=args.retrieval,
                        workers=args.workers, progress=lambda _: bar.update())  # fmt: skip
    return scenes, data


def proposals_train(args: argparse.Namespace) -> int:
    from scenegen.devices import resolve_device
    from scenegen.experiment.proposal_offline import train_on

    if (error := device_error(args)) is not None:
        return fail(error)
    if args.steps < 1 or args.width < 1:
        return fail("--steps and --width must be at least 1")
    try:
        _, data = _examples(args)
        config = {
            "layouts": args.layouts,
            "limit": args.limit,
            "retrieval": args.retrieval and str(args.retrieval),
        }
        model = train_on(data, args.steps, args.seed, args.width, str(resolve_device(args.device)), config)
    except (OSError, ValueError, KeyError) as exc:
        return fail(first_line(exc))
    model.save(args.out)
    print(f"{len(data)} candidates ({int(data.labels.sum())} lifted), {args.steps} steps -> {args.out}")
    return 0


def proposals_eval(args: argparse.Namespace) -> int:
    import json

    from scenegen.core.files import CheckpointError
    from scenegen.experiment.proposal_offline import by_tag, first_ranked
    from scenegen.policy.proposal_model import ProposalModel
    from scenegen.store.batch import atomic_write

    try:
        model = ProposalModel.load(args.model)
        scenes, data = _examples(args)
    except (CheckpointError, OSError, ValueError, KeyError) as exc:
        return fail(first_line(exc))
    table = by_tag(first_ranked(model, data), scenes)
    lines = ["| layouts | n | first-ranked success | ceiling |", "|---|---|---|---|"]
    lines += [
        f"| {k} | {v['layouts']} | {v['success']:.3f} | {v['ceiling']:.3f} |"
        for k, v in sorted(table.items())
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "model": str(args.model),
        "layouts": args.layouts,
        "retrieval": args.retrieval and str(args.retrieval),
    }
    atomic_write(args.out / "summary.json", json.dumps({**summary, "by_tag": table}, indent=1) + "\n")
    atomic_write(args.out / "summary.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"-> {args.out}")
    return 0


def proposals_compare(args: argparse.Namespace) -> int:
    import json

    from scenegen.experiment.proposal_loop import compare_episodes
    from scenegen.store.batch import atomic_write

    rows = []
    for path in (args.first, args.second):
        try:
            rows.append([json.loads(line) for line in path.read_text().splitlines() if line.strip()])
        except (OSError, ValueError) as exc:
            return fail(
                f"{path}: {first_line(exc)} (an episodes .jsonl of `scenegen experiment perception-gap`)"
            )
    try:
        table = compare_episodes(*rows)
    except (KeyError, ValueError) as exc:
        return fail(f"{args.first} against {args.second}: {first_line(exc)}")
    lines = [
        "| measure | group | layouts | first | second | first - second (points) |",
        "|---|---|---|---|---|---|",
    ]
    for measure, groups in table.items():
        for name, c in groups.items():
            d = c["difference"]
            lines.append(
                f"| {measure} | {name} | {d['scenes']} | {c['first']:.3f} | {c['second']:.3f} | "
                f"{100 * d['mean']:+.1f} [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}] |"
            )
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "compare.json", json.dumps({"first": str(args.first), "second": str(args.second),
                                                        **table}, indent=1) + "\n")  # fmt: skip
    atomic_write(args.out / "compare.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"-> {args.out}")
    return 0
