"""`scenegen export`: stored scenes as WebDataset shards, episodes as a LeRobot dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import fail, first_line

FORMATS = ("webdataset", "lerobot")


def add_commands(sub) -> None:
    ex = sub.add_parser(
        "export",
        help="write scenes as WebDataset shards or episodes as a LeRobot dataset",
        description="webdataset: SOURCE is a batch directory; one sample per accepted scene (scene.json, "
        "scene.xml, images) in scenes-NNNNNN.tar, the batch's meshes once in assets-000000.tar, and "
        "export.json (source batch, counts, shard checksums). lerobot: SOURCE is a folder of episode "
        "folders (episode.json + arrays.npz, scenegen.env.episodes) or one episode folder; written "
        "through lerobot's LeRobotDataset.create (install it with `make install-exporters`). The "
        "output appears only when complete.",
    )
    ex.add_argument("source", type=Path, help="batch directory (webdataset) or episodes folder (lerobot)")
    ex.add_argument("--format", choices=FORMATS, required=True)
    ex.add_argument("--out", type=Path, required=True, help="output folder (must not exist, or be empty)")
    ex.add_argument(
        "--scenes-per-shard", type=int, default=100, help="webdataset: scenes per tar shard (default 100)"
    )
    ex.add_argument("--repo-id", default="scenegen/episodes", help="lerobot: the dataset's repo id")
    ex.set_defaults(run=export)


def export(args: argparse.Namespace) -> int:
    if args.format == "webdataset":
        return _webdataset(args)
    return _lerobot(args)


def _webdataset(args: argparse.Namespace) -> int:
    try:
        import webdataset  # noqa: F401
    except ImportError:
        return fail("--format webdataset needs the webdataset package: pip install 'scenegen[export]'")
    from scenegen.export.scene_shards import ExportError, export_webdataset

    try:
        description = export_webdataset(args.source, args.out, args.scenes_per_shard)
    except (ExportError, OSError) as exc:
        return fail(first_line(exc))
    counts = description["counts"]
    print(
        f"{counts['scenes']} scenes in {len(description['shards']) - (counts['assets'] > 0)} shard(s), "
        f"{counts['assets']} assets -> {args.out}"
    )
    return 0


def _lerobot(args: argparse.Namespace) -> int:
    from scenegen.export.lerobot import ExporterMissing, export_lerobot

    source = args.source
    folders = (
        [source]
        if (source / "episode.json").is_file()
        else sorted(p for p in source.glob("*") if (p / "episode.json").is_file())
    )
    if not folders:
        return fail(f"{source}: no episode folders (episode.json + arrays.npz) in it")
    try:
        summary = export_lerobot(folders, args.out, repo_id=args.repo_id)
    except ExporterMissing as exc:
        return fail(first_line(exc))
    except (ValueError, OSError) as exc:
        return fail(first_line(exc))
    print(f"{summary['episodes']} episodes, {summary['frames']} frames -> {args.out}")
    return 0
