"""Convex-part geometry of a scene: objects as their assets' coacd parts (python-fcl convex shapes and
polytopes for the separating-axis test), furniture as boxes, and the signed distance between them.

Part of the core: numpy, scipy and python-fcl over the asset catalog and the layout; no MuJoCo. The
check stage's collision and clearance checks and the proposers' overlap projection (propose/separate.py)
use the same solids, so a projection and the check that follows it cannot disagree.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import fcl
import numpy as np
from scipy.spatial import ConvexHull

from scenegen.assets.catalog import Catalog, part_vertices_at
from scenegen.core.rotations import quat_to_matrix
from scenegen.schema.scene import ObjectPlacement


@dataclass(frozen=True)
class Polytope:
    """A convex piece in the world frame for the separating-axis test: vertices (V, 3), unit face
    normals (F, 3) and unit edge directions (E, 3)."""

    verts: np.ndarray
    normals: np.ndarray
    edges: np.ndarray

    @functools.cached_property
    def lo(self) -> np.ndarray:
        return self.verts.min(0)

    @functools.cached_property
    def hi(self) -> np.ndarray:
        return self.verts.max(0)

    @classmethod
    def of(cls, verts: np.ndarray, faces: np.ndarray) -> Polytope:
        tri = verts[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        pairs = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        keys = np.unique(pairs[:, 0].astype(np.int64) * len(verts) + pairs[:, 1])  # each edge once
        edges = verts[keys % len(verts)] - verts[keys // len(verts)]
        return cls(verts, _unit_rows(normals), _unit_rows(edges))


def _unit_rows(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit length, near-zero rows dropped, near-duplicate directions merged."""
    norm = np.linalg.norm(v, axis=1)
    v = v[norm > 1e-9] / norm[norm > 1e-9, None]
    v = np.where(v[:, [0]] + 1e-9 * v[:, [1]] < 0, -v, v)  # one sign per direction
    return unique_rows(np.round(v, 6))


def unique_rows(v: np.ndarray) -> np.ndarray:
    """The distinct rows of ``v`` (N, D) in lexicographic order: ``np.unique(v, axis=0)``'s values at
    a fraction of its cost (it sorts a structured copy)."""
    if len(v) < 2:
        return v
    v = v[np.lexsort(v.T[::-1])]
    keep = np.concatenate([[True], np.any(v[1:] != v[:-1], axis=1)])
    return v[keep]


def penetration_depth(a: Polytope, b: Polytope) -> float:
    """Minimum translation (m) that separates two intersecting convex polytopes.

    Separating-axis theorem: for convex polyhedra the smallest overlap over the face normals of both
    and the cross products of their edge pairs is the penetration depth (0 if they only touch).
    """
    faces = _overlaps(a, b, np.concatenate([a.normals, b.normals]))
    if faces <= 0.0:
        return 0.0  # a face plane separates them: no need for the many edge-pair axes
    cross = np.cross(a.edges[:, None, :], b.edges[None, :, :]).reshape(-1, 3)
    norm = np.linalg.norm(cross, axis=1)
    edges = _overlaps(a, b, cross[norm > 1e-6] / norm[norm > 1e-6, None])
    return max(0.0, min(faces, edges))


def _overlaps(a: Polytope, b: Polytope, axes: np.ndarray) -> float:
    """The smallest overlap (m) of the two polytopes' shadows on ``axes`` (N, 3); inf without axes."""
    if not len(axes):
        return math.inf
    pa, pb = a.verts @ axes.T, b.verts @ axes.T
    return float(np.minimum(pa.max(0) - pb.min(0), pb.max(0) - pa.min(0)).min())


@dataclass(frozen=True)
class Solid:
    """A named collision body for fcl: one or more convex pieces with their world AABB, and each
    piece as a :class:`Polytope` where it is one (None for the robot's rounded geoms)."""

    name: str
    pieces: tuple[fcl.CollisionObject, ...]
    lo: np.ndarray
    hi: np.ndarray
    polytopes: tuple[Polytope | None, ...] = ()


