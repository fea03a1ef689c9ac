"""The tabletop's fixed geometry as numbers: the table, the furniture kinds, and the surfaces objects
rest on (table, floor strip, furniture tops, the flat tops of objects for stacking).

Pure: numpy, the schema and the asset catalog. Every stage that reasons about supports (proposers,
the generator's encoding and cost, check, settle, tag) reads them here; the MuJoCo back end
(scenegen/sim/world.py) builds its bodies from the same numbers.

Frame: MuJoCo world, metres. The table top is the plane z = ``TABLE_TOP_Z`` over the rectangle
|x| <= TABLE_SIZE[0]/2, |y| <= TABLE_SIZE[1]/2; the robot base sits behind it at negative x.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from scenegen.assets.catalog import Asset, Catalog, convex_part_vertices, part_vertices, part_vertices_at
from scenegen.core.rotations import quat_to_matrix, yaw_matrix
from scenegen.schema.scene import FurniturePlacement, ObjectPlacement

TABLE_SIZE = (0.8, 1.0, 0.05)  # full x, y extents and thickness (m)
TABLE_TOP_Z = 0.8
# The Panda's shoulder, the origin of robot0_link1 in the world frame (m): fixed by where the robot
# stands behind the table, not by its joint angles (joint 1 turns about this point's vertical axis).
# tests/sim/test_world.py checks it against the MuJoCo model at every named pose.
SHOULDER = (-0.56, 0.0, 1.245)
# The arm's envelope around the shoulder (m): a grasp point nearer than 0.25 or farther than 0.95 is
# out of reach (Panda: 0.855 m to the flange, plus the hand; an envelope, not IK). The reachability
# check's defaults, the generator's reach cost and the projection repairs share it.
REACH = (0.25, 0.95)
# An asset others may be stacked on (``stack`` support) has, standing upright (or in its most likely
# pose), a flat top holding a circle of this radius (m): the bundled boxes, plate and cans (2.5 cm and
# up), not the spoons, fork, knife, bottle, mug or bowl (1.6 cm and down). See is_stack_base.
STACK_BASE_MIN_RADIUS = 0.02
# A box-like asset (convex hull filling this much of its bounding box) has a flat top in every pose.
BOX_FILL = 0.9
# Home positions (x, y on the table, m) of the furniture pieces; procedural jitter moves them.
FURNITURE_HOME: dict[str, tuple[float, float]] = {"shelf": (0.24, 0.27), "bin": (0.2, -0.3)}


def is_stack_base(asset: Asset) -> bool:
    """Whether others may be stacked on ``asset``: its flat top, upright (or in its most likely pose),
    holds a circle of STACK_BASE_MIN_RADIUS, measured on its convex parts."""
    return _flat_top_radius(asset.root, asset.parts.files, _base_pose(asset)) >= STACK_BASE_MIN_RADIUS


def is_box_like(asset: Asset) -> bool:
    """Whether ``asset`` has a flat top in every resting pose: its convex hull fills BOX_FILL of its
    bounding box (a box: 1.0; a can: 0.79)."""
    from scipy.spatial import ConvexHull

    points = np.concatenate(part_vertices(asset))
    return ConvexHull(points).volume >= BOX_FILL * float(np.prod(np.ptp(points, axis=0)))


def _base_pose(asset: Asset) -> tuple[float, float, float, float]:
    upright = asset.upright_pose()
    return asset.resting_poses[upright if upright is not None else 0].quat


@functools.lru_cache(maxsize=256)
def _flat_top_radius(root, files: tuple[str, ...], quat: tuple[float, ...]) -> float:
    """Radius (m) of the largest circle about the centre of a convex part's top face that the face
    holds, over the parts whose top is the object's top (within 1.5 mm), in pose ``quat``."""
    from scipy.spatial import ConvexHull, QhullError

    rot = quat_to_matrix(quat)
    parts = [v @ rot.T for v in part_vertices_at(root, files)]
    z_top = max(p[:, 2].max() for p in parts)
    best = 0.0
    for p in parts:
        top = p[p[:, 2] >= z_top - 0.0015][:, :2]
        if len(top) < 3:
            continue
        try:
            hull = ConvexHull(top)
        except QhullError:  # a line or a point: no area
            continue
        centre = top.mean(axis=0)
        best = max(best, float(np.min(-(hull.equations[:, :2] @ centre + hull.equations[:, 2]))))
    return best


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in a furniture body's frame: centre and half sizes (m)."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]


@dataclass(frozen=True)
class FurnitureKind:
    """Boxes of a furniture piece (its frame: origin at the centre of its footprint on the table) and
    the surface objects can rest on (height above the table top, half extents of its inner region)."""

    boxes: tuple[Box, ...]
    surface_height: float
    surface_half: tuple[float, float]
    rgba: tuple[float, float, float, float]


