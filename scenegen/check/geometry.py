"""Cheap geometric checks of a proposal, run before any physics, cheapest first.

workspace -> support -> collision (python-fcl over the assets' convex parts: an AABB broad phase, then
fcl's signed distance as narrow phase) -> robot clearance at the initial pose -> reachability.
Each check returns a :class:`CheckResult` with its label, measured value and threshold; the first
failure ends the sequence. A resting contact (signed distance ~0) is not a collision.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import fcl
import numpy as np
from pydantic import BaseModel, ConfigDict, model_serializer

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.core.solids import (
    Solid,
    aabb_overlap,
    box_solid,
    convex_hull,
    fcl_convex,
    object_solid,
    signed_distance,
)
from scenegen.schema.scene import CheckResult, SceneProposal
from scenegen.sim import world


class CheckSettings(BaseModel):
    """Thresholds of the geometric checks (metres)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    penetration_tolerance: float = 0.001  # deeper than this between parts is a collision
    support_height_tolerance: float = 0.002  # |object bottom - surface| allowed after snapping
    robot_clearance: float = 0.03  # minimum distance between objects/furniture and the robot
    reach_min: float = layout.REACH[0]  # grasp point distance from the shoulder (robot0_link1), m
    reach_max: float = layout.REACH[1]  # Panda: 0.855 m to the flange + hand; an envelope, not IK
    # Furniture stands wholly on the table (``furniture_overhang`` beyond this rejects): off by default,
    # so recipes made before the rule keep their digests and figures; the default recipe turns it on.
    furniture_on_table: bool = False
    furniture_tolerance: float = 0.001

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler):
        data = handler(self)  # a recipe without the rule dumps and hashes as before it existed
        if not data.get("furniture_on_table"):
            data.pop("furniture_on_table", None)
            data.pop("furniture_tolerance", None)
        return data


def _result(check: str, passed: bool, label: str, value: float, threshold: float, detail: str = ""):
    return CheckResult(
        stage="check",
        check=check,
        passed=passed,
        label=None if passed else label,
        value=round(float(value), 6),
        threshold=threshold,
        detail=detail,
    )


def check_workspace(proposal: SceneProposal, catalog: Catalog) -> CheckResult:
    """Every object's centre lies over the table, or over the floor strip beside it when it (or the
    stack it rests on) stands on the floor (value: worst margin to the region's edge, m)."""
    worst, who = math.inf, ""
    for obj in proposal.objects:
        margin = layout.workspace_region(proposal, obj.name).margin(obj.position[:2])
        if margin < worst:
            worst, who = margin, obj.name
    return _result("workspace", worst >= 0.0, "out_of_workspace", worst, 0.0, who)


def check_furniture(proposal: SceneProposal, settings: CheckSettings) -> CheckResult:
    """Every furniture piece stands wholly on the table (value: how far its farthest box corner lies
    beyond the table's edges, m; ``layout.furniture_overhang``)."""
    worst, who = -math.inf, ""
    for piece in proposal.furniture:
        beyond = layout.furniture_overhang(piece)
        if beyond > worst:
            worst, who = beyond, piece.name
    worst = worst if proposal.furniture else 0.0
    limit = settings.furniture_tolerance
    return _result("furniture_support", worst <= limit, "furniture_overhang", worst, limit, who)


def check_support(proposal: SceneProposal, catalog: Catalog, settings: CheckSettings) -> CheckResult:
    """Each object rests on its named support: centre over its region, bottom at its height.

    value: the worst of (margin of the centre inside the region, m) and (-|bottom - surface|, m).
    """
    surfaces = layout.support_surfaces(proposal.furniture, proposal.objects, catalog)
    worst, who = math.inf, ""
    for obj in proposal.objects:
        surface = surfaces.get(obj.support) if obj.support != obj.name else None
        if surface is None:
            return _result("support", False, "unsupported", -math.inf, 0.0, f"{obj.name}: no {obj.support}")
        asset = catalog.get(obj.asset)
        bottom = obj.position[2] - asset.resting_poses[obj.resting_pose].height * obj.scale
        gap = abs(bottom - surface.z)
        score = min(surface.margin(obj.position[:2]), settings.support_height_tolerance - gap)
        if score < worst:
            worst, who = score, obj.name
    return _result("support", worst >= 0.0, "unsupported", worst, 0.0, who)


