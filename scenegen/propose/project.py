"""Projection repairs: a rejection that names an object and measures by how much it failed moves that
object by the margin, as the steerable scene generator projects a sample onto non-penetration; what
no projection can fix is left to re-denoising (propose/repair.py, the diffusion proposer's ``repair``).

What each rejection measured, and the move it gives (``slack`` past the threshold):

- ``out_of_workspace`` (the object whose centre is farthest outside the table, or the floor strip
  when the floor holds it; value: that margin): its centre into the region, ``slack`` inside;
- ``unsupported`` (the object whose centre is outside its support's surface, or off its height):
  centre into the surface, bottom onto its height;
- ``collision`` (the pair, value: the penetration depth): the pair pushed apart along the separating
  axis of its deepest pieces (``separate.separate``, the decoder's own overlap projection, given
  another ``max_shift``);
- ``robot_overlap`` (the object or furniture too close to the arm at its initial pose; value: the
  distance): away from the shoulder in the table plane, by the clearance missing;
- ``unreachable`` (the target; value: the envelope margin): along the line to the shoulder, inward
  when the target lies beyond the reach, outward when it lies too close;
- a required ``near_edge`` missed by ``value - threshold`` m: the target toward its nearest table
  edge by that much; a forbidden one that holds: away from it;
- a required ``occluded``: the tallest other object on the table set between the target and the
  main camera, just clear of the target;
- a required ``low_light`` (irradiance, linear in the ambient and each light's intensity): the
  lighting scaled to ``(1 - slack_light)`` of the threshold; a forbidden one: above it.

An object moves with everything stacked on it, a piece of furniture with what rests on it; each
move adds its length to the objects' ``projection_distance``. Anything else (a missing toppled,
stacked or on_floor; unstable, fell_off; nothing named) has no projection: None.
The projected scene is checked again like any try. Pure: no torch, no MuJoCo, no files.
"""

from __future__ import annotations

import math
import re

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.propose.separate import separate
from scenegen.schema.scene import Rejection, SceneProposal

SLACK = 0.01  # m past the threshold a projection aims for
SLACK_LIGHT = 0.1  # share of the low_light threshold a projected irradiance lies below (or above) it
PROJECTED = (
    "out_of_workspace",
    "unsupported",
    "collision",
    "robot_overlap",
    "unreachable",
    "condition_unmet",
)
_TAG = re.compile(r"(required|forbidden) (\w+) = (-?[\d.eE+-]+) \S+ \(threshold (-?[\d.eE+-]+)\)")


def project(
    proposal: SceneProposal, rejection: Rejection, catalog: Catalog, max_shift: float = 0.05
) -> tuple[SceneProposal, tuple[str, ...]] | None:
    """(``proposal`` moved by what ``rejection`` measured, the names moved), or None when the
    rejection has no projection (see the module docstring) or it would move nothing. An object on
    the table or floor that the move took out of the workspace is put back inside it."""
    moved = _project(proposal, rejection, catalog, max_shift)
    return None if moved is None else _in_workspace(*moved)


def _project(proposal: SceneProposal, rejection: Rejection, catalog: Catalog, max_shift: float):
    label = rejection.label
    if label not in PROJECTED:
        return None
    objects = {o.name: o for o in proposal.objects}
    named = rejection.detail.split(":")[0].split(" by ")[0].strip()
    if label == "out_of_workspace" and named in objects:
        obj = objects[named]
        region = layout.FLOOR if obj.support == "floor" else layout.support_surfaces(())["table"]
        return _moved(proposal, named, _into(region, obj.position[:2]) - obj.position[:2])
    if label == "unsupported" and named in objects:
        return _supported(proposal, named, catalog)
    if label == "collision":
        pair = [n for n in rejection.detail.split("~") if n in objects]
        if not pair:
            return None
        moved = separate(proposal, catalog, max_shift=max_shift)
        names = tuple(a.name for a, b in zip(moved.objects, proposal.objects, strict=True) if a != b)
        return (moved, names) if names else None
    if label == "robot_overlap":
        return _away_from_arm(proposal, named, rejection)
    if label == "unreachable" and named == proposal.target:
        obj, root = objects[named], _root(proposal, named)
        if root is None:
            return None
        shoulder = np.asarray(layout.SHOULDER)
        inward = float(np.linalg.norm(np.asarray(obj.position) - shoulder)) > sum(layout.REACH) / 2
        out = np.asarray(obj.position[:2]) - shoulder[:2]
        step = (abs(rejection.value or 0.0) + SLACK) * out / max(float(np.hypot(*out)), 1e-9)
        return _moved(proposal, root, -step if inward else step)
    if label == "condition_unmet":
        return _tags(proposal, rejection, catalog)
    return None