@functools.lru_cache(maxsize=256)
def _convex_geometry(
    root: Path, files: tuple[str, ...], part: int, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    return convex_hull(part_vertices_at(root, files)[part] * scale)


def convex_hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of points: its vertices (V, 3) and triangles (F, 3) indexing them."""
    hull = ConvexHull(points)
    remap = {old: new for new, old in enumerate(hull.vertices)}
    faces = np.array([[remap[i] for i in simplex] for simplex in hull.simplices])
    return points[hull.vertices], faces


def fcl_convex(verts: np.ndarray, faces: np.ndarray) -> fcl.Convex:
    flat = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    return fcl.Convex(verts, len(faces), flat)


def object_solid(catalog: Catalog, obj: ObjectPlacement) -> Solid:
    asset = catalog.get(obj.asset)
    rot = quat_to_matrix(obj.quat)
    pos = np.asarray(obj.position, float)
    pieces, corners, polytopes = [], [], []
    for i in range(len(asset.parts.files)):
        verts, faces = _convex_geometry(asset.folder, asset.parts.files, i, obj.scale)
        pieces.append(fcl.CollisionObject(fcl_convex(verts, faces), fcl.Transform(rot, pos)))
        corners.append(verts @ rot.T + pos)
        polytopes.append(Polytope.of(corners[-1], faces))
    pts = np.concatenate(corners)
    return Solid(obj.name, tuple(pieces), pts.min(0), pts.max(0), tuple(polytopes))


@dataclass(frozen=True)
class MovableSolid:
    """An object's convex pieces as polytopes only (no fcl), cheap to translate: the overlap
    projection's view of an object (propose/separate.py). ``rotated``: each piece's vertices (V, 3)
    in the world's orientation, not yet translated, so that :meth:`at` gives, bit for bit, the
    vertices :func:`object_solid` would build at that position; face normals and edge directions do
    not change with a translation and are computed once."""

    name: str
    rotated: tuple[np.ndarray, ...]
    shapes: tuple[Polytope, ...]  # the pieces at the first position: their normals and edges

    @classmethod
    def of(cls, catalog: Catalog, obj: ObjectPlacement) -> MovableSolid:
        asset = catalog.get(obj.asset)
        rot = quat_to_matrix(obj.quat)
        pos = np.asarray(obj.position, float)
        rotated, shapes = [], []
        for i in range(len(asset.parts.files)):
            verts, faces = _convex_geometry(asset.folder, asset.parts.files, i, obj.scale)
            rotated.append(verts @ rot.T)
            shapes.append(Polytope.of(verts @ rot.T + pos, faces))
        return cls(obj.name, tuple(rotated), tuple(shapes))

    def at(self, position: Sequence[float]) -> Solid:
        """The pieces at ``position`` (m) as a polytope-only :class:`Solid` (no fcl pieces)."""
        pos = np.asarray(position, float)
        polytopes = tuple(
            Polytope(r + pos, s.normals, s.edges) for r, s in zip(self.rotated, self.shapes, strict=True)
        )
        lo = np.min([q.lo for q in polytopes], axis=0)
        hi = np.max([q.hi for q in polytopes], axis=0)
        return Solid(self.name, (), lo, hi, polytopes)


def overlap_depth(a: Solid, b: Solid) -> float:
    """Deepest interpenetration (m) of any pair of the two solids' convex pieces, 0 when none
    overlaps, by the separating-axis test alone, no fcl (the pieces' boxes, then their face normals
    as a boolean test, then the edge-pair axes for the depth): what the overlap projection needs,
    where :func:`signed_distance` also measures the gaps of separated pieces. Equal to
    ``-signed_distance(a, b)`` whenever that is negative; both solids must be polytopes."""
    best = 0.0
    for qa in a.polytopes:
        for qb in b.polytopes:
            if np.any(qa.lo > qb.hi) or np.any(qb.lo > qa.hi):
                continue  # boxes apart: so are the pieces
            best = max(best, penetration_depth(qa, qb))
    return best


def box_solid(name: str, boxes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> Solid:
    pieces, corners, polytopes = [], [], []
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    for center, rot, half in boxes:
        pieces.append(fcl.CollisionObject(fcl.Box(*(2 * half)), fcl.Transform(rot, center)))
        corners.append((signs * half) @ rot.T + center)
        polytopes.append(Polytope(corners[-1], _unit_rows(rot.T.copy()), _unit_rows(rot.T.copy())))
    pts = np.concatenate(corners)
    return Solid(name, tuple(pieces), pts.min(0), pts.max(0), tuple(polytopes))


def signed_distance(a: Solid, b: Solid) -> float:
    """Minimum signed distance (m) between two solids: negative is penetration depth.

    Per pair of convex pieces: fcl's boolean GJK test; a separated pair gets fcl's GJK distance, an
    intersecting (or touching) pair minus its :func:`penetration_depth` (separating axes; for the
    robot's rounded geoms, fcl's MPR contact depth, an estimate). fcl's own signed distance (EPA) is
    not used: on deeply interpenetrating pieces (two bowls 4.5 cm apart) it throws a C++
    std::logic_error that aborts the whole process (python-fcl 0.7), which Python cannot catch.
    """
    best = math.inf
    test = fcl.CollisionRequest()
    contact = fcl.CollisionRequest(num_max_contacts=1, enable_contact=True)
    request = fcl.DistanceRequest()
    poly_a = a.polytopes or (None,) * len(a.pieces)
    poly_b = b.polytopes or (None,) * len(b.pieces)
    for pa, qa in zip(a.pieces, poly_a, strict=True):
        for pb, qb in zip(b.pieces, poly_b, strict=True):
            d = -1.0
            if not fcl.collide(pa, pb, test, fcl.CollisionResult()):
                d = fcl.distance(pa, pb, request, fcl.DistanceResult())  # -1 when it finds contact
            if d < 0.0:
                if qa is not None and qb is not None:
                    d = -penetration_depth(qa, qb)
                else:
                    result = fcl.CollisionResult()
                    fcl.collide(pa, pb, contact, result)
                    d = -max((c.penetration_depth for c in result.contacts), default=0.0)
            best = min(best, d)
    return best


def aabb_overlap(a: Solid, b: Solid, margin: float) -> bool:
    return bool(np.all(a.lo - margin <= b.hi) and np.all(b.lo - margin <= a.hi))
