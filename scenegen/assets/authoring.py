"""Authoring of the bundled object assets: meshes, convex parts, resting poses, inertia.

Run ``python -m scenegen.assets.authoring`` (or ``make assets``) to rebuild ``assets/``. Meshes are
built from primitives with manifold3d (watertight by construction), so their convex decomposition can
run coacd with ``preprocess_mode="off"``, which keeps the 2-3 mm features of thin utensils (coacd's
voxel preprocessing would erase them, see shared/PITFALLS.md). Convex parts are cached under a key
of (mesh sha256, coacd version, coacd parameters): a rebuild with the same inputs reuses them, so CI
never runs coacd.

Every mesh is authored upright (+z up) and recentred on its centre of mass, so the body frame of an
object is its centre-of-mass frame and ``inertial.pos`` is zero.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import manifold3d as m3
import numpy as np
import trimesh
import yaml

from scenegen.assets.catalog import parts_key
from scenegen.assets.measure import (
    coacd_version,
    convex_parts,
    export_obj,
    hull_to_visual_distance,
    inertial,
    resting_poses,
    sha256_bytes,
)
from scenegen.paths import ASSETS_DIR

SEGMENTS = 40  # circle resolution: a 4 cm radius is off by < 0.5 mm at 40 segments


def _cyl(h: float, r: float, r_top: float | None = None) -> m3.Manifold:
    """Cylinder (or frustum) standing on z = 0."""
    return m3.Manifold.cylinder(h, r, r if r_top is None else r_top, SEGMENTS)


def _box(sx: float, sy: float, sz: float) -> m3.Manifold:
    """Box centred on the origin."""
    return m3.Manifold.cube((sx, sy, sz), center=True)


def _ellipsoid(rx: float, ry: float, rz: float) -> m3.Manifold:
    return m3.Manifold.sphere(1.0, SEGMENTS).scale((rx, ry, rz))


def teaspoon() -> m3.Manifold:
    handle = _box(0.105, 0.011, 0.003).translate((-0.055, 0, 0.0015))
    bowl = _ellipsoid(0.021, 0.014, 0.006).trim_by_plane((0, 0, 1), 0.0)
    return handle + bowl.translate((0.01, 0, 0))


def tablespoon() -> m3.Manifold:
    handle = _box(0.13, 0.014, 0.0035).translate((-0.068, 0, 0.00175))
    bowl = _ellipsoid(0.028, 0.019, 0.008).trim_by_plane((0, 0, 1), 0.0)
    return handle + bowl.translate((0.012, 0, 0))


def fork() -> m3.Manifold:
    handle = _box(0.12, 0.013, 0.003).translate((-0.06, 0, 0.0015))
    head = _box(0.05, 0.024, 0.003).translate((0.025, 0, 0.0015))
    slots = [_box(0.032, 0.003, 0.01).translate((0.035, y, 0.0)) for y in (-0.006, 0.0, 0.006)]
    for slot in slots:
        head = head - slot
    return handle + head


def knife() -> m3.Manifold:
    handle = _box(0.1, 0.018, 0.012).translate((-0.05, 0, 0.006))
    blade = _box(0.11, 0.02, 0.002).translate((0.055, 0, 0.001))
    return handle + blade


def mug() -> m3.Manifold:
    body = _cyl(0.095, 0.04) - _cyl(0.095, 0.035).translate((0, 0, 0.008))
    # A D-shaped handle of straight bars: convex parts follow it exactly (a torus left a filled hole).
    handle = _box(0.035, 0.012, 0.065) - _box(0.023, 0.02, 0.043)
    return body + handle.translate((0.05, 0, 0.05))


def bowl() -> m3.Manifold:
    # A conical bowl of 24 flat facets: walls curved in one direction only, so a ring of convex parts
    # follows them (a hemispherical shell was still 6 mm off with 40 parts).
    outer = m3.Manifold.cylinder(0.06, 0.045, 0.08, 24)
    inner = m3.Manifold.cylinder(0.06, 0.039, 0.074, 24).translate((0, 0, 0.006))
    return outer - inner


def plate() -> m3.Manifold:
    return _cyl(0.016, 0.085, 0.11)


def soda_can() -> m3.Manifold:
    return _cyl(0.122, 0.033)


def soup_can() -> m3.Manifold:
    return _cyl(0.1, 0.038)


def bottle() -> m3.Manifold:
    body = _cyl(0.15, 0.035)
    shoulder = _cyl(0.04, 0.035, 0.013).translate((0, 0, 0.15))
    neck = _cyl(0.045, 0.013).translate((0, 0, 0.19))
    return body + shoulder + neck


def cereal_box() -> m3.Manifold:
    return _box(0.14, 0.05, 0.2)


def small_box() -> m3.Manifold:
    return _box(0.06, 0.06, 0.05)


@dataclass(frozen=True)
class AssetSpec:
    """What the author decides about one asset; everything else is measured from its mesh."""

    name: str
    category: str
    build: Callable[[], m3.Manifold]
    density: float  # kg/m^3 of the solid mesh (hollow goods get an effective density)
    friction: float  # sliding friction coefficient
    rgba: tuple[float, float, float, float]
    coacd: dict = field(default_factory=dict)  # overrides of COACD_DEFAULTS
    flat: bool = False  # lying on either face is normal (utensils): both flat poses count as upright


# Curved thin walls need many small parts to stay within 3 mm of the surface.
THIN_SHELL = {"threshold": 0.02, "max_convex_hull": 32}

ASSET_SPECS: tuple[AssetSpec, ...] = (
    AssetSpec("teaspoon", "spoon", teaspoon, 7800, 0.6, (0.75, 0.75, 0.78, 1), flat=True),
    AssetSpec("tablespoon", "spoon", tablespoon, 7800, 0.6, (0.7, 0.7, 0.74, 1), flat=True),
    AssetSpec("fork", "fork", fork, 7800, 0.6, (0.72, 0.72, 0.76, 1), flat=True),
    AssetSpec("knife", "knife", knife, 3000, 0.6, (0.2, 0.2, 0.22, 1), flat=True),
    AssetSpec("mug", "mug", mug, 2300, 0.8, (0.85, 0.3, 0.25, 1), THIN_SHELL),
    AssetSpec(
        "bowl", "bowl", bowl, 1500, 0.8, (0.9, 0.88, 0.8, 1), {"threshold": 0.02, "max_convex_hull": -1}
    ),
    AssetSpec("plate", "plate", plate, 900, 0.8, (0.95, 0.95, 0.95, 1)),
    AssetSpec("soda_can", "can", soda_can, 850, 0.7, (0.8, 0.1, 0.1, 1)),
    AssetSpec("soup_can", "can", soup_can, 1000, 0.7, (0.9, 0.7, 0.2, 1)),
    AssetSpec("bottle", "bottle", bottle, 600, 0.7, (0.2, 0.55, 0.3, 1), {"threshold": 0.01}),
    AssetSpec("cereal_box", "box", cereal_box, 250, 0.6, (0.95, 0.75, 0.2, 1)),
    AssetSpec("small_box", "box", small_box, 500, 0.6, (0.35, 0.45, 0.8, 1)),
)

COACD_DEFAULTS = {"threshold": 0.03, "preprocess_mode": "off", "max_convex_hull": 16, "seed": 0}


def to_trimesh(solid: m3.Manifold) -> trimesh.Trimesh:
    """Manifold -> trimesh, recentred on its centre of mass."""
    raw = solid.to_mesh()
    mesh = trimesh.Trimesh(np.asarray(raw.vert_properties)[:, :3], np.asarray(raw.tri_verts))
    mesh.apply_translation(-mesh.center_mass)
    return mesh


def build(out_dir: Path = ASSETS_DIR, only: set[str] | None = None) -> dict:
    """(Re)build meshes, convex parts and the catalog under ``out_dir``; returns the catalog."""
    (out_dir / "meshes").mkdir(parents=True, exist_ok=True)
    (out_dir / "parts").mkdir(parents=True, exist_ok=True)
    entries = []
    for spec in ASSET_SPECS:
        if only and spec.name not in only:
            continue
        t0 = time.perf_counter()
        mesh = to_trimesh(spec.build())
        if not mesh.is_watertight:
            raise RuntimeError(f"asset {spec.name}: authored mesh is not watertight")
        obj = export_obj(mesh)
        mesh = trimesh.load(trimesh.util.wrap_as_stream(obj), file_type="obj", process=False)
        mesh_file = out_dir / "meshes" / f"{spec.name}.obj"
        mesh_file.write_bytes(obj)
        mesh_sha = sha256_bytes(obj)

        params = {**COACD_DEFAULTS, **spec.coacd}
        key = parts_key(mesh_sha, coacd_version(), params)
        part_dir = out_dir / "parts" / spec.name / key
        if part_dir.exists():
            parts = [trimesh.load(p, process=False) for p in sorted(part_dir.glob("part_*.obj"))]
        else:
            parts = convex_parts(mesh, params)
            part_dir.mkdir(parents=True)
            for i, part in enumerate(parts):
                (part_dir / f"part_{i:03d}.obj").write_bytes(export_obj(part))
            parts = [trimesh.load(p, process=False) for p in sorted(part_dir.glob("part_*.obj"))]
        hausdorff = hull_to_visual_distance(mesh, parts)
        entries.append(
            {
                "name": spec.name,
                "category": spec.category,
                "mesh": f"meshes/{spec.name}.obj",
                "mesh_sha256": mesh_sha,
                "parts": {
                    "key": key,
                    "coacd_version": coacd_version(),
                    "params": params,
                    "files": [f"parts/{spec.name}/{key}/part_{i:03d}.obj" for i in range(len(parts))],
                },
                "density": spec.density,
                **inertial(mesh, spec.density),
                "friction": spec.friction,
                "rgba": list(spec.rgba),
                "extents": [round(float(e), 5) for e in mesh.extents],
                "hull_to_visual_mm": round(hausdorff * 1000, 3),
                "resting_poses": resting_poses(mesh, spec.flat),
            }
        )
        print(
            f"{spec.name:12s} parts={len(parts):2d} hausdorff={hausdorff * 1000:.2f} mm "
            f"poses={len(entries[-1]['resting_poses'])} ({time.perf_counter() - t0:.1f} s)"
        )
    catalog = {"version": 1, "assets": entries}
    header = (
        "# Generated by `python -m scenegen.assets.authoring`; edit scenegen/assets/authoring.py instead.\n"
    )
    (out_dir / "catalog.yaml").write_text(header + yaml.safe_dump(catalog, sort_keys=False, width=100))
    return catalog


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="asset names to rebuild (default: all)")
    args = parser.parse_args()
    build(only=set(args.only) if args.only else None)
