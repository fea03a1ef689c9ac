"""`scenegen generate` and `scenegen show`: a batch of scenes, and its contact sheet."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from scenegen.cli.common import add_backend_arguments, add_sensor_argument, backend_from, fail

TRIES_PER_SCENE = 50  # the default try cap: this many tries (repairs included) per scene asked for


def request_folder(text: str) -> str:
    """The folder a request's batch goes to by default: its words, lower case, joined by ``_``
    (``"retrieve the mug, not clutter"`` -> ``retrieve_the_mug_not_clutter``), at most 80 characters."""
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")[:80].rstrip("_") or "request"


def add_commands(sub) -> None:
    """The ``generate`` and ``show`` subcommands."""
    gen = sub.add_parser(
        "generate",
        help="generate a batch of verified scenes from a pipeline recipe",
        description="Generate a batch: propose, check, settle and store scenes until --n are accepted.",
    )
    gen.add_argument("pipeline", type=Path, help="pipeline YAML, e.g. pipelines/demo.yaml")
    gen.add_argument("--n", type=int, help="accepted scenes wanted (overrides the recipe's n)")
    gen.add_argument("--seed", type=int, help="batch seed (overrides the recipe's seed)")
    gen.add_argument("--max-proposals", type=int, help="give up after this many proposals (default 40 x n)")
    gen.add_argument(
        "--max-tries",
        type=int,
        help="give up after this many tries: every candidate checked, repairs included (default: the "
        f"recipe's max_tries, else {TRIES_PER_SCENE} x n)",
    )
    gen.add_argument(
        "--out",
        type=Path,
        help="output directory (default runs/<name>, or runs/requests/<name>/<the request's words> with "
        "--request); the same command on a killed batch resumes it",
    )
    gen.add_argument(
        "--request",
        metavar="TEXT",
        help="the request, laid over the recipe's condition, e.g. \"retrieve the mug near edge, not "
        "clutter\" (tags named are required, 'not TAG' forbidden; docs/conditions.md)",
    )
    gen.add_argument(
        "--proposer",
        choices=("diffusion", "procedural", "targeted"),
        help="proposer kind instead of the recipe's (keeps its shared settings): diffusion = the trained "
        "generator (assets/generator); procedural = rejection sampling from the recipe's distributions; "
        "targeted = hand-written rules per required tag",
    )
    gen.add_argument(
        "--workers", type=int, default=1, help="processes (or Ray actors) for check/settle/render (default 1)"
    )
    add_backend_arguments(gen)
    gen.add_argument("--no-render", action="store_true", help="skip rendering (no GL needed; no sensor)")
    add_sensor_argument(
        gen,
        "a depth sensor's frames stored beside the exact depth, <cam>_depth_<sensor>.png, instead of "
        "the recipe's sensor (whose default, exact, stores none)",
        default=None,
    )
    gen.add_argument(
        "--check",
        action="store_true",
        help="only validate: read the recipe (request, overrides and proposer applied), load its "
        "generator checkpoint, print what would run; writes nothing",
    )
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.set_defaults(run=generate)

    show = sub.add_parser(
        "show",
        help="write a contact sheet PNG of a batch",
        description="Contact sheet of a batch: RGB thumbnails labelled with scene id, target and tags.",
    )
    show.add_argument("batch", type=Path, help="batch directory written by `scenegen generate`")
    show.add_argument("--out", type=Path, help="PNG to write (default BATCH/contact_sheet.png)")
    show.add_argument("--camera", help="camera name (default: the first camera of each scene)")
    show.add_argument("--depth", action="store_true", help="add depth beside each RGB thumbnail")
    show.add_argument("--seg", action="store_true", help="add segmentation beside each RGB thumbnail")
    show.add_argument("--max", type=int, default=24, help="at most this many scenes (default 24)")
    show.add_argument("--columns", type=int, default=4, help="thumbnails per row (default 4)")
    show.set_defaults(run=show_batch)


def generate(args: argparse.Namespace) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.runner.config import ConfigError, load_pipeline
    from scenegen.runner.executors import BackendError

    overrides = {"n": args.n, "seed": args.seed, "max_proposals": args.max_proposals}
    overrides["max_tries"] = args.max_tries
    if args.sensor:
        overrides["sensor"] = args.sensor
    if args.no_render:
        overrides |= {"render": False, "sensor": "exact"}
    if args.workers < 1:
        return fail(f"--workers {args.workers}: must be at least 1")
    try:
        backend = backend_from(args)
        config = load_pipeline(args.pipeline, overrides, request=args.request, proposer=args.proposer)
        if config.max_tries is None:
            overrides["max_tries"] = TRIES_PER_SCENE * config.n
            config = load_pipeline(args.pipeline, overrides, request=args.request, proposer=args.proposer)
    except (ConfigError, CatalogError, BackendError) as exc:
        return fail(str(exc))
    if config.proposer.kind == "diffusion":
        from scenegen.propose.diffusion import load_generator

        try:
            load_generator(config.proposer)  # a checkpoint that does not load fails before any file
        except ValueError as exc:
            return fail(str(exc))
    out = args.out or Path("runs") / config.name
    if args.out is None and args.request:  # beside the recipe's own batch, never inside it
        out = Path("runs") / "requests" / config.name / request_folder(args.request)
    if args.check:
        tags = ", ".join(f"{t}={v}" for t, v in config.condition.tags.items() if v != "unspecified") or "none"
        print(
            f"{args.pipeline}: valid. {config.n} scenes of {config.condition.task} {config.condition.target} "
            f"(tags: {tags}) by the {config.proposer.kind} proposer, seed {config.seed}, at most "
            f"{config.max_tries} tries, render {'on' if config.render else 'off'} -> {out}"
        )
        return 0
    if config.render:
        from scenegen.render.offscreen import gl_problem

        problem = gl_problem()
        if problem:
            return fail(problem)

    from scenegen.runner.executors import backend_session
    from scenegen.runner.pipeline import run_batch
    from scenegen.store.batch import StoreError

    try:
        with backend_session(backend, args.workers):
            summary = run_batch(config, out, workers=args.workers, progress=not args.quiet, backend=backend)
    except (StoreError, BackendError) as exc:
        return fail(str(exc))
    report_batch(summary, config, out)
    return 0 if summary.accepted >= config.n else 1


def report_batch(summary, config, out: Path) -> None:
    """What ``generate`` prints at the end: scenes of tries, rejections, stage seconds; on stderr the
    cap that stopped a short batch, and the realism hint wherever ``unrealistic`` leads the
    rejections."""
    rejected = sum(summary.rejections.values())
    tries = summary.proposals  # every candidate checked: accepted plus every logged rejection
    print(f"{summary.accepted} scenes accepted of {tries} tries in {summary.wall:.1f} s -> {out}")
    if rejected:
        print("rejections: " + ", ".join(f"{k} {v}" for k, v in summary.rejections.most_common()))
    print("stage seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in summary.seconds.items()))
    if summary.accepted < config.n:
        capped = config.max_tries is not None and tries >= config.max_tries
        cap = (
            f"try cap ({config.max_tries} tries); raise --max-tries"
            if capped
            else f"proposal cap ({config.proposal_cap} first tries); raise --max-proposals"
        )
        print(
            f"scenegen: warning: only {summary.accepted} of {config.n} scenes accepted in {tries} tries, "
            f"stopped by the {cap} or relax the request",
            file=sys.stderr,
        )
    if rejected and summary.rejections.most_common(1)[0][0] == "unrealistic":
        print(
            f"scenegen: {summary.rejections['unrealistic']} of {rejected} rejections are unrealistic, the "
            "most common: the scenes asked for lie far from every reference layout (e.g. a combination "
            "the reference never shows); lower the recipe's realism.min_score or leave realism out to "
            "get them",
            file=sys.stderr,
        )


def show_batch(args: argparse.Namespace) -> int:
    from scenegen.analysis.contact_sheet import SheetError, contact_sheet

    try:
        path = contact_sheet(
            args.batch,
            args.out,
            camera=args.camera,
            depth=args.depth,
            seg=args.seg,
            limit=args.max,
            columns=args.columns,
        )
    except SheetError as exc:
        return fail(str(exc))
    print(path)
    return 0


# Values mujoco accepts for MUJOCO_GL on Linux (mujoco/gl_context.py); anything else fails at import.