def _shelf() -> FurnitureKind:
    depth, width, height, t = 0.26, 0.42, 0.24, 0.02
    return FurnitureKind(
        boxes=(
            Box((0.0, -(width - t) / 2, (height - t) / 2), (depth / 2, t / 2, (height - t) / 2)),
            Box((0.0, (width - t) / 2, (height - t) / 2), (depth / 2, t / 2, (height - t) / 2)),
            Box((0.0, 0.0, height - t / 2), (depth / 2, width / 2, t / 2)),  # the overhanging board
        ),
        surface_height=height,
        surface_half=(depth / 2, width / 2),
        rgba=(0.55, 0.38, 0.22, 1.0),
    )


def _bin() -> FurnitureKind:
    lx, ly, h, t = 0.24, 0.30, 0.08, 0.01
    return FurnitureKind(
        boxes=(
            Box((0.0, 0.0, t / 2), (lx / 2, ly / 2, t / 2)),
            Box((-(lx - t) / 2, 0.0, h / 2), (t / 2, ly / 2, h / 2)),
            Box(((lx - t) / 2, 0.0, h / 2), (t / 2, ly / 2, h / 2)),
            Box((0.0, -(ly - t) / 2, h / 2), (lx / 2, t / 2, h / 2)),
            Box((0.0, (ly - t) / 2, h / 2), (lx / 2, t / 2, h / 2)),
        ),
        surface_height=t,
        surface_half=(lx / 2 - t, ly / 2 - t),
        rgba=(0.3, 0.35, 0.4, 1.0),
    )


FURNITURE: dict[str, FurnitureKind] = {"shelf": _shelf(), "bin": _bin()}


@dataclass(frozen=True)
class Surface:
    """A horizontal support surface in the world frame: height z, centre, half extents, yaw (rad)."""

    name: str
    z: float
    center: tuple[float, float]
    half: tuple[float, float]
    yaw: float = 0.0

    def local_xy(self, xy: Sequence[float]) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = xy[0] - self.center[0], xy[1] - self.center[1]
        return np.array([c * dx + s * dy, -s * dx + c * dy])

    def margin(self, xy: Sequence[float]) -> float:
        """Signed distance (m) from a point to the surface's boundary; positive inside."""
        local = np.abs(self.local_xy(xy))
        return float(min(self.half[0] - local[0], self.half[1] - local[1]))


# The floor strip beside the table (+y side) where an object may lie on the floor (``on_floor``).
FLOOR = Surface("floor", 0.0, (0.0, TABLE_SIZE[1] / 2 + 0.18), (0.35, 0.12))


def support_surfaces(
    furniture: Sequence[FurniturePlacement],
    objects: Sequence[ObjectPlacement] = (),
    catalog: Catalog | None = None,
) -> dict[str, Surface]:
    """Surfaces objects can rest on, keyed by name: ``table``, ``floor``, each furniture piece, and
    (given the catalog) the flat top of each object, under the object's name (stacking)."""
    surfaces = {
        "table": Surface("table", TABLE_TOP_Z, (0.0, 0.0), (TABLE_SIZE[0] / 2, TABLE_SIZE[1] / 2)),
        "floor": FLOOR,
    }
    for piece in furniture:
        kind = FURNITURE[piece.kind]
        surfaces[piece.name] = Surface(
            piece.name,
            TABLE_TOP_Z + kind.surface_height,
            (piece.position[0], piece.position[1]),
            kind.surface_half,
            piece.yaw,
        )
    if catalog is not None:
        for obj in objects:
            surfaces[obj.name] = object_top_surface(catalog, obj)
    return surfaces


def object_top_surface(catalog: Catalog, obj: ObjectPlacement, tolerance: float = 0.0015) -> Surface:
    """The top of an object as a support: its highest convex-part vertices (within ``tolerance``),
    bounded by a rectangle in the object's yaw frame. A pointed or round top gives a tiny region."""
    rot = quat_to_matrix(obj.quat)
    pts = np.concatenate(convex_part_vertices(catalog, obj.asset)) * obj.scale @ rot.T
    top = pts[pts[:, 2] >= pts[:, 2].max() - tolerance]
    x_axis = rot[:, 0] if np.hypot(rot[0, 0], rot[1, 0]) > 1e-6 else rot[:, 1]
    yaw = math.atan2(x_axis[1], x_axis[0])
    c, s = math.cos(yaw), math.sin(yaw)
    local = top[:, :2] @ np.array([[c, -s], [s, c]])  # world offsets -> yaw frame
    lo, hi = local.min(axis=0), local.max(axis=0)
    mid = (lo + hi) / 2
    center = np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1]]) + obj.position[:2]
    return Surface(
        obj.name,
        float(obj.position[2] + pts[:, 2].max()),
        (float(center[0]), float(center[1])),
        (float((hi - lo)[0] / 2), float((hi - lo)[1] / 2)),
        yaw,
    )


def furniture_boxes(piece: FurniturePlacement) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """World-frame boxes of a furniture piece: (centre (3,), rotation (3, 3), half sizes (3,))."""
    rot = yaw_matrix(piece.yaw)
    origin = np.array([piece.position[0], piece.position[1], TABLE_TOP_Z])
    return [
        (origin + rot @ np.array(box.center), rot, np.array(box.half)) for box in FURNITURE[piece.kind].boxes
    ]


