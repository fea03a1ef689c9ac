"""The scene store: one directory per batch, written only by the coordinating process.

Layout of a batch ``OUT/``::

    pipeline.yaml       the resolved recipe (overrides applied)
    _assets/            every mesh and texture the scenes reference, once per batch
    scene_000012/       one accepted scene: scene.json (the record) and scene.xml (MJCF)
    index.jsonl         one row per accepted scene, in proposal-index order
    rejections.jsonl    one row per rejected proposal, keyed by proposal index
    manifest.yaml       the batch manifest (counts derived from the files above)
    timings.json        wall and CPU time per stage, summed over the batch's finished runs, each run
                        listed (not part of the deterministic output)

Three views may be written into it later, by default: ``contact_sheet.png`` (``scenegen show``),
``coverage.png`` (``scenegen coverage``) and ``report.html`` with its thumbnails in ``report_files/``
(``scenegen report``); they are not part of the data. ``scenegen audit`` refuses anything else
(scenegen/audit/files.py).

Scenes are written to a temporary directory and renamed into place, so a scene directory is either
complete or absent.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import shutil
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from scenegen.core.files import SCENE_ID, OutsideRootError, confined, sha256_file
from scenegen.schema.scene import Rejection, SceneRecord

ASSETS = "_assets"
INDEX = "index.jsonl"
REJECTIONS = "rejections.jsonl"
MANIFEST = "manifest.yaml"
TIMINGS = "timings.json"
REPORT = "report.html"  # scenegen report: a view, not data
REPORT_FILES = "report_files"  # its thumbnails


@functools.lru_cache(maxsize=4096)
def source_sha256(path: str) -> str:
    """sha256 of a bundled mesh or texture file (cached: these files do not change during a run)."""
    return sha256_file(Path(path))


def asset_name(path: str) -> str:
    """Content-addressed name of a mesh or texture file inside ``_assets/``."""
    return f"{source_sha256(path)[:12]}_{Path(path).name}"


def scene_xml(
    spec: mujoco.MjSpec, qpos: np.ndarray, ctrl: np.ndarray, objects: dict, stand_ins: bool = True
) -> tuple[str, dict[str, str]]:
    """MJCF of a settled scene, with mesh and texture files referenced inside ``../_assets/``.

    Free bodies are moved to their settled poses and keyframe 0 ``settled`` holds the full qpos and
    ctrl. ``objects`` maps body name -> qpos address. Returns (xml text, {asset file name: source path}).
    ``stand_ins``: MuJoCo compiles the whole spec again to write it, and most of that compile is the
    robot's visual meshes (~45 of ~60 ms); the text names a mesh's file but holds nothing read from it,
    so the spec is written with a four-vertex stand-in for every mesh file and the real file names put
    back (the same bytes: tests/store/test_scene_xml.py).
    """
    for name, adr in objects.items():
        body = spec.body(name)
        body.pos = qpos[adr : adr + 3]
        body.quat = qpos[adr + 3 : adr + 7]
    for key in list(spec.keys):
        spec.delete(key)
    spec.add_key(name="settled", qpos=qpos, ctrl=ctrl)
    with _stand_in_meshes(spec) if stand_ins else contextlib.nullcontext({}) as mesh_files:
        root = ET.fromstring(spec.to_xml())
    needed: dict[str, str] = {}
    for element in root.iter():
        if element.tag in ("mesh", "texture", "hfield", "skin") and element.get("file"):
            source = element.get("file")
            if element.tag == "mesh":
                source = mesh_files.get(element.get("name"), source)
            name = asset_name(source)
            needed[name] = source
            element.set("file", name)
            element.attrib.pop("content_type", None)
    # to_xml() prints 6 significant digits (5 um at the table's height): write the settled state in full.
    exact = {name: (qpos[adr : adr + 3], qpos[adr + 3 : adr + 7]) for name, adr in objects.items()}
    for element in root.iter("body"):
        if element.get("name") in exact:
            pos, quat = exact[element.get("name")]
            element.set("pos", _floats(pos))
            element.set("quat", _floats(quat))
    cams = {c.name: c for c in spec.cameras}
    for element in root.iter("camera"):
        cam = cams.get(element.get("name"))
        if cam is not None:
            element.set("pos", _floats(cam.pos))
            element.set("quat", _floats(cam.quat))
    lights = {light.name: light for light in spec.lights}
    for element in root.iter("light"):
        light = lights.get(element.get("name"))
        if light is not None:
            element.set("pos", _floats(light.pos))
            element.set("dir", _floats(light.dir))
            element.set("diffuse", _floats(light.diffuse))
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


_TETRAHEDRON = ((0.0, 0.0, 0.0), (0.01, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.0, 0.01))
_TETRAHEDRON_FACES = ((0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3))


@functools.cache
def _stand_in_files() -> dict[str, str]:
    """A four-vertex mesh as .obj and .stl, written once per process to a folder removed at exit."""
    import atexit
    import struct
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="scenegen_stand_in_"))
    atexit.register(shutil.rmtree, folder, True)
    obj = "".join("v {} {} {}\n".format(*v) for v in _TETRAHEDRON)
    obj += "".join("f {} {} {}\n".format(*(i + 1 for i in f)) for f in _TETRAHEDRON_FACES)
    (folder / "stand_in.obj").write_text(obj)
    triangles = b"".join(
        struct.pack("<12fH", 0, 0, 0, *(c for i in f for c in _TETRAHEDRON[i]), 0) for f in _TETRAHEDRON_FACES
    )
    (folder / "stand_in.stl").write_bytes(bytes(80) + struct.pack("<I", len(_TETRAHEDRON_FACES)) + triangles)
    return {".obj": str(folder / "stand_in.obj"), ".stl": str(folder / "stand_in.stl")}


@contextlib.contextmanager
def _stand_in_meshes(spec: mujoco.MjSpec):
    """Within the block, every named .obj / .stl mesh of ``spec`` reads a stand-in file; yields {mesh
    name: its real file}, restored on exit."""
    stand_ins, real = _stand_in_files(), {}
    try:
        for mesh in spec.meshes:
            stand_in = stand_ins.get(Path(mesh.file).suffix.lower())
            if mesh.name and mesh.file and stand_in:
                real[mesh.name] = mesh.file
                mesh.file = stand_in
        yield real
    finally:
        for mesh in spec.meshes:
            if mesh.name in real:
                mesh.file = real[mesh.name]


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


class StoreError(ValueError):
    """The output directory cannot take this batch; the message names it and what to do."""


@dataclass
class ResumeState:
    """Where a batch stands: the next proposal index, scenes stored, rejections by label."""

    next_index: int = 0
    accepted: int = 0
    rejections: Counter = field(default_factory=Counter)


class BatchStore:
    """Writer of one batch directory."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def open(self, pipeline_yaml: str) -> ResumeState:
        """Start a new batch, or pick up a killed one of the same recipe exactly where it stopped.

        Everything after the last complete commit is undone: temporary directories and files, a
        torn last line of the index or rejection log, a scene directory whose index row was never
        written. Since every stage is a pure function of its proposal, redoing that work gives the
        same bytes as an uninterrupted run.
        """
        root = self.root
        if root.exists() and not root.is_dir():
            raise StoreError(f"--out {root}: is a file; choose a directory")
        recipe = root / "pipeline.yaml"
        if not recipe.is_file() and _never_started(root):
            # pipeline.yaml is written first, so a run killed before it leaves at most its temp file
            root.mkdir(parents=True, exist_ok=True)
            for leftover in root.iterdir():
                leftover.unlink()
            atomic_write(recipe, pipeline_yaml)
            self._skeleton()
            return ResumeState()
        if not recipe.is_file():
            raise StoreError(
                f"--out {root}: already exists and is not a scenegen batch; choose a new directory"
            )
        if recipe.read_text() != pipeline_yaml:
            raise StoreError(
                f"--out {root}: holds a batch of another recipe or overrides; rerun the same command to "
                "resume it, or choose a new directory"
            )
        for leftover in [*root.glob(".tmp_*"), *root.glob(".*.tmp*"), *(root / ASSETS).glob(".*.tmp*")]:
            shutil.rmtree(leftover) if leftover.is_dir() else leftover.unlink()
        self._skeleton()  # a run killed just after pipeline.yaml may not have made it
        index = recover_jsonl(root / INDEX)
        rejections = _unfinished_repairs_cut(root / REJECTIONS, recover_jsonl(root / REJECTIONS), index)
        indexed = {row["scene_id"] for row in index}
        for entry in root.iterdir():
            if entry.is_dir() and entry.name.startswith("scene_") and entry.name not in indexed:
                shutil.rmtree(entry)
        last = max((row["proposal_index"] for row in [*index, *rejections]), default=-1)
        return ResumeState(last + 1, len(index), Counter(row["label"] for row in rejections))

    def _skeleton(self) -> None:
        (self.root / ASSETS).mkdir(exist_ok=True)
        for log in (INDEX, REJECTIONS):  # present from the start, empty or not
            (self.root / log).touch()

    def _ensure_assets(self, needed: dict[str, str]) -> None:
        for name, source in needed.items():
            dest = self.root / ASSETS / name
            if not dest.exists():
                tmp = dest.with_name(f".{name}.tmp")
                shutil.copyfile(source, tmp)
                os.replace(tmp, dest)

    def commit_scene(
        self, record: SceneRecord, xml: str, needed: dict[str, str], images: dict[str, bytes]
    ) -> SceneRecord:
        """Write one scene atomically and append its index row; returns the record with file hashes."""
        self._ensure_assets(needed)
        final = self.root / record.scene_id
        tmp = self.root / f".tmp_{record.scene_id}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        (tmp / "scene.xml").write_text(xml)
        files = {"scene.xml": sha256_file(tmp / "scene.xml")}
        for name, data in sorted(images.items()):
            (tmp / name).write_bytes(data)
            files[name] = hashlib.sha256(data).hexdigest()
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
                "tags": sorted(t for t, v in record.tags.items() if v.holds),
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