def scene_solids(proposal: SceneProposal, catalog: Catalog) -> tuple[list[Solid], list[Solid]]:
    """(objects, furniture) as fcl solids in the world frame."""
    objects = [object_solid(catalog, obj) for obj in proposal.objects]
    furniture = [box_solid(p.name, layout.furniture_boxes(p)) for p in proposal.furniture]
    return objects, furniture


def check_collision(
    objects: Sequence[Solid], furniture: Sequence[Solid], settings: CheckSettings
) -> CheckResult:
    """Pairwise object-object and object-furniture penetration (value: min signed distance, m)."""
    worst, who = math.inf, ""
    others = [*objects, *furniture]
    for i, a in enumerate(objects):
        for b in others[i + 1 :]:
            if not aabb_overlap(a, b, settings.penetration_tolerance):  # broad phase
                continue
            d = signed_distance(a, b)
            if d < worst:
                worst, who = d, f"{a.name}~{b.name}"
    if worst is math.inf:
        worst = 1.0  # nothing near anything: report a large clearance
    threshold = -settings.penetration_tolerance
    return _result("collision", worst >= threshold, "collision", worst, threshold, who)


@functools.lru_cache(maxsize=8)
def robot_geometry(robot_pose: tuple[float, ...]) -> tuple[Solid, np.ndarray]:
    """The arm and gripper's collision geoms at ``robot_pose`` as one solid, and the shoulder position."""
    pieces, corners, shoulder = _robot_geoms(tuple(robot_pose))
    pts = np.concatenate(corners)
    return Solid("robot", pieces, pts.min(0), pts.max(0)), shoulder


@functools.lru_cache(maxsize=8)
def arm_discs(robot_pose: tuple[float, ...]) -> np.ndarray:
    """The arm's and gripper's collision geoms at ``robot_pose`` as discs in the table plane (G, 4):
    x, y of the centre of the geom's box, its lowest point z, the radius that holds its box (m).
    What the generator's soft arm clearance (diffusion/cost.py) keeps objects out of."""
    discs = []
    for c in _robot_geoms(tuple(robot_pose))[1]:
        centre = (c[:, :2].min(0) + c[:, :2].max(0)) / 2
        discs.append([*centre, c[:, 2].min(), float(np.linalg.norm(c[:, :2] - centre, axis=1).max())])
    return np.asarray(discs)


@functools.lru_cache(maxsize=8)
def _robot_geoms(robot_pose: tuple[float, ...]):
    """The arm and gripper's collision geoms at ``robot_pose``: fcl pieces, each geom's corners in the
    world frame (its vertices, box corners or bounding sphere's box), and the shoulder position."""
    import mujoco

    model = world.robot_spec().compile()
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = world.initial_state(model, robot_pose, [])
    mujoco.mj_forward(model, data)
    pieces, corners = [], []
    for g in range(model.ngeom):
        body = model.body(model.geom_bodyid[g]).name
        if not body.startswith(world.ROBOT_PREFIXES) or model.geom_contype[g] == 0:
            continue
        rot, pos = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            verts = model.mesh_vert[model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]]
            local, faces = convex_hull(verts)
            geom = fcl_convex(local, faces)
        elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            local = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            local = local * model.geom_size[g]
            geom = fcl.Box(*(2 * model.geom_size[g]))
        else:  # spheres, capsules, cylinders: bound by a sphere of their radius + half length
            r = float(model.geom_rbound[g])
            local = np.array([[-r, -r, -r], [r, r, r]])
            geom = fcl.Sphere(r)
        pieces.append(fcl.CollisionObject(geom, fcl.Transform(rot.copy(), pos.copy())))
        corners.append(local @ rot.T + pos)
    shoulder = data.body("robot0_link1").xpos.copy()
    return tuple(pieces), tuple(corners), shoulder