def _in_workspace(proposal: SceneProposal, names: tuple[str, ...]):
    """(``proposal`` with each moved object on the table or floor whose centre left its region moved
    back ``SLACK`` inside it, ``names``)."""
    for name in names:
        obj = next((o for o in proposal.objects if o.name == name), None)
        if obj is None or obj.support not in ("table", "floor"):
            continue
        region = layout.FLOOR if obj.support == "floor" else layout.support_surfaces(())["table"]
        if region.margin(obj.position[:2]) < 0:
            proposal = _moved(proposal, name, _into(region, obj.position[:2]) - obj.position[:2])[0]
    return proposal, names


def _into(region: layout.Surface, xy) -> np.ndarray:
    """The nearest point to ``xy`` that lies ``SLACK`` inside ``region`` (its centre if it is smaller)."""
    local = region.local_xy(xy)
    half = np.maximum(np.asarray(region.half) - SLACK, 0.0)
    local = np.clip(local, -half, half)
    c, s = math.cos(region.yaw), math.sin(region.yaw)
    return np.asarray(region.center) + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])


def _supported(proposal: SceneProposal, name: str, catalog: Catalog):
    """The object's centre into its support's surface and its bottom onto the surface's height."""
    obj = next(o for o in proposal.objects if o.name == name)
    surfaces = layout.support_surfaces(proposal.furniture, proposal.objects, catalog)
    surface = surfaces.get(obj.support) if obj.support != name else None
    if surface is None:
        return None
    height = catalog.get(obj.asset).resting_poses[obj.resting_pose].height * obj.scale
    dxy = _into(surface, obj.position[:2]) - obj.position[:2]
    return _moved(proposal, name, dxy, dz=surface.z + height - obj.position[2])


def _away_from_arm(proposal: SceneProposal, name: str, rejection: Rejection):
    """The named object or furniture away from the shoulder by the clearance it lacks."""
    missing = (rejection.threshold or 0.0) - (rejection.value or 0.0) + SLACK
    if missing <= 0:
        return None
    shoulder = np.asarray(layout.SHOULDER[:2])
    pieces = {p.name: p for p in proposal.furniture}
    objects = {o.name: o for o in proposal.objects}
    where = objects[name].position if name in objects else pieces[name].position if name in pieces else None
    if where is None:
        return None
    out = np.asarray(where[:2]) - shoulder
    return _moved(proposal, name, missing * out / max(float(np.hypot(*out)), 1e-9))


def _tags(proposal: SceneProposal, rejection: Rejection, catalog: Catalog):
    """A missed near_edge, clutter or low_light, by its measured value (any other tag: None)."""
    tags = {m[1]: (m[0], float(m[2]), float(m[3])) for m in _TAG.findall(rejection.detail)}
    if not tags or set(tags) - {"near_edge", "clutter", "occluded", "low_light"}:
        return None  # another tag failed too: re-denoising must change the scene anyway
    out, names = proposal, ()
    steps = (
        ("near_edge", _near_edge),
        ("clutter", _clutter),
        ("occluded", _occluded),
        ("low_light", _low_light),
    )
    for tag, step in steps:
        if tag in tags:
            moved = step(out, *tags[tag], catalog)
            if moved is None:
                return None
            out, names = moved[0], (*names, *moved[1])
    return out, tuple(dict.fromkeys(names))