def _unfinished_repairs_cut(path: Path, rejections: list[dict], index: list[dict]) -> list[dict]:
    """The rejection log without the rows of a proposal index whose repairs a kill interrupted (its
    last rows say ``repaired`` and nothing of the index follows): the index is redone on resume,
    first pass and repairs, as an uninterrupted run would have them. Rewrites the log if so."""
    if not rejections or not rejections[-1].get("repaired"):
        return rejections
    last = rejections[-1]["proposal_index"]
    if last in {row["proposal_index"] for row in index}:
        return rejections  # the index ended accepted: its repairs are complete
    keep = len(rejections)
    while keep and rejections[keep - 1].get("repaired") and rejections[keep - 1]["proposal_index"] == last:
        keep -= 1  # only the last index's rows: an earlier accepted index's repair rows stay
    if keep == len(rejections):
        return rejections
    kept = rejections[:keep]
    atomic_write(path, "".join(json.dumps(row, sort_keys=True) + "\n" for row in kept))
    return kept


def _never_started(root: Path) -> bool:
    """Whether ``root`` is absent, empty, or holds only the temp file of a pipeline.yaml whose write
    was killed: a batch that never began."""
    if not root.exists():
        return True
    return all(entry.name.startswith(".pipeline.yaml.tmp") for entry in root.iterdir())