def check_robot_clearance(
    objects: Sequence[Solid], furniture: Sequence[Solid], robot: Solid, settings: CheckSettings
) -> CheckResult:
    """Distance (m) from the robot at its initial pose to the nearest object or furniture piece."""
    worst, who = math.inf, ""
    for solid in [*objects, *furniture]:
        if not aabb_overlap(solid, robot, settings.robot_clearance):
            continue
        d = signed_distance(solid, robot)
        if d < worst:
            worst, who = d, solid.name
    if worst is math.inf:
        worst = settings.robot_clearance + 1.0
    return _result(
        "robot_clearance",
        worst >= settings.robot_clearance,
        "robot_overlap",
        worst,
        settings.robot_clearance,
        who,
    )


def check_reachability(
    proposal: SceneProposal, catalog: Catalog, shoulder: np.ndarray, settings: CheckSettings
) -> CheckResult:
    """The target has a top or side approach whose grasp point lies in the arm's envelope.

    Top approach: grasp at the top of the object, open only if no furniture box lies above it.
    Side approach: grasp at mid-height from the robot's side; always open, so an object under a
    shelf is hard, not unreachable. value: the best approach's margin inside the envelope
    [reach_min, reach_max] around the shoulder (m).
    """
    obj = next(o for o in proposal.objects if o.name == proposal.target)
    if layout.stack_ground(proposal, obj.name) == "floor":
        # A target on the floor (or on a stack standing there) is outside a table-top arm's envelope by
        # construction: a recovery case for another base or robot, so it is recorded as hard, not
        # rejected.
        return CheckResult(
            stage="check", check="reachability", passed=True, detail=f"{obj.name} on the floor"
        )
    pos = np.asarray(obj.position)
    top = pos + [0, 0, catalog.get(obj.asset).resting_poses[obj.resting_pose].height * obj.scale]
    candidates = {"side": pos}
    boxes = [box for piece in proposal.furniture for box in layout.furniture_boxes(piece)]
    if not any(_over(top, box) for box in boxes):
        candidates["top"] = top
    best, how = -math.inf, ""
    for name, point in candidates.items():
        r = float(np.linalg.norm(point - shoulder))
        margin = min(r - settings.reach_min, settings.reach_max - r)
        if margin > best:
            best, how = margin, name
    return _result("reachability", best >= 0.0, "unreachable", best, 0.0, f"{obj.name} by {how}")


def _over(point: np.ndarray, box: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
    """Whether a world box (centre, rotation, half sizes) lies above ``point``, blocking a top approach."""
    center, rot, half = box
    local = rot.T @ (point - center)
    return bool(np.all(np.abs(local[:2]) <= half[:2]) and center[2] - half[2] > point[2])


def run_checks(
    proposal: SceneProposal, catalog: Catalog, settings: CheckSettings
) -> tuple[list[CheckResult], bool]:
    """All geometric checks, cheapest first; stops at the first failure. Returns (results, passed)."""
    results = [check_workspace(proposal, catalog)]
    if results[-1].passed and settings.furniture_on_table:
        results.append(check_furniture(proposal, settings))
    if results[-1].passed:
        results.append(check_support(proposal, catalog, settings))
    if not results[-1].passed:
        return results, False
    objects, furniture = scene_solids(proposal, catalog)
    results.append(check_collision(objects, furniture, settings))
    if not results[-1].passed:
        return results, False
    robot, shoulder = robot_geometry(tuple(proposal.condition.robot_pose))
    results.append(check_robot_clearance(objects, furniture, robot, settings))
    if not results[-1].passed:
        return results, False
    results.append(check_reachability(proposal, catalog, shoulder, settings))
    return results, results[-1].passed