def _near_edge(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target, with what holds it up (the furniture piece or the stack under it), toward the
    nearest table edge it stays in reach at by the margin missing (required), or away from its
    nearest edge by the excess (forbidden)."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    root = _root(proposal, target.name)
    if root is None:
        return None
    x, y = target.position[:2]
    hx, hy = layout.TABLE_SIZE[0] / 2, layout.TABLE_SIZE[1] / 2
    gaps = {(1.0, 0.0): hx - x, (-1.0, 0.0): hx + x, (0.0, 1.0): hy - y, (0.0, -1.0): hy + y}
    if kind == "forbidden":
        direction = np.asarray(min(gaps, key=gaps.get))
        return _moved(proposal, root, -(threshold - value + SLACK) * direction)
    by = value - threshold + SLACK
    shoulder = np.asarray(layout.SHOULDER)
    for direction in sorted(gaps, key=gaps.get):  # the nearest edge whose side keeps it in reach
        there = np.asarray(target.position) + by * np.array([*direction, 0.0])
        if float(np.linalg.norm(there - shoulder)) <= layout.REACH[1] - SLACK:
            return _moved(proposal, root, by * np.asarray(direction))
    return None


def _root(proposal: SceneProposal, name: str) -> str | None:
    """What carries object ``name`` on the table: itself, the furniture piece or the bottom of the
    stack it rests on; None when it rests on the floor."""
    objects = {o.name: o for o in proposal.objects}
    pieces = {p.name for p in proposal.furniture}
    seen = set()
    while name in objects and name not in seen:
        seen.add(name)
        support = objects[name].support
        if support == "table":
            return name
        if support in pieces:
            return support
        if support not in objects:
            return None
        name = support
    return None


# The clutter predicate's radius (tags/predicates.py TagSettings.clutter_radius, which a proposer may
# not import; tests/propose/test_project.py checks they agree), and how far inside it a projected
# neighbour's centre is placed
CLUTTER_RADIUS, CLUTTER_AIM = 0.2, 0.06
CLUTTER_COUNT, NEAR_EDGE = 3, 0.03  # the predicates' defaults as well (clutter_count, near_edge_distance)


def _clutter(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """A required clutter missing ``threshold - value`` neighbours: that many of the nearest other
    objects on the table (with their stacks) moved toward the target to CLUTTER_AIM inside the
    radius, then pushed apart where they overlap (``separate``, the target held). A forbidden
    clutter: None."""
    if kind != "required":
        return None
    target = next(o for o in proposal.objects if o.name == proposal.target)
    centre = np.asarray(target.position[:2])
    distance = {
        o.name: float(np.hypot(*(np.asarray(o.position[:2]) - centre)))
        for o in proposal.objects
        if o.name != target.name and o.support == "table"
    }
    outside = sorted((d, n) for n, d in distance.items() if d > CLUTTER_RADIUS)
    need = int(round(threshold - value))
    if need < 1 or len(outside) < need:
        return None
    out, names = proposal, []
    aim = CLUTTER_RADIUS - CLUTTER_AIM
    for d, name in outside[:need]:
        obj = next(o for o in out.objects if o.name == name)
        towards = centre - np.asarray(obj.position[:2])
        out, moved = _moved(out, name, (d - aim) * towards / d)
        names += moved
    apart = separate(out, catalog, max_shift=CLUTTER_AIM / 2, spacing=True, fixed=frozenset({target.name}))
    names += [a.name for a, b in zip(apart.objects, out.objects, strict=True) if a != b]
    return apart, tuple(names)


def _occluded(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """A required occluded: the tallest other object on the table (with its stack) set on the line
    from the target to the main camera, just clear of the target, where it hides most of it from
    the camera. A forbidden occluded: None."""
    if kind != "required":
        return None
    target = next(o for o in proposal.objects if o.name == proposal.target)
    candidates = [o for o in proposal.objects if o.name != target.name and o.support == "table"]
    if not candidates:
        return None

    def height(o) -> float:
        asset = catalog.get(o.asset)
        return (asset.resting_poses[o.resting_pose].height + layout.pose_top(asset, o.resting_pose)) * o.scale

    occluder = max(candidates, key=lambda o: (height(o), o.name))
    towards = np.asarray(proposal.cameras[0].position[:2]) - np.asarray(target.position[:2])
    towards = towards / max(float(np.hypot(*towards)), 1e-9)
    radius = layout.footprint_radius
    gap = radius(catalog.get(target.asset), target.resting_pose) * target.scale
    gap += radius(catalog.get(occluder.asset), occluder.resting_pose) * occluder.scale + SLACK
    place = np.asarray(target.position[:2]) + gap * towards
    return _moved(proposal, occluder.name, place - np.asarray(occluder.position[:2]))


def _low_light(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The lighting scaled to SLACK_LIGHT below the threshold (required) or above it (forbidden)."""
    if value <= 0:
        return None
    aim = threshold * (1 - SLACK_LIGHT if kind == "required" else 1 + SLACK_LIGHT)
    return _lit(proposal, aim / value), ("lights",)


def _lit(proposal: SceneProposal, factor: float) -> SceneProposal:
    """The scene's ambient light and every light's intensity scaled by ``factor``."""
    lighting = proposal.lighting
    lights = tuple(
        light.model_copy(update={"intensity": round(min(light.intensity * factor, 3.0), 6)})
        for light in lighting.lights
    )
    ambient = tuple(round(min(a * factor, 1.0), 6) for a in lighting.ambient)
    lit = lighting.model_copy(update={"lights": lights, "ambient": ambient})
    return proposal.model_copy(update={"lighting": lit})


def _moved(proposal: SceneProposal, name: str, dxy, dz: float = 0.0):
    """``proposal`` with object or furniture ``name`` moved by ``dxy`` (and ``dz``), with everything
    resting on it, transitively; (proposal, names moved), or None for a move under 0.1 mm."""
    dxy = np.asarray(dxy, float)
    if float(np.hypot(*dxy)) < 1e-4 and abs(dz) < 1e-4:
        return None
    carried, frontier = {name}, [name]
    while frontier:
        base = frontier.pop()
        above = [o.name for o in proposal.objects if o.support == base and o.name not in carried]
        carried.update(above)
        frontier += above
    shift = np.array([dxy[0], dxy[1], 0.0])
    distance = float(np.hypot(*dxy))

    def placed(position, z_too: bool):
        moved = np.asarray(position, float) + shift + ([0.0, 0.0, dz] if z_too else 0.0)
        return tuple(round(float(v), 6) for v in moved)

    objects = tuple(
        o.model_copy(
            update={
                "position": placed(o.position, True),
                "projection_distance": round(math.hypot(o.projection_distance, distance, dz), 6),
            }
        )
        if o.name in carried
        else o
        for o in proposal.objects
    )
    furniture = tuple(
        p.model_copy(update={"position": placed(p.position, False)}) if p.name == name else p
        for p in proposal.furniture
    )
    names = [*(o.name for o in proposal.objects), *(p.name for p in proposal.furniture)]
    moved = tuple(n for n in names if n in carried)
    return proposal.model_copy(update={"objects": objects, "furniture": furniture}), moved


def anticipated(proposal: SceneProposal, catalog: Catalog, max_shift: float = 0.05) -> SceneProposal:
    """``proposal`` projected before any check, on what the proposer can measure itself: the
    request's ``near_edge`` (the target's footprint margin to the table's edges, measured on its
    convex parts as placed) and ``clutter`` (neighbours' centres within the radius less 2 cm) by the
    same moves as their repairs, then every object on the table or floor into the workspace, and
    overlaps pushed apart with the target held. Tags that need settling or rendering to measure
    (toppled, stacked, occluded, low_light, on_floor) are left to the model and the checks."""
    condition = proposal.condition
    target = next(o for o in proposal.objects if o.name == proposal.target)
    out, names = proposal, []
    state = condition.tags.get("near_edge", "unspecified")
    if state != "unspecified" and target.support != "floor":
        margin = _edge_margin(catalog, target)
        wrong = margin > NEAR_EDGE - SLACK if state == "required" else margin <= NEAR_EDGE + SLACK
        moved = _near_edge(out, state, margin, NEAR_EDGE, catalog) if wrong else None
        if moved is not None:
            out, names = moved[0], [*names, *moved[1]]
    if condition.tags.get("clutter") == "required":
        centre = np.asarray(next(o for o in out.objects if o.name == out.target).position[:2])
        near = sum(
            float(np.hypot(*(np.asarray(o.position[:2]) - centre))) <= CLUTTER_RADIUS - 0.02
            for o in out.objects
            if o.name != out.target
        )
        moved = _clutter(out, "required", near, CLUTTER_COUNT, catalog) if near < CLUTTER_COUNT else None
        if moved is not None:
            out, names = moved[0], [*names, *moved[1]]
    out, _ = _in_workspace(out, tuple(o.name for o in out.objects))
    if names:
        out = separate(out, catalog, max_shift=max_shift, spacing=True, fixed=frozenset({out.target}))
        out, _ = _in_workspace(out, tuple(o.name for o in out.objects))
    return out


def _edge_margin(catalog: Catalog, obj) -> float:
    """The near_edge predicate's value for ``obj`` as placed: the smallest distance from its convex
    parts' vertices to a table edge (m; negative past it)."""
    from scenegen.assets.catalog import convex_part_vertices
    from scenegen.core.rotations import quat_to_matrix

    rot = quat_to_matrix(obj.quat)
    pts = np.concatenate(convex_part_vertices(catalog, obj.asset)) * obj.scale @ rot.T + obj.position
    hx, hy = layout.TABLE_SIZE[0] / 2, layout.TABLE_SIZE[1] / 2
    return float(min((hx - np.abs(pts[:, 0])).min(), (hy - np.abs(pts[:, 1])).min()))
