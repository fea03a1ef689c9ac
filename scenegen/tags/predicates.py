"""Rare-case predicates: measured facts about a settled scene and its target.

Every predicate is geometric (positions, meshes, MuJoCo ray casts), so no renderer is needed to tag a
scene. Each returns a :class:`TagValue`: the measured value, its threshold and unit, and whether the
tag holds (decided on the value rounded to 6 decimals, as stored, so the two always agree).
``nominal`` holds when no rare tag does. The predicate set carries a version
(:data:`PREDICATE_VERSION`), stamped into every scene, batch manifest, dataset and checkpoint, so
data tagged by different predicates is never mixed; it is bumped by hand when a predicate's output
changes, and tests/tags/test_predicate_panel.py fails until it is.

Frames: MuJoCo world, metres; the table top is the plane z = ``layout.TABLE_TOP_Z``.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.core.rotations import quat_to_matrix
from scenegen.schema.condition import Condition
from scenegen.schema.scene import (
    CheckResult,
    Contact,
    FurniturePlacement,
    Lighting,
    ObjectPlacement,
    TagValue,
)
from scenegen.sim import world


class TagSettings(BaseModel):
    """Thresholds of the predicates (metres, radians, counts, fractions)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    near_edge_distance: float = 0.03  # target footprint within this of a table edge (or past it)
    overhang_cover: float = 0.5  # fraction of the target footprint under a furniture box above it
    toppled_angle: float = math.radians(45)  # tilt of the target's authored up axis from vertical
    occluded_fraction: float = 0.5  # fraction of target sample points hidden from the main camera
    occlusion_points: int = 48
    clutter_radius: float = 0.2  # other objects with centres within this of the target (xy)
    clutter_count: int = 3
    low_light_irradiance: float = 0.25  # ambient + direct light reaching the target (unitless, 0..)
    on_floor_drop: float = 0.3  # target centre at least this far below the table top


@dataclass
class TagContext:
    """What the predicates look at: a settled scene (model with data at its settled state) and its target."""

    model: mujoco.MjModel
    data: mujoco.MjData
    target: str
    objects: Sequence[str]
    furniture: Sequence[FurniturePlacement]
    lighting: Lighting
    camera_position: np.ndarray  # the main camera (first camera of the scene)
    contacts: Sequence[Contact]
    upright_axes: np.ndarray  # (k, 3) world-up in the target's body frame for each upright resting pose
    orientation_free: bool = False  # the target is round: no way of lying is toppled

    @classmethod
    def of_scene(
        cls,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        catalog: Catalog,
        target: str,
        objects: Sequence[ObjectPlacement],
        furniture: Sequence[FurniturePlacement],
        lighting: Lighting,
        camera_position: Sequence[float],
        contacts: Sequence[Contact],
    ) -> TagContext:
        """The context of a settled scene (``data`` forwarded at its settled state)."""
        asset = catalog.get(next(o.asset for o in objects if o.name == target))
        axes = [quat_to_matrix(p.quat)[2, :] for p in asset.resting_poses if p.upright]
        return cls(
            model,
            data,
            target,
            [o.name for o in objects],
            furniture,
            lighting,
            np.asarray(camera_position, float),
            contacts,
            np.array(axes).reshape(-1, 3),
            asset.orientation_free,
        )


Predicate = Callable[[TagContext, TagSettings], TagValue]
PREDICATES: dict[str, Predicate] = {}


def predicate(name: str):
    """Register a rare-case predicate under its tag name."""

    def decorate(fn: Predicate) -> Predicate:
        PREDICATES[name] = fn
        return fn

    return decorate


def _measured(value: float, threshold: float, unit: str, holds: Callable[[float, float], bool]) -> TagValue:
    """A predicate's result, decided on the value rounded to 6 decimals as it is stored."""
    value = round(float(value), 6)
    return TagValue(holds=bool(holds(value, threshold)), value=value, threshold=threshold, unit=unit)


def _geom_points(ctx: TagContext, body: str, group: int) -> np.ndarray:
    """World-frame vertices (N, 3) of a body's mesh geoms in ``group``."""
    m, d = ctx.model, ctx.data
    body_id = m.body(body).id
    points = []
    for g in range(m.ngeom):
        if (
            m.geom_bodyid[g] != body_id
            or m.geom_group[g] != group
            or m.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH
        ):
            continue
        mesh = m.geom_dataid[g]
        local = m.mesh_vert[m.mesh_vertadr[mesh] : m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
        points.append(local @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g])
    return np.concatenate(points) if points else np.zeros((0, 3))


def _hull_points(ctx: TagContext) -> np.ndarray:
    return _geom_points(ctx, ctx.target, world.COLLISION_GROUP)


