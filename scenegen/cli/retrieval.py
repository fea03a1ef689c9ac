"""Retrieval head commands: `retrieval train` (a category-conditioned target localiser trained on
scene sources mixed by the seed's recipe) and `retrieval eval` (its offline metrics per tag)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenegen.cli.common import add_device_argument, add_sensor_argument, device_error, fail, first_line

DEFAULT_CACHE = Path("runs/cache/frames")


def add_commands(sub) -> None:
    ret = sub.add_parser(
        "retrieval",
        help="train the retrieval head (RGB-D + category -> the target's pixels); measure it offline",
        description="The retrieval head finds the object of a requested category in the planner's "
        "RGB-D frames (front and side, 320x240), so the closed loop needs no simulator mask. Frames "
        "are rendered once per scene and cached by content (--cache).",
    )
    cmds = ret.add_subparsers(dest="retrieval_command", metavar="COMMAND", required=True)
    _add_train(cmds)
    _add_eval(cmds)


def _add_train(cmds) -> None:
    from scenegen.perception.retrieval.regions import DEPTH_RULES

    tr = cmds.add_parser(
        "train",
        help="train a retrieval head on scene sources (safetensors checkpoint)",
        description="Each --data source is a batch directory or a reference table; its first --limit "
        "feasible scenes are rendered (cached) and their segmentation gives the labels: every object's "
        "pixels under its category. Batches of scenes are drawn by the seed's mixture: real and "
        "reference sources weight 1, generated batches --alpha. Resumable: rerun the same command after "
        "an interruption.",
    )
    tr.add_argument(
        "--data", type=Path, nargs="+", required=True, help="batch directories or reference tables"
    )
    tr.add_argument("--out", type=Path, required=True, help="checkpoint folder")
    tr.add_argument("--limit", type=int, default=1000, help="scenes per source (default 1000)")
    tr.add_argument("--split", default="train", help="a table's split: train (default), heldout or all")
    tr.add_argument(
        "--shuffle",
        type=int,
        metavar="SEED",
        help="a table's training layouts in the seeded order of the transfer experiment's reference sets "
        "(20: the natural-rate set of the learning curves, docs/retrieval.md) before --limit",
    )
    tr.add_argument("--alpha", type=float, default=1.0, help="weight of the synthetic sources (default 1)")
    tr.add_argument(
        "--design",
        choices=("instances", "candidates", "segmenter"),
        default="instances",
        help="instances (default): regions split by a learned boundary map, named by a crop classifier; "
        "candidates: regions split where depth jumps by 4 cm (the design of issue 33); segmenter: a "
        "U-Net with a plane per category (docs/retrieval.md measures them)",
    )
    tr.add_argument(
        "--separator-steps",
        type=int,
        help="instances: training steps of the boundary network (default 3000; 12000 under the learned "
        "depth rule, whose separator also learns the object map: docs/sensor.md)",
    )
    tr.add_argument(
        "--steps",
        type=int,
        help="training steps (default: the crop classifier of instances and candidates 6000 batches of 64 "
        "crops, segmenter 2000)",
    )
    tr.add_argument(
        "--batch-size", type=int, default=8, help="segmenter: scenes per step, each with both cameras"
    )
    tr.add_argument(
        "--width",
        type=int,
        default=8,
        help="segmenter, and the instances design's separator: channels of the first level (default 8)",
    )
    tr.add_argument(
        "--depth-rule",
        choices=tuple(DEPTH_RULES),
        help="instances: how the region step reads depth (regions.DEPTH_RULES; default: exact for exact "
        "depth, the sensor's rule through a sensor, docs/sensor.md); saved in the checkpoint and applied "
        "wherever it is used",
    )
    tr.add_argument("--seed", type=int, default=0)
    add_device_argument(tr)
    _common(tr)
    tr.set_defaults(run=retrieval_train)


def _add_eval(cmds) -> None:
    ev = cmds.add_parser(
        "eval",
        help="per-tag IoU, hit, wrong-object, miss and false-alarm rates of a retrieval head",
        description="Predicts the target of each scene in both cameras and scores it against the "
        "simulator's segmentation: IoU with the true target mask, hit (the predicted region's centre "
        "on the target), wrong object (most of it on another object), miss (nothing predicted where "
        "the target is visible). Writes images.jsonl, summary.json and summary.md under --out.",
    )
    ev.add_argument("--checkpoint", type=Path, required=True)
    ev.add_argument(
        "--scenes",
        type=Path,
        required=True,
        help="batch directory, reference table, or a version 2 panels file (assets/panels/v2/panels.json)",
    )
    ev.add_argument("--split", default="heldout", help="a table's split (default heldout)")
    ev.add_argument(
        "--side", choices=("validation", "test"), default="validation", help="a panels file's side"
    )
    ev.add_argument("--limit", type=int, help="only the first N selected scenes")
    ev.add_argument(
        "--select",
        choices=("all", "nominal", "rare"),
        default="all",
        help="which scenes (default all); from a table or batch, version 2 panel layouts are always left "
        "out (rare and all: both sides; nominal: the test side), and it says so",
    )
    ev.add_argument(
        "--unique-category",
        action="store_true",
        help="only scenes holding one object of the target's category",
    )
    ev.add_argument("--out", type=Path, required=True, help="folder for the metrics")
    _common(ev)
    ev.set_defaults(run=retrieval_eval)


def _common(parser) -> None:
    parser.add_argument(
        "--cache",
        type=Path,
        default=DEFAULT_CACHE,
        help=f"rendered frames, by content (default {DEFAULT_CACHE})",
    )
    parser.add_argument("--workers", type=int, default=1, help="rendering processes (default 1)")
    add_sensor_argument(parser, "the frames' depth, cached apart per sensor (default exact)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _scenes(source: Path, split: str, limit: int | None, shuffle: int | None = None):
    from scenegen.env.scenes import load_scenes
    from scenegen.manipulation.task import feasible

    if shuffle is not None:
        if source.suffix != ".parquet" or split != "train":
            raise ValueError(
                f"--shuffle: orders a table's training split; {source} (split {split}) is not one"
            )
        from scenegen.core.files import load_rows
        from scenegen.env.scenes import reference_scene
        from scenegen.experiment.transfer_sources import choose_reference_sets

        rows = load_rows(source, "train")
        n = min(limit or len(rows), sum(not r["tag_on_floor"] for r in rows))
        order = choose_reference_sets(rows, n, n, 0, shuffle).a  # the natural-rate prefix of that order
        by_index = {r["index"]: r for r in rows}
        return [reference_scene(by_index[i], source.stem) for i in order]
    scenes = [s for s in load_scenes(source, None if split == "all" else split) if feasible(s)]
    return scenes[:limit] if limit is not None else scenes


def retrieval_train(args: argparse.Namespace) -> int:
    import torch

    from scenegen.assets.catalog import load_catalog
    from scenegen.core.files import sha256_file
    from scenegen.perception.retrieval.frames import scene_frames
    from scenegen.perception.retrieval.train import retrieval_data, train_head

    if args.steps is None:
        args.steps = 2000 if args.design == "segmenter" else 6000
    counts = (args.steps, args.batch_size, args.limit, args.workers, args.separator_steps or 1)
    if min(counts) < 1 or args.alpha < 0:
        return fail(
            "--steps, --separator-steps, --batch-size, --limit and --workers must be at least 1, --alpha at "
            "least 0"
        )
    if not 2 <= args.width <= 64:
        return fail("--width must lie between 2 and 64")
    if args.depth_rule not in (None, "exact") and args.design != "instances":
        return fail(
            f"--depth-rule {args.depth_rule}: only the instances design has a region step's depth rule"
        )
    if (problem := device_error(args)) is not None:
        return fail(problem)
    try:
        scenes = [s for source in args.data for s in _scenes(source, args.split, args.limit, args.shuffle)]
    except (OSError, ValueError, KeyError) as exc:  # KeyError: a table without a reference column
        return fail(first_line(exc))
    if not scenes:
        return fail(f"--data {' '.join(map(str, args.data))}: no feasible scene in split {args.split}")
    torch.set_num_threads(1)  # the budget is CPU seconds: one thread wastes none (and fixes the bytes)
    frames = scene_frames(scenes, args.cache, args.workers, progress=not args.quiet, sensor=args.sensor)
    categories = list(load_catalog().categories)
    described = {
        "sources": [
            {"path": str(p), **({"sha256": sha256_file(p)} if p.is_file() else {})} for p in args.data
        ],
        "split": args.split,
        "limit": args.limit,
        **({"shuffle": args.shuffle} if args.shuffle is not None else {}),
        **({"sensor": args.sensor} if args.sensor != "exact" else {}),  # exact: as before sensors
    }
    if args.design in ("candidates", "instances"):
        from scenegen.perception.retrieval.candidates import train_classifier, train_instances

        common = {"alpha": args.alpha, "description": described, "device": args.device}
        if args.design == "instances":
            from scenegen.perception.retrieval.regions import DEPTH_RULES, rule_name_for

            extra = {"progress": not args.quiet, "separator_steps": args.separator_steps}
            if args.width != 8:
                extra["width"] = args.width
            rule = args.depth_rule or rule_name_for(args.sensor)
            if rule != "exact":  # exact's call stays as it was (a retrained default keeps its bytes)
                extra["rule"] = DEPTH_RULES[rule]
            frames, train = list(frames), train_instances
        else:  # the call of issue 33, so a retrained baseline keeps its bytes
            extra, train = {}, train_classifier
        summary = train(scenes, frames, categories, args.out, args.steps, args.seed, **common, **extra)
        print(
            f"{summary['scenes']} scenes ({summary['candidates']} candidates), {args.steps} steps: loss "
            f"{_mean(summary['losses'][:20]):.4f} -> {_mean(summary['losses'][-20:]):.4f} "
            f"({summary['cpu_seconds']} CPU-s) -> {args.out}"
        )
        return 0
    summary = train_head(
        retrieval_data(scenes, frames, categories),
        args.out,
        steps=args.steps,
        batch_size=args.batch_size,
        alpha=args.alpha,
        seed=args.seed,
        width=args.width,
        description=described,
        progress=not args.quiet,
        device=args.device,
    )
    print(
        f"{summary['scenes']} scenes ({summary['images']} images), {args.steps} steps: loss "
        f"{_mean(summary['losses'][:20]):.4f} -> {_mean(summary['losses'][-20:]):.4f} "
        f"({summary['cpu_seconds']} CPU-s) -> {args.out}"
    )
    return 0


def _mean(values) -> float:
    return sum(values) / max(len(values), 1)


def held_out(scenes: list, select: str) -> tuple[list, str]:
    """The layouts of a table or batch that ``retrieval eval --select`` reports on, and what it says
    it left out. Held-out figures never include a layout of the version 2 test panels; rare and all
    selections leave out the validation side too (its rare layouts are what transfer version 2
    pilots on); a nominal selection keeps the validation side's common layouts, which are the
    head's validation set of issue 33 (the first 300 unique-category nominal held-out layouts,
    docs/retrieval.md)."""
    from scenegen.policy.panels import outside_panels

    if select != "all":
        scenes = [s for s in scenes if bool(s.tags.get("nominal")) == (select == "nominal")]
    sides = ("test",) if select == "nominal" else ("test", "validation")
    kept = outside_panels(scenes, sides, version1=False)
    if len(kept) == len(scenes):
        return kept, ""
    where = " and ".join(sides) + (" sides" if len(sides) > 1 else " side")
    return kept, f"left out {len(scenes) - len(kept)} layouts of the version 2 panels ({where})"


def retrieval_eval(args: argparse.Namespace) -> int:
    from scenegen.core.files import CheckpointError
    from scenegen.env.scenes import unique_category
    from scenegen.perception.retrieval.evaluate import evaluate_head, summary_table
    from scenegen.perception.retrieval.frames import scene_frames
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    if args.workers < 1 or (args.limit is not None and args.limit < 1):
        return fail("--workers and --limit must be at least 1")
    try:
        RetrievalPerception.load(args.checkpoint)
        if args.scenes.suffix == ".json":
            from scenegen.policy.panels_v2 import load_panels_v2, panel_id, panel_scenes

            panel = panel_scenes(load_panels_v2(args.scenes), args.side)
            scenes = list({panel_id(s): s for ss in panel.values() for s in ss}.values())
        else:
            scenes = _scenes(args.scenes, args.split, None)
    except (CheckpointError, OSError, ValueError, KeyError) as exc:
        return fail(first_line(exc))
    if args.scenes.suffix != ".json":
        scenes, said = held_out(scenes, args.select)
        if said:
            print(said, file=sys.stderr)
    elif args.select != "all":
        scenes = [s for s in scenes if bool(s.tags.get("nominal")) == (args.select == "nominal")]
    if args.unique_category:
        scenes = [s for s in scenes if unique_category(s)]
    scenes = scenes[: args.limit] if args.limit is not None else scenes
    if not scenes:
        return fail(f"--scenes {args.scenes}: no scene left after the selection")
    frames = list(scene_frames(scenes, args.cache, args.workers, progress=not args.quiet, sensor=args.sensor))
    try:
        summary = evaluate_head(args.checkpoint, scenes, frames, args.out, sensor=args.sensor)
    except ValueError as exc:  # a category the head does not know
        return fail(first_line(exc))
    print(summary_table(summary), end="")
    print(f"-> {args.out}")
    return 0
