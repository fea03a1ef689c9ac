"""The scene store: one directory per batch, written only by the coordinating process.

Layout of a batch ``OUT/``::

    pipeline.yaml       the resolved recipe (overrides applied)
    _assets/            every mesh and texture the scenes reference, once per batch
    scene_000012/       one accepted scene: scene.json (the record) and scene.xml (MJCF)
    index.jsonl         one row per accepted scene, in proposal-index order
    rejections.jsonl    one row per rejected proposal, keyed by proposal index
    manifest.yaml       the batch manifest (counts derived from the files above)
    timings.json        wall-clock time per stage (not part of the deterministic output)

Scenes are written to a temporary directory and renamed into place, so a scene directory is either
complete or absent.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from scenegen.schema.scene import Rejection, SceneRecord

ASSETS = "_assets"
INDEX = "index.jsonl"
REJECTIONS = "rejections.jsonl"


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@functools.lru_cache(maxsize=4096)
def source_sha256(path: str) -> str:
    """sha256 of a bundled mesh or texture file (cached: these files do not change during a run)."""
    return sha256_file(Path(path))


def asset_name(path: str) -> str:
    """Content-addressed name of a mesh or texture file inside ``_assets/``."""
    return f"{source_sha256(path)[:12]}_{Path(path).name}"


def scene_xml(
    spec: mujoco.MjSpec, qpos: np.ndarray, ctrl: np.ndarray, objects: dict
) -> tuple[str, dict[str, str]]:
    """MJCF of a settled scene, with mesh and texture files referenced inside ``../_assets/``.

    Free bodies are moved to their settled poses and keyframe 0 ``settled`` holds the full qpos and
    ctrl. ``objects`` maps body name -> qpos address. Returns (xml text, {asset file name: source path}).
    """
    for name, adr in objects.items():
        body = spec.body(name)
        body.pos = qpos[adr : adr + 3]
        body.quat = qpos[adr + 3 : adr + 7]
    for key in list(spec.keys):
        spec.delete(key)
    spec.add_key(name="settled", qpos=qpos, ctrl=ctrl)
    root = ET.fromstring(spec.to_xml())
    needed: dict[str, str] = {}
    for element in root.iter():
        if element.tag in ("mesh", "texture", "hfield", "skin") and element.get("file"):
            source = element.get("file")
            name = asset_name(source)
            needed[name] = source
            element.set("file", name)
    # to_xml() prints 6 significant digits (5 um at the table's height): write the settled state in full.
    exact = {name: (qpos[adr : adr + 3], qpos[adr + 3 : adr + 7]) for name, adr in objects.items()}
    for element in root.iter("body"):
        if element.get("name") in exact:
            pos, quat = exact[element.get("name")]
            element.set("pos", _floats(pos))
            element.set("quat", _floats(quat))
    for key in root.iter("key"):
        key.set("qpos", _floats(qpos))
        key.set("ctrl", _floats(ctrl))
    compiler = root.find("compiler")
    if compiler is None:
        compiler = ET.SubElement(root, "compiler")
        root.remove(compiler)
        root.insert(0, compiler)
    compiler.set("meshdir", f"../{ASSETS}/")
    compiler.set("texturedir", f"../{ASSETS}/")
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n", needed


def _floats(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def atomic_write(path: Path, data: bytes | str) -> None:
    """Write a file so that readers see the old content or the new one, never a part."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class BatchStore:
    """Writer of one batch directory."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def prepare(self, pipeline_yaml: str) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / ASSETS).mkdir(exist_ok=True)
        atomic_write(self.root / "pipeline.yaml", pipeline_yaml)

    def _ensure_assets(self, needed: dict[str, str]) -> None:
        for name, source in needed.items():
            dest = self.root / ASSETS / name
            if not dest.exists():
                tmp = dest.with_name(f".{name}.tmp")
                shutil.copyfile(source, tmp)
                os.replace(tmp, dest)

    def commit_scene(self, record: SceneRecord, xml: str, needed: dict[str, str]) -> SceneRecord:
        """Write one scene atomically and append its index row; returns the record with file hashes."""
        self._ensure_assets(needed)
        final = self.root / record.scene_id
        tmp = self.root / f".tmp_{record.scene_id}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        (tmp / "scene.xml").write_text(xml)
        files = {"scene.xml": sha256_file(tmp / "scene.xml")}
        files.update({f"../{ASSETS}/{n}": source_sha256(src) for n, src in sorted(needed.items())})
        record = record.model_copy(update={"files": files})
        text = record.model_dump_json(indent=1) + "\n"
        (tmp / "scene.json").write_text(text)
        os.replace(tmp, final)
        self._append(
            INDEX,
            {
                "scene_id": record.scene_id,
                "proposal_index": record.proposal_index,
                "target": record.target,
                "n_objects": len(record.objects),
                "scene_json_sha256": hashlib.sha256(text.encode()).hexdigest(),
            },
        )
        return record

    def log_rejection(self, rejection: Rejection) -> None:
        self._append(REJECTIONS, rejection.model_dump(mode="json"))

    def _append(self, name: str, row: dict) -> None:
        with open(self.root / name, "a") as f:
            f.write(json.dumps(row, sort_keys=True) + "\n")
            f.flush()
            os.fsync(f.fileno())


def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