@predicate("near_edge")
def near_edge(ctx: TagContext, s: TagSettings) -> TagValue:
    """Smallest distance (m) from the target's footprint to a table edge; negative = overhanging."""
    pts = _hull_points(ctx)
    on_table = pts[:, 2].min() > layout.TABLE_TOP_Z - 0.01
    margin = layout.edge_margin(pts)
    return _measured(margin, s.near_edge_distance, "m", lambda v, t: on_table and v <= t)


@predicate("under_overhang")
def under_overhang(ctx: TagContext, s: TagSettings) -> TagValue:
    """Fraction of the target's footprint points that have a furniture box above the target's top."""
    cover = layout.overhang_cover(_hull_points(ctx), ctx.furniture)
    return _measured(cover, s.overhang_cover, "fraction", operator.ge)


@predicate("toppled")
def toppled(ctx: TagContext, s: TagSettings) -> TagValue:
    """Angle (rad) between the target's orientation and its nearest upright resting pose, yaw aside:
    the angle between world-up seen in the body frame now and in that pose (0 for a round target)."""
    if ctx.orientation_free:
        return _measured(0.0, round(s.toppled_angle, 6), "rad", operator.gt)
    up_now = ctx.data.body(ctx.target).xmat.reshape(3, 3)[2, :]  # third row = world z in body frame
    axes = ctx.upright_axes if len(ctx.upright_axes) else np.array([[0.0, 0.0, 1.0]])
    angle = min(math.acos(max(-1.0, min(1.0, float(np.dot(up_now, a) / np.linalg.norm(a))))) for a in axes)
    return _measured(angle, round(s.toppled_angle, 6), "rad", operator.gt)


def _sample_indices(n: int, k: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int))


