"""Stored scenes as WebDataset tar shards (``scenegen export BATCH --format webdataset --out DIR``).

One sample per accepted scene, its key the scene id: ``scene.json``, ``scene.xml`` and every image the
scene stored (``<cam>_rgb.png``, ``<cam>_depth.png``, ``<cam>_seg.png`` and a depth sensor's
``<cam>_depth_<sensor>.png``), byte for byte. The batch's
meshes and textures (its ``_assets/`` folder, referenced by every scene.xml as ``../_assets/``) go
once into ``assets-000000.tar``, one sample per file. A scene is rebuilt from the shards alone by
writing its ``scene.xml`` into ``<dir>/<scene_id>/`` and the asset samples into ``<dir>/_assets/``
(:func:`rebuild_scene`).

``export.json`` makes the export self-describing: its format, the source batch (path and the
checksum root of its manifest), counts, and the sha256 of every shard. The export is written into a
temporary folder beside ``out`` and renamed into place at the end: an interrupted export leaves no
``out``.
"""

from __future__ import annotations

import importlib.metadata
import json
import shutil
import tarfile
import tempfile
from collections.abc import Iterator
from pathlib import Path

from scenegen import __version__
from scenegen.core.files import OutsideRootError, confined, sha256_file
from scenegen.store.batch import ASSETS, StoreError, scene_dirs

EXPORT_FILE = "export.json"
SCENES_PER_SHARD = 100
SCENE_FILES = ("scene.json", "scene.xml")


class ExportError(ValueError):
    """An export that cannot be made; the message names the file and what to do."""


def _scene_sample(scene_dir: Path, batch: Path) -> dict:
    sample = {"__key__": scene_dir.name}
    for path in sorted(scene_dir.iterdir()):
        if path.is_file() and (path.name in SCENE_FILES or path.suffix == ".png"):
            sample[path.name] = _read_inside(path, batch)
    missing = [name for name in SCENE_FILES if name not in sample]
    if missing:
        raise ExportError(f"{scene_dir}: missing {', '.join(missing)}; is the batch complete?")
    return sample


def _read_inside(path: Path, batch: Path) -> bytes:
    """The bytes of a batch's file; ExportError when it leads out of the batch (a symlink)."""
    try:
        return confined(path, batch, "a file to export").read_bytes()
    except OutsideRootError as exc:
        raise ExportError(str(exc)) from None


def _asset_samples(assets: Path, batch: Path) -> Iterator[dict]:
    for path in sorted(assets.iterdir()):
        if path.name.count(".") != 1:  # WebDataset splits key and extension at the first dot
            raise ExportError(f"{path}: an asset name needs exactly one dot (key.ext) to be a sample")
        yield {"__key__": path.stem, path.suffix[1:]: _read_inside(path, batch)}


def _finished(out: Path, batch: Path, scenes_per_shard: int) -> dict | None:
    """The description of ``out`` when it is a complete export of this batch as it is now (same
    source, checksum root and shard size; every shard with its recorded digest), else None."""
    try:
        description = json.loads((out / EXPORT_FILE).read_text())
        same = description["source"] == {
            "batch": str(batch.resolve()),
            "checksum_root": _checksum_root(batch),
        }
        shards = description["shards"]
        size = description.get("scenes_per_shard", SCENES_PER_SHARD)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    names = {p.name for p in out.iterdir()}
    if not same or size != scenes_per_shard or names != {EXPORT_FILE, *shards}:
        return None
    if any(sha256_file(out / name) != digest for name, digest in shards.items()):
        return None
    return description