def _box_corners(asset: Asset, pose: int) -> np.ndarray:
    """(8, 3) corners of the asset's bounding box in resting pose ``pose`` (yaw 0), about its origin."""
    ext = np.asarray(asset.extents) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * ext
    return corners @ quat_to_matrix(asset.resting_poses[pose].quat).T


def _footprint_corners(asset: Asset, pose: int) -> np.ndarray:
    """xy (8, 2) of the corners of the asset's bounding box in resting pose ``pose`` (yaw 0)."""
    return _box_corners(asset, pose)[:, :2]


def pose_top(asset: Asset, pose: int) -> float:
    """Height (m) of the asset's top above its origin when it rests in pose ``pose`` (its bounding
    box's height less the origin's height above the support)."""
    z = _box_corners(asset, pose)[:, 2]
    return float(z.max() - z.min() - asset.resting_poses[pose].height)


def footprint_radius(asset: Asset, pose: int) -> float:
    """Radius (m) of a circle that holds the asset's footprint in resting pose ``pose``, any yaw."""
    return float(np.linalg.norm(_footprint_corners(asset, pose), axis=1).max())


def footprint_half_extents(asset: Asset, pose: int) -> np.ndarray:
    """Half extents (m, x and y) of the asset's footprint box in resting pose ``pose`` at yaw 0."""
    return np.abs(_footprint_corners(asset, pose)).max(0)


def edge_margin(points: np.ndarray) -> float:
    """The smallest distance (m) from any of ``points`` (N, 3) to a table edge in the plane; negative
    past it. The near_edge predicate's value, and what its projection measures before a check."""
    hx, hy = TABLE_SIZE[0] / 2, TABLE_SIZE[1] / 2
    return float(min((hx - np.abs(points[:, 0])).min(), (hy - np.abs(points[:, 1])).min()))


def overhang_cover(points: np.ndarray, furniture) -> float:
    """The share of ``points`` (N, 3) that have a furniture box wholly above their highest point: the
    under_overhang predicate's value, and what its projection measures before a check."""
    top = points[:, 2].max()
    boxes = [box for piece in furniture for box in furniture_boxes(piece)]
    covered = 0
    for p in points:
        for centre, rot, half in boxes:
            local = rot.T @ (p - centre)
            if np.all(np.abs(local[:2]) <= half[:2]) and centre[2] - half[2] > top:
                covered += 1
                break
    return covered / len(points)


def stack_ground(proposal, name: str) -> str:
    """What the stack under object ``name`` of a SceneProposal stands on: "table", "floor" or a
    furniture piece's name (``name``'s own support when it rests on no object)."""
    objects = {o.name: o for o in proposal.objects}
    seen = set()
    while name in objects and name not in seen:
        seen.add(name)
        name = objects[name].support
    return name


def workspace_region(proposal, name: str) -> Surface:
    """The region object ``name``'s centre must lie over: the floor strip when its stack stands on the
    floor, else the table (the workspace check's, and where a projection puts it back)."""
    return FLOOR if stack_ground(proposal, name) == "floor" else support_surfaces(())["table"]


def furniture_overhang(piece: FurniturePlacement) -> float:
    """How far (m) the farthest corner of a furniture piece's boxes lies beyond the table top's edges
    (at most 0 when the piece stands wholly on the table): the furniture-support check's value."""
    corners = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)])
    worst = -math.inf
    for centre, rot, half in furniture_boxes(piece):
        xy = centre[:2] + (corners * half[:2]) @ rot[:2, :2].T
        beyond = np.abs(xy) - np.array(TABLE_SIZE[:2]) / 2
        worst = max(worst, float(beyond.max()))
    return worst


# How far the floor strip's table-side edge lies beyond the table's (+y) edge: a target whose centre is
# over the strip has its centre at least this far from anything standing wholly on the table.
FLOOR_GAP = FLOOR.center[1] - FLOOR.half[1] - TABLE_SIZE[1] / 2


def floor_cover_bound(points: np.ndarray, yaws: int = 72) -> float:
    """The largest share of an object's points (N, 3; about its centre, in a resting pose) that any of
    ``yaws`` yaws brings ``FLOOR_GAP`` or more toward the table: with its centre over the floor strip,
    no more of it can lie over the table, so a furniture board standing wholly on the table covers at
    most this share (an upper bound of the under_overhang predicate's value for a target on the floor;
    the grid of yaws is checked against a finer one in tests/propose/test_refusals.py)."""
    angles = np.linspace(0.0, 2 * math.pi, yaws, endpoint=False)
    # y of each point after a yaw by a: x sin a + y cos a
    y = np.outer(np.sin(angles), points[:, 0]) + np.outer(np.cos(angles), points[:, 1])
    return float((y <= -FLOOR_GAP).mean(axis=1).max())