def _visible_side_points(ctx: TagContext, k: int) -> np.ndarray:
    """Up to ``k`` centroids of the target's visual-mesh faces that face the main camera (world frame)."""
    m, d = ctx.model, ctx.data
    body_id = m.body(ctx.target).id
    centroids, normals = [], []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != body_id or m.geom_group[g] != world.VISUAL_GROUP:
            continue
        mesh = m.geom_dataid[g]
        verts = m.mesh_vert[m.mesh_vertadr[mesh] : m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
        faces = m.mesh_face[m.mesh_faceadr[mesh] : m.mesh_faceadr[mesh] + m.mesh_facenum[mesh]]
        world_verts = verts @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
        tri = world_verts[faces]
        centroids.append(tri.mean(axis=1))
        normals.append(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    if not centroids:
        return np.zeros((0, 3))
    c, nrm = np.concatenate(centroids), np.concatenate(normals)
    facing = np.einsum("ij,ij->i", nrm, ctx.camera_position - c) > 0
    c = c[facing]
    return c[_sample_indices(len(c), k)] if len(c) else c


@predicate("occluded")
def occluded(ctx: TagContext, s: TagSettings) -> TagValue:
    """Fraction of sample points on the camera-facing side of the target whose ray from the main camera
    hits another body first (mujoco.mj_ray over visible geoms). A target facing away entirely counts
    as hidden (1.0)."""
    pts = _visible_side_points(ctx, s.occlusion_points)
    if not len(pts):
        return TagValue(holds=True, value=1.0, threshold=s.occluded_fraction, unit="fraction")
    cam = np.asarray(ctx.camera_position, float)
    geomgroup = np.zeros(6, np.uint8)
    geomgroup[world.VISUAL_GROUP] = 1
    target_id = ctx.model.body(ctx.target).id
    geomid = np.zeros(1, np.int32)
    hidden = 0
    for p in pts:
        vec = p - cam
        reach = float(np.linalg.norm(vec))
        dist = mujoco.mj_ray(ctx.model, ctx.data, cam, vec / reach, geomgroup, 1, -1, geomid)
        if geomid[0] >= 0 and ctx.model.geom_bodyid[geomid[0]] != target_id and dist < reach - 1e-3:
            hidden += 1
    return _measured(hidden / len(pts), s.occluded_fraction, "fraction", operator.ge)


@predicate("clutter")
def clutter(ctx: TagContext, s: TagSettings) -> TagValue:
    """Number of other objects whose centres lie within ``clutter_radius`` of the target (xy)."""
    t = ctx.data.body(ctx.target).xpos[:2]
    count = sum(
        1
        for name in ctx.objects
        if name != ctx.target and np.linalg.norm(ctx.data.body(name).xpos[:2] - t) <= s.clutter_radius
    )
    return _measured(count, float(s.clutter_count), "objects", operator.ge)


@predicate("stacked")
def stacked(ctx: TagContext, s: TagSettings) -> TagValue:
    """Number of other objects the target rests on (settled contacts)."""
    names = set(ctx.objects)
    count = sum(1 for c in ctx.contacts if c.a == ctx.target and c.kind == "rests_on" and c.b in names)
    return _measured(count, 1.0, "objects", operator.ge)


@predicate("low_light")
def low_light(ctx: TagContext, s: TagSettings) -> TagValue:
    """Light reaching the top of the target: mean ambient + sum over lights of colour x intensity x
    spot falloff x cos(incidence on an upward surface), each light only if a shadow ray from the
    target to it is unobstructed (for lights that cast shadows; the others, like the renderer, pass
    through)."""
    m, d = ctx.model, ctx.data
    pts = _hull_points(ctx)
    point = np.array([pts[:, 0].mean(), pts[:, 1].mean(), pts[:, 2].max() + 1e-3])
    target_id = m.body(ctx.target).id
    geomgroup = np.zeros(6, np.uint8)
    geomgroup[world.VISUAL_GROUP] = 1
    irradiance = float(np.mean(ctx.lighting.ambient))
    geomid = np.zeros(1, np.int32)
    for i, light in enumerate(ctx.lighting.lights):
        lid = m.light(f"light{i}").id
        to_light = d.light_xpos[lid] - point
        distance = float(np.linalg.norm(to_light))
        direction = to_light / distance
        spot_axis = d.light_xdir[lid] / np.linalg.norm(d.light_xdir[lid])
        cos_spot = float(np.dot(-direction, spot_axis))
        if cos_spot < math.cos(math.radians(m.light_cutoff[lid])):
            continue
        hit = mujoco.mj_ray(m, d, point, direction, geomgroup, 1, target_id, geomid)
        if light.cast_shadow and 0 <= hit < distance:
            continue  # in shadow (a light without shadows is not blocked, as in the render)
        falloff = cos_spot ** m.light_exponent[lid]
        incidence = max(0.0, float(direction[2]))
        irradiance += float(np.mean(light.colour)) * light.intensity * falloff * incidence
    return _measured(irradiance, s.low_light_irradiance, "irradiance", operator.lt)


@predicate("on_floor")
def on_floor(ctx: TagContext, s: TagSettings) -> TagValue:
    """How far (m) the target's centre is below the table top; holds for a target on the floor."""
    drop = layout.TABLE_TOP_Z - float(ctx.data.body(ctx.target).xpos[2])
    return _measured(drop, s.on_floor_drop, "m", operator.ge)


def measure_tags(ctx: TagContext, settings: TagSettings | None = None) -> dict[str, TagValue]:
    """Every rare tag's measurement, plus ``nominal`` (holds when none of them does)."""
    settings = settings or TagSettings()
    tags = {name: fn(ctx, settings) for name, fn in PREDICATES.items()}
    held = sum(t.holds for t in tags.values())
    tags["nominal"] = TagValue(holds=held == 0, value=float(held), threshold=0.0, unit="rare tags held")
    return tags


def scene_tags(model, data, catalog, proposal, contacts, settings: TagSettings | None = None) -> dict:
    """Every tag (:func:`measure_tags`) of a proposal's scene settled in ``data``, measured from the
    proposal's main camera (its first); ``contacts``: the settled contact configuration."""
    context = TagContext.of_scene(
        model,
        data,
        catalog,
        proposal.target,
        proposal.objects,
        proposal.furniture,
        proposal.lighting,
        proposal.cameras[0].position,
        contacts,
    )
    return measure_tags(context, settings)


def condition_check(tags: dict[str, TagValue], condition: Condition) -> CheckResult:
    """``condition_unmet`` when a required tag does not hold or a forbidden one does."""
    missing = [t for t in condition.required() if not tags[t].holds]
    present = [t for t in condition.forbidden() if tags[t].holds]
    detail = "; ".join(
        [f"required {t} = {tags[t].value} {tags[t].unit} (threshold {tags[t].threshold})" for t in missing]
        + [f"forbidden {t} = {tags[t].value} {tags[t].unit} (threshold {tags[t].threshold})" for t in present]
    )
    passed = not missing and not present
    return CheckResult(
        stage="tag",
        check="condition",
        passed=passed,
        label=None if passed else "condition_unmet",
        value=float(len(missing) + len(present)),
        threshold=0.0,
        detail=detail,
    )


# Bump (to a new 16-hex-digit string) whenever any predicate's output or default threshold changes,
# then re-record tests/fixtures/predicate_panel.json; tests/tags/test_predicate_panel.py fails until both are
# done. Edits that change no output (comments, imports, refactors) keep it. Data stamped with another
# version (reference set, checkpoints, manifests) is then stale and must be regenerated.
PREDICATE_VERSION = "f571cb9bb73d1d5d"