def recover_jsonl(path: Path) -> list[dict]:
    """Rows of an append-only log, cutting a torn last line (a write killed midway) off the file."""
    if not path.exists():
        return []
    data = path.read_bytes()
    keep = data[: data.rfind(b"\n") + 1]
    if keep != data:
        atomic_write(path, keep)
    return [json.loads(line) for line in keep.decode().splitlines() if line.strip()]


def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def scene_dirs(batch: Path) -> list[tuple[dict, Path]]:
    """Every (index row, scene directory) of a stored batch, in index order. StoreError (one line,
    naming the file) when index.jsonl is missing or unreadable, a row's scene_id is not a scene name,
    or a scene directory leads out of the batch (a symlink)."""
    batch = Path(batch)
    index = batch / INDEX
    if not index.is_file():
        raise StoreError(f"{batch}: no {INDEX}; give a batch directory written by `scenegen generate`")
    out = []
    try:
        lines = index.read_bytes().decode("utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise StoreError(
            f"{index}: unreadable ({type(exc).__name__}); regenerate or restore the batch"
        ) from None
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError:
            raise StoreError(f"{index}: line {number} is not JSON; regenerate or restore the batch") from None
        scene_id = row.get("scene_id") if isinstance(row, dict) else None
        if not isinstance(scene_id, str) or not SCENE_ID.match(scene_id):
            shown = repr(scene_id)[:40]
            raise StoreError(f"{index}: line {number}: scene_id {shown} is not a scene name (scene_NNNNNN)")
        try:
            out.append((row, confined(batch / scene_id, batch, "the scene directory")))
        except OutsideRootError as exc:
            raise StoreError(str(exc)) from None
    return out


