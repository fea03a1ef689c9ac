"""``scenegen assets add``: a user's mesh becomes a verified asset of a user catalog.

The import measures what the bundled assets carry (authoring.py): convex parts (coacd on the
watertight solid, or its convex hull), resting poses with their probabilities (trimesh's quasi-static
estimate, each kept only if a 1 s MuJoCo drop leaves it lying that way), mass and inertia, extents,
the hull-to-visual distance; it keeps the mesh's texture or its colour.

A user catalog is a folder: ``catalog.yaml`` and one folder per asset (``NAME/visual.obj``,
``NAME/parts/KEY/part_*.obj``, ``NAME/texture.png``). An import is atomic: it stages everything in
``.staging-PID-*`` inside the catalog's folder, moves the asset's folder into place, then replaces
``catalog.yaml`` in one rename. A failed or killed import leaves ``catalog.yaml`` as it was; the next
import removes a killed one's staging folder, and a folder it moved in without its catalog entry.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import trimesh
import yaml

from scenegen.assets.catalog import (
    ASSETS_DIR,
    CATALOG_FILE,
    Asset,
    CatalogError,
    catalog_file,
    entry_files,
    load_catalog,
    parts_key,
    validate_asset_files,
)
from scenegen.assets.measure import (
    coacd_version,
    convex_parts,
    hull_to_visual_distance,
    inertial,
    resting_poses,
    sha256_bytes,
)
from scenegen.core.files import sha256_file
from scenegen.data.asset_meshes import UNITS, MeshImportError, UserMesh, obj_text, read_user_mesh
from scenegen.paths import USER_CATALOG  # noqa: F401 - the default catalog, re-exported

NAME = re.compile(r"^[a-z][a-z0-9_]{0,39}$")
STAGING_PREFIX = ".staging-"
DEFAULT_DENSITY = 500.0  # kg/m^3, when neither --mass nor --density is given (a note says so)
COACD_PARAMS = {"threshold": 0.03, "preprocess_mode": "off", "max_convex_hull": 16, "seed": 0}
DROP_SECONDS, DROP_TILT_DEG = 1.0, 10.0  # a resting pose is kept if a drop tilts it less than this
ROUND_HEIGHTS, ROUND_EXTENTS = 0.1, 1.25  # a round object: see _upright_by_geometry
HEADER = "# Written by `scenegen assets add`; each asset's files are in the folder of its name.\n"


@dataclass(frozen=True)
class ImportOptions:
    """What the user says about one mesh (``scenegen assets add --help``)."""

    category: str | None  # None: refused before any import (a folder's file the sidecar left out)
    name: str | None = None
    scale: float | None = None
    units: str | None = None
    mass: float | None = None  # kg
    density: float | None = None  # kg/m^3
    friction: float = 0.7
    up: str = "z"
    texture: Path | None = None
    collision: str = "auto"  # auto: coacd on a watertight solid; hull: one convex part


@dataclass(frozen=True)
class ImportResult:
    asset: Asset
    catalog: Path
    notes: tuple[str, ...]
    seconds: float


def add_asset(
    mesh_path: Path, options: ImportOptions, catalog: Path = USER_CATALOG, log=print
) -> ImportResult:
    """Import ``mesh_path`` into the user catalog ``catalog`` (a catalog.yaml or its folder; created
    if missing). Raises MeshImportError (the file) or CatalogError (the catalog) with one line; on
    any failure the catalog is as it was."""
    return commit_asset(stage_asset(mesh_path, options, catalog, log), catalog)


def default_name(mesh_path: Path) -> str:
    """An asset's name when none is given: the file's name, lowercased, other characters as _."""
    return re.sub(r"[^a-z0-9_]", "_", Path(mesh_path).stem.lower()).strip("_")


@dataclass(frozen=True)
class StagedAsset:
    """An import's measured files in a staging folder of the catalog's folder, not yet listed."""

    name: str
    entry: dict
    stage: Path  # holds NAME/
    notes: tuple[str, ...]
    seconds: float


def stage_asset(mesh_path: Path, options: ImportOptions, catalog: Path, log=print) -> StagedAsset:
    """The costly half of an import (mesh repair, convex parts, drops): the asset's files staged
    beside ``catalog``, which is not written. Imports of different meshes may stage in parallel;
    :func:`commit_asset` lists each, one at a time. Raises as :func:`add_asset`."""
    start = time.perf_counter()
    mesh_path, target = Path(mesh_path), catalog_file(catalog)
    name = options.name or default_name(mesh_path)
    _check_names(mesh_path, name, options, target)
    folder = target.parent
    _check_folder(folder, target, _entries(target))
    mesh = read_user_mesh(mesh_path, options.scale, options.units, options.up, options.texture)
    notes = list(mesh.notes)
    if options.collision == "hull" and mesh.collision != "convex_hull":
        mesh.solid, mesh.collision = mesh.solid.convex_hull, "convex_hull"
        notes.append("collision model: the convex hull (one part), as --collision hull asks")
    folder.mkdir(parents=True, exist_ok=True)
    _remove_dead_staging(folder)
    stage = Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=folder))
    try:
        entry = _stage_asset(stage / name, name, mesh_path, mesh, options, notes, log)
        validate_asset_files(Asset(**entry).model_copy(update={"root": stage}))
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return StagedAsset(name, entry, stage, tuple(notes), time.perf_counter() - start)


def commit_asset(staged: StagedAsset, catalog: Path) -> ImportResult:
    """List a staged asset: its folder moved into place, then ``catalog.yaml`` replaced in one
    rename, under a lock on the catalog's folder (another import may be committing). The staging
    folder is removed whatever happens."""
    start = time.perf_counter()
    target = catalog_file(catalog)
    folder, name, notes = target.parent, staged.name, list(staged.notes)
    try:
        with _locked(folder):
            entries = _entries(target)
            if any(entry.get("name") == name for entry in entries):
                raise CatalogError(f"asset {name!r} is already in {target}; choose another with --name")
            listing = {"version": 1, "assets": [*entries, staged.entry]}
            (staged.stage / CATALOG_FILE).write_text(
                HEADER + yaml.safe_dump(listing, sort_keys=False, width=100)
            )
            leftover = folder / name
            if _left_by_an_import(leftover):  # moved in by an import killed before its entry was written
                shutil.rmtree(leftover)
                notes.append(f"removed {leftover}, left by an interrupted import")
            os.rename(staged.stage / name, folder / name)
            os.replace(staged.stage / CATALOG_FILE, target)
    finally:
        shutil.rmtree(staged.stage, ignore_errors=True)
    load_catalog.cache_clear()
    asset = load_catalog(target).get(name)
    return ImportResult(asset, target, tuple(notes), staged.seconds + time.perf_counter() - start)


@contextmanager
def _locked(folder: Path):
    """An exclusive lock on a catalog's folder itself (flock on its directory: no file to leave
    behind), released when the process ends however it ends."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing drops the lock


