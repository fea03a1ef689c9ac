"""The asset catalogs: what objects exist and their physical description.

The bundled catalog (assets/catalog.yaml, written by authoring.py) and any user catalogs (written by
``scenegen assets add``, importer.py) have one format; :func:`load_catalogs` merges them, bundled
first, and refuses a name two of them use. Each asset keeps the folder of its own catalog
(``Asset.root``), against which its file paths resolve.

Loading validates every entry against its files: the mesh exists, its sha256 matches, it parses
(triangles or polygons, with or without texture coordinates), an authored mesh is watertight, and its
convex parts and texture exist. A broken asset is an error that names it.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
from collections.abc import Iterator, Sequence
from contextvars import ContextVar
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from scenegen.paths import ASSETS_DIR


class CatalogError(ValueError):
    """The catalog or one of its assets is broken; the message names the asset and what to do."""


class RestingPose(BaseModel):
    """A stable way for the asset to lie on a horizontal surface (yaw free)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    quat: tuple[float, float, float, float]  # wxyz rotation of the body frame, yaw removed
    height: float  # metres from the surface up to the centre of mass (the body origin)
    probability: float
    upright: bool


class ConvexParts(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    key: str  # hash of (mesh sha256, coacd version, params)
    coacd_version: str
    params: dict
    files: tuple[str, ...]


class AssetSource(BaseModel):
    """Where an imported asset came from and what the import did to it (absent for authored ones)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    file: str  # the user's file name, without its folder
    sha256: str  # of the user's file
    scale: float = Field(gt=0)  # applied to the file's coordinates to get metres
    up: Literal["z", "y"]  # the file's up axis
    notes: tuple[str, ...] = ()  # what the import repaired, merged, decimated or dropped


class Asset(BaseModel):
    """One object kind. Mesh frame = centre-of-mass frame, upright (+z up), metres.

    ``collision`` says how the convex parts were made: ``convex_decomposition`` (coacd on a watertight
    mesh) or ``convex_hull`` (one part, for a mesh that could not be made watertight). ``root`` is the
    folder of the asset's catalog, set by the loader (never read from the file)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    name: str
    category: str
    mesh: str
    mesh_sha256: str
    parts: ConvexParts
    density: float = Field(gt=0)
    mass: float = Field(gt=0)  # kg
    inertia: tuple[tuple[float, float, float], ...]  # kg m^2 about the centre of mass
    friction: float = Field(gt=0)
    rgba: tuple[float, float, float, float]
    extents: tuple[float, float, float]  # axis-aligned size of the authored mesh (m)
    hull_to_visual_mm: float  # Hausdorff distance between convex parts and visual mesh
    resting_poses: tuple[RestingPose, ...] = Field(min_length=1)
    texture: str | None = None  # a PNG mapped with the visual mesh's texture coordinates
    collision: Literal["convex_decomposition", "convex_hull"] = "convex_decomposition"
    source: AssetSource | None = None
    # A round object (every resting pose at about the same height, a lemon): every pose is upright
    # and ``toppled`` never holds for it, whatever way it has rolled.
    orientation_free: bool = False
    root: Path | None = Field(default=None, exclude=True)

    @property
    def folder(self) -> Path:
        """Its catalog's folder (the bundled one for an asset built outside a loader)."""
        return self.root or ASSETS_DIR

    def file(self, relative: str) -> Path:
        """A file of this asset (its mesh, a part, its texture), resolved in its catalog's folder."""
        return self.folder / relative

    def upright_pose(self) -> int | None:
        """Index of the upright resting pose, if the asset has one."""
        return next((i for i, p in enumerate(self.resting_poses) if p.upright), None)


class CatalogFile(BaseModel):
    """One catalog file a merged catalog was loaded from, for provenance."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    path: str
    sha256: str


class Catalog(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    version: int
    assets: tuple[Asset, ...]
    root: Path = ASSETS_DIR  # the (first) catalog's folder
    sha256: str = ""  # of catalog.yaml (of the list of catalogs' sha256 when merged), in provenance
    files: tuple[CatalogFile, ...] = ()  # the catalog files, in load order

    @functools.cached_property
    def by_name(self) -> dict[str, Asset]:
        return {a.name: a for a in self.assets}

    @property
    def categories(self) -> tuple[str, ...]:
        return tuple(sorted({a.category for a in self.assets}))

    def of_category(self, category: str) -> tuple[Asset, ...]:
        return tuple(a for a in self.assets if a.category == category)

    def get(self, name: str) -> Asset:
        try:
            return self.by_name[name]
        except KeyError:
            raise CatalogError(
                f"unknown asset {name!r}; valid assets: {', '.join(sorted(self.by_name))}"
            ) from None

    def path(self, relative: str) -> Path:
        return self.root / relative


CATALOG_FILE = "catalog.yaml"


def catalog_file(location: Path) -> Path:
    """The catalog file a location names: the file itself, or ``catalog.yaml`` in a folder."""
    location = Path(location)
    return location / CATALOG_FILE if location.is_dir() or location.suffix == "" else location


@functools.lru_cache(maxsize=16)
def load_catalog(root: Path = ASSETS_DIR) -> Catalog:
    """Load and validate one catalog: ``root/catalog.yaml``, or ``root`` itself when it is a file
    (cached per location). Its assets' files resolve in the catalog file's folder."""
    file = catalog_file(root)
    bundled = file.resolve() == _bundled_file()
    if not file.is_file():
        remedy = "run `make assets` to build it" if bundled else "create it with `scenegen assets add`"
        raise CatalogError(f"{file}: asset catalog missing; {remedy}")
    raw_bytes = file.read_bytes()
    try:
        raw = yaml.safe_load(raw_bytes)
        sha = hashlib.sha256(raw_bytes).hexdigest()
        files = (CatalogFile(path=str(file), sha256=sha),)
        catalog = Catalog(**raw, root=file.parent.resolve(), sha256=sha, files=files)
    except (ValidationError, TypeError, yaml.YAMLError) as exc:
        reason = (str(exc).strip() or type(exc).__name__).splitlines()[0]
        raise CatalogError(f"{file}: invalid catalog: {reason}") from None
    assets = tuple(a.model_copy(update={"root": catalog.root}) for a in catalog.assets)  # absolute
    catalog = catalog.model_copy(update={"assets": assets})
    for asset in catalog.assets:
        validate_asset_files(asset)
    return catalog


def load_catalogs(locations: Sequence[Path] = ()) -> Catalog:
    """The bundled catalog merged with the user catalogs at ``locations`` (each a catalog file or its
    folder), in that order. No user catalog: the bundled catalog itself, sha256 and all. An asset
    name used twice is an error naming both catalogs."""
    bundled = load_catalog(ASSETS_DIR)
    others = [load_catalog(Path(loc)) for loc in locations if not is_bundled(Path(loc))]
    if not others:
        return bundled
    assets, owner = list(bundled.assets), dict.fromkeys(bundled.by_name, bundled.files[0].path)
    for catalog in others:
        for asset in catalog.assets:
            if asset.name in owner:
                raise CatalogError(
                    f"asset {asset.name!r} is in both {owner[asset.name]} and {catalog.files[0].path}; "
                    "rename one (scenegen assets add --name) or leave one catalog out"
                )
            owner[asset.name] = catalog.files[0].path
            assets.append(asset)
    files = (*bundled.files, *(c.files[0] for c in others))
    sha = hashlib.sha256("\n".join(f.sha256 for f in files).encode()).hexdigest()
    return Catalog(version=bundled.version, assets=tuple(assets), root=bundled.root, sha256=sha, files=files)


_ACTIVE: ContextVar[tuple[str, ...]] = ContextVar("scenegen_user_catalogs", default=())


@contextlib.contextmanager
def using_catalogs(locations: Sequence[Path | str]) -> Iterator[Catalog]:
    """Within the block, :func:`active_catalog` is the bundled catalog merged with ``locations``:
    what a recipe's ``catalogs`` key names while the recipe is validated (its target category, the
    assets its proposer names). Yields that catalog."""
    catalog = load_catalogs([Path(p) for p in locations])
    token = _ACTIVE.set(tuple(str(p) for p in locations))
    try:
        yield catalog
    finally:
        _ACTIVE.reset(token)


def active_catalog() -> Catalog:
    """The catalog requests are validated against: the bundled one, merged with the user catalogs of
    an enclosing :func:`using_catalogs` block."""
    return load_catalogs([Path(p) for p in _ACTIVE.get()])


def _bundled_file() -> Path:
    return (ASSETS_DIR / CATALOG_FILE).resolve()


def entry_files(entry) -> list[str] | None:
    """The files a catalog entry as written (a mapping from catalog.yaml) references, relative to
    its catalog's folder: its mesh first, then its convex parts and its texture; None when the
    entry does not name them as texts."""
    parts = entry.get("parts") if isinstance(entry, dict) else None
    files = parts.get("files") if isinstance(parts, dict) else None
    texture = entry.get("texture") if isinstance(entry, dict) else None
    if (
        not isinstance(files, list)
        or not all(isinstance(f, str) for f in [entry.get("mesh"), *files])
        or not isinstance(texture, str | None)
    ):
        return None
    return [entry["mesh"], *files, *([texture] if texture is not None else [])]


def is_bundled(location: Path) -> bool:
    """Whether ``location`` (a catalog file or its folder) is the bundled catalog."""
    return catalog_file(location).resolve() == _bundled_file()


def validate_asset_files(asset: Asset) -> None:
    mesh_file = asset.file(asset.mesh)
    where = f"asset {asset.name!r} ({mesh_file})"
    remedy = (
        "rebuild with `make assets`" if asset.source is None else "import it again with `scenegen assets add`"
    )
    for relative in (asset.mesh, *asset.parts.files, *([asset.texture] if asset.texture else [])):
        if not confined_to(asset.folder, relative):
            raise CatalogError(f"asset {asset.name!r}: {relative} is outside its catalog's folder; {remedy}")
    if not mesh_file.is_file():
        raise CatalogError(f"{where}: mesh file missing; {remedy}")
    data = mesh_file.read_bytes()
    if hashlib.sha256(data).hexdigest() != asset.mesh_sha256:
        raise CatalogError(f"{where}: mesh sha256 does not match the catalog; {remedy}")
    vertices, faces = read_obj(data, where)
    if asset.source is None and not _is_watertight(faces):
        raise CatalogError(f"{where}: mesh is not watertight (every edge must join two faces)")
    if parts_key(asset.mesh_sha256, asset.parts.coacd_version, asset.parts.params) != asset.parts.key:
        raise CatalogError(f"{where}: convex parts were made for another mesh or coacd version; {remedy}")
    for part in asset.parts.files:
        if not asset.file(part).is_file():
            raise CatalogError(f"asset {asset.name!r}: convex part {part} missing; {remedy}")
    if asset.texture and not asset.file(asset.texture).is_file():
        raise CatalogError(f"asset {asset.name!r}: texture {asset.texture} missing; {remedy}")


def confined_to(root: Path, relative: str) -> bool:
    """Whether ``relative`` names a path inside ``root`` (no absolute path, no way out through ..)."""
    if Path(relative).is_absolute():
        return False
    base = Path(root).resolve()
    return (base / relative).resolve().is_relative_to(base)


def parts_key(mesh_sha: str, coacd_version: str, params: dict) -> str:
    """Cache key of an asset's convex parts: (mesh sha256, coacd version, coacd parameters)."""
    blob = json.dumps({"mesh": mesh_sha, "coacd": coacd_version, "params": params}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def read_obj(data: bytes, where: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangle faces (F, 3, zero-based) of an OBJ file: polygons are split into
    triangle fans; texture and normal indices (``f v/vt/vn``) and negative indices are understood."""
    vertices, faces = [], []
    try:
        for line in data.decode().splitlines():
            if line.startswith("v "):
                vertices.append([float(v) for v in line.split()[1:4]])
            elif line.startswith("f "):
                corners = [int(v.split("/")[0]) for v in line.split()[1:]]
                corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
                faces.extend([corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1))
    except (ValueError, UnicodeDecodeError) as exc:
        raise CatalogError(f"{where}: cannot parse OBJ: {exc}") from None
    v, f = np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64)
    if len(v) < 4 or len(f) < 4 or f.min() < 0 or f.max() >= len(v) or not np.isfinite(v).all():
        raise CatalogError(f"{where}: mesh is empty or has invalid vertices or face indices")
    return v, f


def _is_watertight(faces: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool((counts == 2).all())


def convex_part_vertices(catalog: Catalog, asset_name: str) -> tuple[np.ndarray, ...]:
    """Vertices (V, 3) of each convex part of an asset, in its body frame."""
    return part_vertices(catalog.get(asset_name))


def part_vertices(asset: Asset) -> tuple[np.ndarray, ...]:
    """Vertices (V, 3) of each convex part of ``asset``, in its body frame (read once per process)."""
    return part_vertices_at(asset.folder, asset.parts.files)


@functools.lru_cache(maxsize=256)
def part_vertices_at(root: Path, files: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    """Vertices (V, 3) of each part file under ``root`` (cached per root and files)."""
    return tuple(read_obj((root / f).read_bytes(), f)[0] for f in files)