def xml_references(scene_xml: Path) -> list[Path]:
    """The files a stored scene.xml names (meshes, textures, includes), resolved as MuJoCo would:
    against the compiler's meshdir / texturedir, relative to the scene.xml's folder."""
    try:
        root = ET.parse(scene_xml).getroot()
    except (ET.ParseError, OSError) as exc:
        raise StoreError(f"{scene_xml}: not readable XML ({str(exc).splitlines()[0][:80]})") from None
    folder = Path(scene_xml).parent
    compiler = root.find("compiler")
    dirs = {"mesh": "meshdir", "skin": "meshdir", "texture": "texturedir", "hfield": "assetdir"}
    refs = []
    for element in root.iter():
        if "file" not in element.attrib:
            continue
        base = (
            compiler.get(dirs.get(element.tag, ""), compiler.get("assetdir", ""))
            if compiler is not None
            else ""
        )
        refs.append(folder / base / element.attrib["file"])
    for key in ("meshdir", "texturedir", "assetdir"):
        if compiler is not None and key in compiler.attrib:
            refs.append(folder / compiler.attrib[key])
    return refs


def check_scene_xml(scene_dir: Path, batch: Path) -> Path:
    """``scene_dir``/scene.xml when every file it names lies inside ``batch``; StoreError otherwise
    (a scene.xml pointing at /etc or ../../ is refused before MuJoCo reads anything)."""
    scene_xml = Path(scene_dir) / "scene.xml"
    try:
        confined(scene_xml, batch, "scene.xml")
        for path in xml_references(scene_xml):
            confined(path, batch, f"a file {scene_xml.name} names")
    except OutsideRootError as exc:
        raise StoreError(str(exc)) from None
    return scene_xml


def measure_stored_scene(scene_dir: Path, catalog=None, settings=None) -> dict:
    """Recompute every tag of a stored scene from its files alone: scene.xml at its keyframe (the
    settled state) and the placements, lighting and main camera in scene.json. ``settings``: the
    batch recipe's thresholds (``PipelineConfig.tags``; default the defaults). Returns tag -> TagValue,
    to compare with the tags the pipeline recorded."""
    from scenegen.assets.catalog import load_catalog
    from scenegen.settle.physics import contact_configuration
    from scenegen.tags.predicates import TagContext, measure_tags

    scene_dir = Path(scene_dir)
    record = SceneRecord.model_validate_json((scene_dir / "scene.json").read_text())
    model = mujoco.MjModel.from_xml_path(str(check_scene_xml(scene_dir, scene_dir.parent)))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    names = [o.name for o in record.objects]
    context = TagContext.of_scene(
        model,
        data,
        catalog or load_catalog(),
        record.target,
        record.objects,
        record.furniture,
        record.lighting,
        record.cameras[0]["position"],
        contact_configuration(model, data.qpos, names),
    )
    return measure_tags(context, settings)