def _remove_dead_staging(folder: Path) -> None:
    """Remove the staging folders of imports whose process is gone (killed mid-way)."""
    for stage in folder.glob(f"{STAGING_PREFIX}*"):
        pid = stage.name[len(STAGING_PREFIX) :].split("-")[0]
        try:
            os.kill(int(pid), 0)
        except (ValueError, ProcessLookupError):
            shutil.rmtree(stage, ignore_errors=True)
        except PermissionError:
            pass  # another user's live process


def _check_names(mesh_path: Path, name: str, options: ImportOptions, target: Path) -> None:
    if not NAME.match(name):
        raise MeshImportError(
            f"{mesh_path}: asset name {name!r} must be lowercase letters, digits and _ "
            "(starting with a letter, at most 40); give one with --name"
        )
    if not NAME.match(options.category):
        raise MeshImportError(
            f"category {options.category!r} must be lowercase letters, digits and _ "
            "(starting with a letter), e.g. --category fruit"
        )
    if target.resolve() == (ASSETS_DIR / CATALOG_FILE).resolve():
        raise CatalogError(
            f"{target}: the bundled catalog is written by `make assets` only; "
            "import into a user catalog (--catalog user_assets/catalog.yaml)"
        )
    if options.mass is not None and options.density is not None:
        raise MeshImportError(f"{mesh_path}: give --mass or --density, not both")
    for label, value in (
        ("--mass", options.mass),
        ("--density", options.density),
        ("--friction", options.friction),
    ):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise MeshImportError(f"{mesh_path}: {label} {value} must be a positive number")
    taken = {a.name: str(ASSETS_DIR / CATALOG_FILE) for a in load_catalog(ASSETS_DIR).assets}
    if target.is_file():
        taken |= {a.name: str(target) for a in load_catalog(target).assets}
    if name in taken:
        raise CatalogError(f"asset {name!r} is already in {taken[name]}; choose another with --name")


IMPORTED = frozenset({"visual.obj", "texture.png", "parts"})  # what an import moves into NAME/


