"""The asset catalog (assets/catalog.yaml): what objects exist and their physical description.

Loading validates every entry against its files: the mesh exists, its sha256 matches, it parses into a
watertight triangle mesh, and its convex parts exist. A broken asset is an error that names it.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path

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


class Asset(BaseModel):
    """One object kind. Mesh frame = centre-of-mass frame, authored upright (+z up), metres."""

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

    def upright_pose(self) -> int | None:
        """Index of the upright resting pose, if the asset has one."""
        return next((i for i, p in enumerate(self.resting_poses) if p.upright), None)


class Catalog(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    version: int
    assets: tuple[Asset, ...]
    root: Path = ASSETS_DIR
    sha256: str = ""  # of catalog.yaml, stamped into every scene's provenance

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


@functools.lru_cache(maxsize=4)
def load_catalog(root: Path = ASSETS_DIR) -> Catalog:
    """Load and validate ``root/catalog.yaml`` (cached per root)."""
    root = Path(root)
    catalog_file = root / "catalog.yaml"
    if not catalog_file.is_file():
        raise CatalogError(f"{catalog_file}: asset catalog missing; run `make assets` to build it")
    raw_bytes = catalog_file.read_bytes()
    raw = yaml.safe_load(raw_bytes)
    try:
        catalog = Catalog(**raw, root=root, sha256=hashlib.sha256(raw_bytes).hexdigest())
    except (ValidationError, TypeError) as exc:
        raise CatalogError(f"{catalog_file}: invalid catalog: {exc}") from None
    for asset in catalog.assets:
        _validate_files(catalog, asset)
    return catalog


def _validate_files(catalog: Catalog, asset: Asset) -> None:
    mesh_file = catalog.path(asset.mesh)
    where = f"asset {asset.name!r} ({mesh_file})"
    if not mesh_file.is_file():
        raise CatalogError(f"{where}: mesh file missing; rebuild with `make assets`")
    data = mesh_file.read_bytes()
    if hashlib.sha256(data).hexdigest() != asset.mesh_sha256:
        raise CatalogError(f"{where}: mesh sha256 does not match the catalog; rebuild with `make assets`")
    vertices, faces = read_obj(data, where)
    if not _is_watertight(faces):
        raise CatalogError(f"{where}: mesh is not watertight (every edge must join two faces)")
    if parts_key(asset.mesh_sha256, asset.parts.coacd_version, asset.parts.params) != asset.parts.key:
        raise CatalogError(
            f"{where}: convex parts were made for another mesh or coacd version; rebuild with `make assets`"
        )
    for part in asset.parts.files:
        if not catalog.path(part).is_file():
            raise CatalogError(
                f"asset {asset.name!r}: convex part {part} missing; rebuild with `make assets`"
            )


def parts_key(mesh_sha: str, coacd_version: str, params: dict) -> str:
    """Cache key of an asset's convex parts: (mesh sha256, coacd version, coacd parameters)."""
    blob = json.dumps({"mesh": mesh_sha, "coacd": coacd_version, "params": params}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def read_obj(data: bytes, where: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangle faces (F, 3, zero-based) of a plain OBJ file."""
    vertices, faces = [], []
    try:
        for line in data.decode().splitlines():
            if line.startswith("v "):
                vertices.append([float(v) for v in line.split()[1:4]])
            elif line.startswith("f "):
                faces.append([int(v.split("/")[0]) - 1 for v in line.split()[1:4]])
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


@functools.lru_cache(maxsize=64)
def convex_part_vertices(root: Path, asset_name: str) -> tuple[np.ndarray, ...]:
    """Vertices (V, 3) of each convex part of an asset, in its body frame."""
    catalog = load_catalog(root)
    asset = catalog.get(asset_name)
    return tuple(read_obj(catalog.path(f).read_bytes(), f)[0] for f in asset.parts.files)