def export_webdataset(batch: Path, out: Path, scenes_per_shard: int = SCENES_PER_SHARD) -> dict:
    """Write ``batch``'s accepted scenes as shards into ``out`` (which must not exist or be empty);
    returns the export description (what ``export.json`` holds)."""
    import webdataset as wds

    batch, out = Path(batch), Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        done = _finished(out, batch, scenes_per_shard)
        if done is None:
            raise ExportError(f"{out}: exists and is not an empty folder; choose a new --out")
        return done  # the same export, already complete: a rerun is a no-op
    if scenes_per_shard < 1:
        raise ExportError(f"scenes_per_shard {scenes_per_shard}: must be at least 1")
    try:
        scenes = scene_dirs(batch)
    except StoreError as exc:
        raise ExportError(str(exc)) from None
    checksum_root = _checksum_root(batch)  # before anything is written: a broken manifest is an error
    rows = [row for row, _ in scenes]
    out.parent.mkdir(parents=True, exist_ok=True)
    for stale in out.parent.glob(f".{out.name}.tmp*"):  # left by an export that was killed
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp"))
    try:
        shards = str(tmp / "scenes-%06d.tar")
        with wds.ShardWriter(shards, maxcount=scenes_per_shard, verbose=0, mtime=0) as sink:  # no clock time
            for _, scene_dir in scenes:
                sink.write(_scene_sample(scene_dir, batch))
        assets = 0
        if (batch / ASSETS).is_dir():
            with wds.TarWriter(str(tmp / "assets-000000.tar"), mtime=0) as sink:
                for sample in _asset_samples(batch / ASSETS, batch):
                    sink.write(sample)
                    assets += 1
        description = {
            "format": "webdataset",
            "scenegen": __version__,
            "webdataset": importlib.metadata.version("webdataset"),
            "source": {"batch": str(batch.resolve()), "checksum_root": checksum_root},
            "counts": {"scenes": len(rows), "assets": assets},
            "scenes_per_shard": scenes_per_shard,
            "scene_ids": [row["scene_id"] for row in rows],
            "shards": {p.name: sha256_file(p) for p in sorted(tmp.glob("*.tar"))},
        }
        (tmp / EXPORT_FILE).write_text(json.dumps(description, indent=1) + "\n")
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return description


def _checksum_root(batch: Path) -> str | None:
    """The batch manifest's checksum root (None for a batch without a manifest); ExportError when
    the manifest cannot be read."""
    from scenegen.manifest import ManifestError, read_manifest

    if not (batch / "manifest.yaml").is_file():
        return None
    try:
        sources = read_manifest(batch / "manifest.yaml").sources
    except ManifestError as exc:
        raise ExportError(str(exc)) from None
    if not sources:
        raise ExportError(f"{batch / 'manifest.yaml'}: sources: empty (a batch manifest has one)")
    return getattr(sources[0].checksums, "root", None)


def _member_file(shard: Path, member: tarfile.TarInfo, name: str) -> str:
    """``name`` (a shard member's file name) when it is a plain file name; ExportError otherwise (a
    member named ``../x`` or ``/etc/x``, or a link, would write outside the folder it is rebuilt in)."""
    if not member.isfile() or "/" in name or "\\" in name or name in ("", ".", ".."):
        raise ExportError(f"{shard}: member {member.name[:80]!r} is not a plain file name; refused")
    return name


def rebuild_scene(export: Path, scene_id: str, into: Path) -> Path:
    """Write ``scene_id``'s files and the assets from the shards of ``export`` under ``into``; returns
    the scene folder (its scene.xml loads with ``mujoco.MjModel.from_xml_path``). Every member name is
    checked before anything is written: a member that would land outside ``into`` is an ExportError."""
    export, into = Path(export), Path(into)
    files: dict[Path, bytes] = {}
    with tarfile.open(export / "assets-000000.tar") as tar:
        for member in tar.getmembers():
            name = _member_file(export / "assets-000000.tar", member, member.name)
            files[into / ASSETS / name] = tar.extractfile(member).read()
    folder = None
    for shard in sorted(export.glob("scenes-*.tar")):
        with tarfile.open(shard) as tar:
            members = [m for m in tar.getmembers() if m.name.startswith(f"{scene_id}.")]
            if members:
                folder = into / scene_id
                for member in members:
                    name = _member_file(shard, member, member.name[len(scene_id) + 1 :])
                    files[folder / name] = tar.extractfile(member).read()
                break
    if folder is None:
        raise ExportError(f"{export}: no scene {scene_id!r} in its shards")
    for path, data in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return folder