def _check_folder(folder: Path, target: Path, entries: list[dict]) -> None:
    """A catalog needs a folder of its own: the audit of every batch made with it counts each file
    there that the catalog does not reference as a violation. Refuses (one line) a folder whose top
    level holds anything but the catalog file, its entries' folders, import staging folders and
    asset folders an import moved in before it was killed (holding only what an import writes:
    the next import of that name replaces one)."""
    if not folder.is_dir():
        return
    owned = {target.name}
    for entry in entries:
        owned |= {PurePosixPath(f).parts[0] for f in entry_files(entry) or [] if PurePosixPath(f).parts}
    # one listing: another import's staging folder made meanwhile is still seen as staging
    others = [p for p in folder.iterdir() if p.name not in owned and not p.name.startswith(STAGING_PREFIX)]
    strangers = sorted(p.name for p in others if not _left_by_an_import(p))
    if strangers:
        shown = ", ".join(strangers[:3]) + (f" and {len(strangers) - 3} more" if len(strangers) > 3 else "")
        raise CatalogError(
            f"{folder}: holds {shown}, which {target.name} does not own; a catalog needs a folder of its "
            "own (e.g. --catalog my_objects/catalog.yaml in a new folder)"
        )


def _left_by_an_import(path: Path) -> bool:
    """Whether ``path`` is an asset folder an import moved in and was killed before listing: a
    folder (not a link) holding its visual mesh and nothing but what an import writes."""
    if not path.is_dir() or path.is_symlink():
        return False
    names = {p.name for p in path.iterdir()}
    return "visual.obj" in names and names <= IMPORTED


def _entries(target: Path) -> list[dict]:
    """The catalog's entries as written (an empty list for a new catalog)."""
    if not target.is_file():
        return []
    raw = yaml.safe_load(target.read_text())
    return list(raw.get("assets") or [])


def _stage_asset(
    out: Path, name: str, source: Path, mesh: UserMesh, options: ImportOptions, notes: list[str], log
) -> dict:
    """Write the asset's files under ``out`` (its folder) and return its catalog entry."""
    (out / "parts").mkdir(parents=True)
    visual_bytes = obj_text(mesh.visual, mesh.uv)
    (out / "visual.obj").write_bytes(visual_bytes)
    mesh_sha = sha256_bytes(visual_bytes)
    texture = None
    if mesh.texture is not None:
        import cv2

        cv2.imwrite(str(out / "texture.png"), mesh.texture[:, :, ::-1])
        texture = f"{name}/texture.png"
    params = {**COACD_PARAMS, "collision": mesh.collision}
    key = parts_key(mesh_sha, coacd_version(), params)
    parts = _parts(mesh, params, log)
    (out / "parts" / key).mkdir()
    files = []
    for i, part in enumerate(parts):
        (out / "parts" / key / f"part_{i:03d}.obj").write_bytes(obj_text(part))
        files.append(f"{name}/parts/{key}/part_{i:03d}.obj")
    density = options.density or (options.mass / mesh.solid.volume if options.mass else DEFAULT_DENSITY)
    if options.mass is None and options.density is None:
        notes.append(f"density {DEFAULT_DENSITY:g} kg/m^3 assumed: give --mass or --density")
    poses, dropped = checked_resting_poses(mesh.solid, parts, density, options.friction)
    if dropped:
        notes.append(f"{dropped} resting pose(s) trimesh predicted fell over in a MuJoCo drop: left out")
    orientation_free = _upright_by_geometry(poses, mesh.solid.extents, notes)
    return {
        "name": name,
        "category": options.category,
        "mesh": f"{name}/visual.obj",
        "mesh_sha256": mesh_sha,
        "parts": {"key": key, "coacd_version": coacd_version(), "params": params, "files": files},
        "density": round(float(density), 3),
        **inertial(mesh.solid, density),
        "friction": options.friction,
        "rgba": list(mesh.rgba),
        "extents": [round(float(e), 5) for e in mesh.solid.extents],
        "hull_to_visual_mm": round(_hull_to_visual(mesh, parts) * 1000, 3),
        "resting_poses": poses,
        "texture": texture,
        "collision": mesh.collision,
        "orientation_free": orientation_free,
        "source": {
            "file": source.name,
            "sha256": sha256_file(source),
            "scale": float(options.scale or UNITS[options.units or "m"]),
            "up": options.up,
            "notes": notes,
        },
    }


def _upright_by_geometry(poses: list[dict], extents, notes: list[str]) -> bool:
    """Settle which resting poses count as upright where the file's +z does not (poses are changed in
    place); returns whether the object is round. Round: about as long as wide as high (ROUND_EXTENTS)
    and every pose's centre of mass within ROUND_HEIGHTS of the others' (a lemon, an apple), so every
    pose is upright and none toppled. Otherwise, if no pose keeps +z up, the most likely pose (and
    its mirror images) counts as upright."""
    heights = [p["height"] for p in poses]
    compact = max(extents) <= ROUND_EXTENTS * min(extents)
    if compact and max(heights) <= (1 + ROUND_HEIGHTS) * min(heights):
        for pose in poses:
            pose["upright"] = True
        notes.append("round (its resting poses all stand about as high): every pose upright, never toppled")
        return True
    if not any(p["upright"] for p in poses):
        best = max(p["probability"] for p in poses)
        for pose in poses:
            pose["upright"] = pose["probability"] >= best - 0.01
        notes.append("no resting pose keeps its +z up: its most likely pose counts as upright (--up?)")
    return False


