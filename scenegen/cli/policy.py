"""Policy commands: `label` (expert labels: every primitive from every scene's settled state) and
`success-table` (success per tag x primitive from those labels), `policy train|eval`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenegen.cli.common import add_backend_arguments, backend_from, fail, first_line, physics_from
from scenegen.perception.retrieval import DEFAULT_HEAD


def add_commands(sub) -> None:
    _add_label(sub)
    _add_success_table(sub)
    _add_policy(sub)


def _add_label(sub) -> None:
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
    lab.add_argument("--limit", type=int, help="label only the first N feasible scenes")
    lab.add_argument(
        "--outside-panels",
        action="store_true",
        help="leave out the transfer experiment's panel layouts (version 1 and both sides of version 2)",
    )
    lab.add_argument(
        "--per-tag", type=int, help="only the first N scenes holding each rare tag and N nominal ones"
    )
    lab.add_argument(
        "--per-cell",
        type=int,
        metavar="N",
        help="only the first N scenes of each (tag, target category) cell of --categories",
    )
    lab.add_argument("--categories", nargs="+", help="target categories for --per-cell (e.g. can mug box)")
    lab.add_argument(
        "--unique-category", action="store_true", help="only scenes with one object of the target's category"
    )
    lab.add_argument(
        "--until-solved",
        action="store_true",
        help="stop each scene at its first success, primitives tried in the cheapest order (or --primitives' "
        "order): enough to say which scenes some primitive solves (panels), at about half the rows",
    )
    lab.add_argument("--workers", type=int, default=1, help="processes or Ray actors (default 1)")
    add_backend_arguments(lab)
    lab.add_argument(
        "--observation",
        choices=("rgbd", "state"),
        default="rgbd",
        help="what the planners see: camera frames (default) or the simulator's state (the ablation)",
    )
    _add_physics(lab)
    lab.add_argument("--quiet", action="store_true", help="no progress bar")
    lab.set_defaults(run=label)


def _add_physics(parser, reads: bool = False) -> None:
    # names only: importing the settings would load MuJoCo before the CLI has checked MUJOCO_GL
    what = (
        "whose label rows to read: those simulated under this physics (default: the default, dt5; "
        "the committed stores of assets/policy/labels are exact's)"
        if reads
        else "what the primitives are simulated under: a name of the control loop's physics settings "
        "(default: its default, dt5; docs/env.md 'The physics'); stored rows say theirs, and rows "
        "of another physics are not reused"
    )
    parser.add_argument("--physics", metavar="NAME", help=what)


def _add_success_table(sub) -> None:
    tab = sub.add_parser(
        "success-table",
        help="success of each primitive per rare tag (and tag x category) from expert labels",
        description="Markdown table of success rate, 95 %% Wilson interval and scenes per tag x primitive "
        "(best per tag in bold) and per (tag, target category) cell with enough scenes, then the cells "
        "whose best primitive beats nominal's best of the same category by 15 points or more.",
    )
    tab.add_argument(
        "labels", type=Path, nargs="+", help="labels Parquet files written by `scenegen label` (combined)"
    )
    tab.add_argument(
        "--observation",
        choices=("rgbd", "state"),
        default="rgbd",
        help="whose rows to count: the cameras' (default) or the state ablation's; never both",
    )
    tab.add_argument("--min-cell", type=int, default=30, help="scenes a (tag, category) cell needs (30)")
    _add_physics(tab, reads=True)
    tab.set_defaults(run=success_table)


def _add_policy(sub) -> None:
    pol = sub.add_parser(
        "policy", help="train the baseline policy on labelled sources; evaluate it in closed loop"
    )
    cmds = pol.add_subparsers(dest="policy_command", metavar="COMMAND", required=True)
    tr = cmds.add_parser(
        "train",
        help="train the primitive-choosing CNN on labelled sources (safetensors checkpoint)",
        description="Each --data pair is a scene source (batch or reference table) and its `scenegen "
        "label` output. Examples are the front camera's RGB-D + target mask at the settled state; "
        "batches are drawn by the seed's mixture: real/reference sources weight 1, batches alpha.",
    )
    tr.add_argument(
        "--data", nargs=2, action="append", type=Path, metavar=("SCENES", "LABELS"), required=True
    )
    tr.add_argument("--out", type=Path, required=True, help="checkpoint folder")
    tr.add_argument("--steps", type=int, default=500)
    tr.add_argument("--batch-size", type=int, default=32)
    tr.add_argument("--alpha", type=float, default=1.0, help="weight of the synthetic sources (default 1)")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--quiet", action="store_true", help="no progress bars")
    tr.add_argument("--split", default="train", help="a table's split: train (default), heldout or all")
    _add_physics(tr, reads=True)
    tr.set_defaults(run=policy_train)
    ev = cmds.add_parser(
        "eval",
        help="run a policy in closed loop on scenes: episodes with traces and failure labels",
        description="Observe, choose, execute, re-observe, up to 3 attempts per scene; one episode folder "
        "per scene under --out and summary.json (success rate, failure labels).",
    )
    ev.add_argument("--checkpoint", type=Path, help="the chooser over the hand planners (a policy folder)")
    ev.add_argument(
        "--proposals",
        type=Path,
        metavar="MODEL",
        help="act by a proposal model instead of --checkpoint (scenegen proposals train; e.g. "
        "assets/proposals/natural600): candidates sampled from what the robot sees, the best executed; "
        "writes episodes.jsonl and summary.json",
    )
    ev.add_argument("--scenes", type=Path, required=True, help="batch directory or reference table")
    ev.add_argument("--split", default="heldout", help="a table's split (default heldout)")
    ev.add_argument("--n", type=int, default=50, help="scenes to run (default 50)")
    ev.add_argument(
        "--outside-panels",
        action="store_true",
        help="skip the transfer experiment's panel layouts (version 1 and both sides of version 2)",
    )
    ev.add_argument("--labels", type=Path, help="expert labels of these scenes (for grasp-choice failures)")
    ev.add_argument(
        "--retrieval",
        default=str(DEFAULT_HEAD),
        help="the retrieval head checkpoint the policy sees through, no simulator mask at decision time "
        "(default assets/retrieval/instances; issue 33's was assets/retrieval/baseline), or `oracle`: the "
        "simulator's instance masks, the ceiling",
    )
    ev.add_argument("--out", type=Path, required=True, help="folder for the episodes and summary.json")
    _add_physics(ev)
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(run=policy_eval)


def label(args: argparse.Namespace) -> int:
    from scenegen.policy.labels import LabelError, label
    from scenegen.runner.executors import BackendError

    try:
        backend = backend_from(args)
    except BackendError as exc:
        return fail(str(exc))
    if args.workers < 1 or any(v is not None and v < 1 for v in (args.limit, args.per_tag)):
        return fail("--workers, --limit and --per-tag must be at least 1")
    if (args.per_cell is None) != (args.categories is None):
        return fail("--per-cell N and --categories go together: name the categories whose cells to fill")
    if args.per_cell is not None and args.per_cell < 1:
        return fail("--per-cell must be at least 1")
    from scenegen.runner.executors import backend_session

    try:
        with backend_session(backend, args.workers):
            stats = label(
                args.scenes,
                args.out,
                primitives=args.primitives,
                split=None if args.split == "all" else args.split,
                limit=args.limit,
                workers=args.workers,
                progress=not args.quiet,
                per_tag=args.per_tag,
                observation=args.observation,
                per_cell=(args.per_cell, args.categories) if args.per_cell is not None else None,
                outside_panels=args.outside_panels,
                backend=backend,
                unique=args.unique_category,
                until_solved=args.until_solved,
                **({"physics": args.physics} if args.physics else {}),
            )
    except (LabelError, OSError, BackendError) as exc:
        return fail(first_line(exc))
    print(f"{stats['rows']} rows ({stats['ran']} run, {stats['reused']} reused) -> {stats['out']}")
    return 0


def success_table(args: argparse.Namespace) -> int:
    import pyarrow.parquet as pq

    from scenegen.policy.labels import current_rows
    from scenegen.policy.success_table import differs_from_nominal, markdown_table

    tables = []
    for path in args.labels:
        try:
            tables.append(pq.read_table(path).to_pylist())
        except (OSError, ValueError) as exc:
            return fail(f"{path}: not a labels Parquet file ({first_line(exc)})")
    try:
        rows, stale = current_rows(tables, args.observation, physics_from(args))
    except ValueError as exc:
        return fail(f"--physics {first_line(exc)}")
    except KeyError as exc:
        return fail(f"{', '.join(map(str, args.labels))}: not labels written by `scenegen label` (no {exc})")
    if stale:
        print(
            f"left out {stale} rows of older primitive versions, another observation kind or another "
            f"physics (relabel with `scenegen label`: it reuses the current rows; or name --physics)",
            file=sys.stderr,
        )
    if not rows:
        named = ", ".join(map(str, args.labels))
        return fail(
            f"{named}: no rows of the current primitives ({args.observation} observation, "
            f"{physics_from(args)} physics); rows of another physics: name it with --physics"
        )
    print(markdown_table(rows, args.min_cell))
    found = differs_from_nominal(rows, args.min_cell)
    print(f"{len(found)} (tag, category) cells whose best primitive beats nominal's best by >= 15 points:")
    for f in found:
        print(
            f"  {f['tag']} / {f['category']}: {f['best']} {f['best_rate']:.2f} vs "
            f"{f['nominal_best']} {f['nominal_best_rate_here']:.2f} (n={f['scenes']})"
        )
    return 0


def policy_train(args: argparse.Namespace) -> int:
    from scenegen.policy.train import data_description, labelled_examples, train_policy

    if args.steps < 1 or args.batch_size < 1 or args.alpha < 0:
        return fail("--steps and --batch-size must be at least 1, --alpha at least 0")
    split = None if args.split == "all" else args.split
    try:
        physics = physics_from(args)
    except ValueError as exc:
        return fail(f"--physics {first_line(exc)}")
    try:
        examples = labelled_examples(
            [tuple(pair) for pair in args.data], split, progress=not args.quiet, physics=physics
        )
    except (OSError, ValueError) as exc:
        return fail(first_line(exc))
    summary = train_policy(
        examples,
        args.out,
        args.steps,
        args.batch_size,
        args.alpha,
        args.seed,
        data=data_description(args.data),
        progress=not args.quiet,
    )
    first, last = summary["losses"][:20], summary["losses"][-20:]
    print(
        f"{summary['examples']} examples, {args.steps} steps: loss {sum(first) / len(first):.4f} -> "
        f"{sum(last) / len(last):.4f} ({summary['cpu_seconds']} CPU-s) -> {args.out}"
    )
    return 0


def _eval_proposals(args: argparse.Namespace, scenes) -> int:
    from scenegen.core.files import CheckpointError
    from scenegen.experiment.proposal_loop import evaluate_scenes
    from scenegen.policy.proposal_model import ProposalModel

    if args.labels is not None:
        return fail("--labels: the proposal model's episodes have no grasp-choice failures to label")
    try:
        ProposalModel.load(args.proposals)
        physics = physics_from(args)
    except (CheckpointError, OSError, ValueError) as exc:
        return fail(first_line(exc))
    if not scenes:
        return fail("no feasible scene to evaluate (targets on the floor are out of reach)")
    retrieval = None if str(args.retrieval) == "oracle" else Path(args.retrieval)
    summary = evaluate_scenes(args.proposals, scenes, args.out, retrieval, physics, not args.quiet)
    low, high = summary["interval"]
    print(
        f"{summary['episodes']} episodes, success {summary['success']:.2%} [{low:.2%}, {high:.2%}], "
        f"first attempt {summary['first_attempt']:.2%}, failures {summary['failures']} -> {args.out}"
    )
    return 0


def policy_eval(args: argparse.Namespace) -> int:
    from scenegen.env.scenes import load_scenes

    if (args.checkpoint is None) == (args.proposals is None):
        return fail(
            "policy eval: give --checkpoint (the chooser) or --proposals (a proposal model), one of them"
        )
    from scenegen.manipulation.task import feasible
    from scenegen.policy.evaluate import evaluate

    try:
        scenes = load_scenes(args.scenes, None if args.split == "all" else args.split)
        if args.outside_panels:
            from scenegen.policy.panels import outside_panels

            scenes = outside_panels(scenes)
        scenes = [s for s in scenes if feasible(s)]  # on_floor targets are out of reach: not counted
        if args.proposals is not None:
            return _eval_proposals(args, scenes[: args.n])
        summary = evaluate(
            args.checkpoint,
            scenes[: args.n],
            args.out,
            args.labels,
            not args.quiet,
            args.retrieval,
            **({"physics": args.physics} if args.physics else {}),
        )
    except (OSError, ValueError) as exc:
        return fail(first_line(exc))
    print(
        f"{summary['episodes']} episodes ({summary['perception']} perception), "
        f"success {summary['success_rate']:.2%}, "
        f"failures {summary['failures']}"
    )
    return 0