def _parts(mesh: UserMesh, params: dict, log) -> list[trimesh.Trimesh]:
    """Convex parts of the solid: its hull, or coacd's parts (cached under the parts key of the
    collision input in SCENEGEN_CACHE, default ~/.cache/scenegen/coacd)."""
    if mesh.collision == "convex_hull":
        return [mesh.solid.convex_hull]
    solid_bytes = obj_text(mesh.solid)
    coacd_params = {k: v for k, v in params.items() if k != "collision"}
    cache = _cache_dir() / parts_key(sha256_bytes(solid_bytes), coacd_version(), coacd_params)
    if cache.is_dir():
        return [trimesh.load(p, process=False) for p in sorted(cache.glob("part_*.obj"))]
    log(f"convex decomposition (coacd) of {len(mesh.solid.faces)} triangles: up to ~2 min on 2 cores")
    solid = trimesh.load(trimesh.util.wrap_as_stream(solid_bytes), file_type="obj", process=False)
    parts = convex_parts(solid, coacd_params)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=_cache_dir()))
    for i, part in enumerate(parts):
        (tmp / f"part_{i:03d}.obj").write_bytes(obj_text(part))
    try:
        os.rename(tmp, cache)
    except OSError:  # another import filled it meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return [trimesh.load(p, process=False) for p in sorted(cache.glob("part_*.obj"))]


def _cache_dir() -> Path:
    root = Path(os.environ.get("SCENEGEN_CACHE", Path.home() / ".cache" / "scenegen")) / "coacd"
    root.mkdir(parents=True, exist_ok=True)
    return root


def _hull_to_visual(mesh: UserMesh, parts: list[trimesh.Trimesh]) -> float:
    """Hausdorff distance (m) between the parts and the solid; for a hull, from the hull's surface
    to the visual surface (how far the collision model stands off the object)."""
    if mesh.collision == "convex_decomposition":
        return hull_to_visual_distance(mesh.solid, parts, n=5000)
    points, _ = trimesh.sample.sample_surface(parts[0], 5000, seed=0)
    return float(trimesh.proximity.closest_point(mesh.visual, points)[1].max())


def checked_resting_poses(
    solid: trimesh.Trimesh, parts: list[trimesh.Trimesh], density: float, friction: float
) -> tuple[list[dict], int]:
    """trimesh's resting poses of ``solid`` (measure.resting_poses), each kept only if the convex
    parts dropped 2 mm onto a plane in that pose lie the same way after DROP_SECONDS (the body's up
    axis tilts less than DROP_TILT_DEG). Returns the kept poses and how many were dropped."""
    import mujoco

    poses = resting_poses(solid)
    model = _drop_model(parts, inertial(solid, density), friction)
    data = mujoco.MjData(model)
    kept = []
    for pose in poses:
        mujoco.mj_resetData(model, data)
        data.qpos[:3] = [0.0, 0.0, pose["height"] + 0.002]
        data.qpos[3:7] = pose["quat"]
        for _ in range(int(DROP_SECONDS / model.opt.timestep)):
            mujoco.mj_step(model, data)
        before, after = np.zeros(9), np.zeros(9)
        mujoco.mju_quat2Mat(before, np.asarray(pose["quat"], float))
        mujoco.mju_quat2Mat(after, data.qpos[3:7])
        up_before, up_after = before.reshape(3, 3)[2], after.reshape(3, 3)[2]  # world z in body axes
        tilt = np.degrees(np.arccos(np.clip(up_before @ up_after, -1.0, 1.0)))
        if tilt < DROP_TILT_DEG:
            kept.append(pose)
    if not kept:  # nothing survived: keep the most likely pose rather than none (noted by the caller)
        kept = poses[:1]
    return kept, len(poses) - len(kept)


def _drop_model(parts: list[trimesh.Trimesh], mass: dict, friction: float):
    import mujoco

    from scenegen.sim import world

    # Settling's solver options but multiccd (not set here when the committed measurements were made).
    spec = mujoco.MjSpec()
    spec.option.timestep = world.TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = world.CONTACT_OPTIONS["impratio"]
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1, 1, 0.1], friction=[0.8, 0.005, 0.0001])
    body = spec.worldbody.add_body(name="object")
    body.add_freejoint()
    world.set_inertial(body, mass["mass"], mass["inertia"])
    for i, part in enumerate(parts):
        spec.add_mesh(name=f"part{i}", uservert=np.asarray(part.vertices, float).ravel().tolist())
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"part{i}", mass=0, **world.object_contact(friction)
        )
    return spec.compile()
