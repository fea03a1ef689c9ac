"""Projections of the request's tags: a rare tag a scene missed (or held against the request) moved
onto by the margin its predicate measured, or by the discrete change that makes it hold, each
derived from the predicate's own definition (tags/predicates.py). What propose/project.py applies
after a ``condition_unmet`` rejection and, where the proposer can measure the tag itself, before the
first check (``anticipated``). Pure: numpy, the layout, the catalog and the schema.
"""

from __future__ import annotations

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.propose.moves import GROUNDS, SLACK, ground_of, moved, rehomed, resting, root
from scenegen.propose.separate import separate
from scenegen.propose.stack_projection import stacked
from scenegen.schema.scene import SceneProposal

SLACK_LIGHT = 0.1  # share of the low_light threshold a projected irradiance lies below (or above) it


def near_edge(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target, with what holds it up (the furniture piece or the stack under it), toward the
    nearest table edge it stays in reach at until its footprint as placed lies ``SLACK`` inside the
    threshold (required; keeping a required under_overhang it holds, below), or away from its
    nearest edge until ``SLACK`` outside it (forbidden); the margins are measured on the placement
    (``value``, the settled one, is not needed)."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    base = root(proposal, target.name)
    if base is None:
        return None
    pts = _placed_vertices(catalog, target)
    hx, hy = layout.TABLE_SIZE[0] / 2, layout.TABLE_SIZE[1] / 2
    gaps = {  # each edge's distance to the footprint as placed, the predicate's measure per edge
        (1.0, 0.0): hx - pts[:, 0].max(),
        (-1.0, 0.0): hx + pts[:, 0].min(),
        (0.0, 1.0): hy - pts[:, 1].max(),
        (0.0, -1.0): hy + pts[:, 1].min(),
    }
    if kind == "forbidden":
        direction = min(gaps, key=gaps.get)
        return moved(proposal, base, -(threshold - gaps[direction] + SLACK) * np.asarray(direction))
    shoulder = np.asarray(layout.SHOULDER)
    # a required under_overhang the target holds is kept: the nearest edge it can reach while under
    # its piece, alone or with the piece (which stays on the table, off the arm's side); else, or
    # without one, the nearest edge it can reach
    cover = covering(proposal, catalog, base)
    first = None
    for direction in sorted(gaps, key=gaps.get):
        by = gaps[direction] - threshold + SLACK
        shift = by * np.asarray(direction)
        there = np.asarray(target.position) + [*shift, 0.0]
        if float(np.linalg.norm(there - shoulder)) > layout.REACH[1] - SLACK:
            continue
        alone = moved(proposal, base, shift)
        if cover is None or alone is None or covering(alone[0], catalog, base) is not None:
            return alone
        first = first or alone
        axis = int(direction[1] != 0)
        if _furthest(cover, direction) + by <= (hx, hy)[axis] and float(np.dot(direction, shoulder[:2])) <= 0:
            return moved_under(proposal, base, shift, cover)
    return first


def moved_under(proposal: SceneProposal, base: str, dxy, cover=None):
    """``moved`` of ``base`` (what carries the target) by ``dxy``, with ``cover`` (the furniture piece
    the target lies under, :func:`covering`; None: none) moved alike, so that it stays under it."""
    out = moved(proposal, base, dxy)
    if out is None or cover is None:
        return out
    shifted = moved(out[0], cover.name, dxy)
    return out if shifted is None else (shifted[0], (*out[1], *shifted[1]))


def covering(proposal: SceneProposal, catalog: Catalog, base: str):
    """The furniture piece the target lies under as placed, as the under_overhang predicate counts
    it, when the request requires under_overhang and ``base`` (what carries the target) is not
    furniture itself; or None."""
    required = proposal.condition.tags.get("under_overhang") == "required"
    if not required or base in {p.name for p in proposal.furniture}:
        return None
    points = _placed_vertices(catalog, next(o for o in proposal.objects if o.name == proposal.target))
    for piece in proposal.furniture:
        if layout.overhang_cover(points, [piece]) >= OVERHANG_COVER:
            return piece
    return None


def _furthest(piece, direction) -> float:
    """How far the piece's boxes reach along ``direction`` (a table axis, signed), in the plane."""
    axis = int(direction[1] != 0)
    sign = float(direction[axis])
    reach = -np.inf
    for centre, rot, half in layout.furniture_boxes(piece):
        corners = np.array([[sx, sy, 0.0] for sx in (-1, 1) for sy in (-1, 1)]) * half
        reach = max(reach, float((sign * (corners @ rot.T + centre)[:, axis]).max()))
    return reach


CLUTTER_RADIUS, CLUTTER_AIM = 0.2, 0.06  # CLUTTER_AIM: the closest a neighbour's centre is set
CLUTTER_COUNT, NEAR_EDGE = 3, 0.03  # the predicates' defaults as well (clutter_count, near_edge_distance)
FLOOR_SIDES = ((1.0, 0.0), (-1.0, 0.0), (0.0, -1.0), (0.0, 1.0))  # where a neighbour comes from on the floor


def clutter(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """A required clutter: as many of the nearest other objects standing on the table or the floor
    (with their stacks) as the scene as placed lacks within the radius less 2 cm moved toward the
    target until just clear of its footprint as placed, those that fit there well inside the radius,
    onto the target's ground (on the floor strip from its sides, the target's narrow ones first),
    then pushed apart where they overlap (``separate``, the target held). A forbidden clutter: None."""
    if kind != "required":
        return None
    target = next(o for o in proposal.objects if o.name == proposal.target)
    ground = ground_of(proposal, target.name)
    centre = np.asarray(target.position[:2])
    distance = {
        o.name: float(np.hypot(*(np.asarray(o.position[:2]) - centre)))
        for o in proposal.objects
        if o.name != target.name
    }
    near = CLUTTER_RADIUS - 0.02  # counted as placed, 2 cm inside the radius: settling moves things

    def radius(o) -> float:
        return layout.footprint_radius(catalog.get(o.asset), o.resting_pose) * o.scale

    objects = {o.name: o for o in proposal.objects}
    around = _placed_vertices(catalog, target)[:, :2] - centre  # the target's footprint as placed

    def aim(o, side) -> float:  # a neighbour's centre on ``side`` of the target, just clear of it
        return max(float((around @ side).max()) + radius(o) + SLACK, CLUTTER_AIM)

    # on the floor strip: the target's narrow sides first
    sides = sorted(FLOOR_SIDES, key=lambda side: float((around @ np.asarray(side)).max()))
    need = int(round(threshold)) - sum(d <= near for d in distance.values())
    if need < 1:
        return None
    out, names, brought = proposal, [], 0
    for d, name in sorted((d, n) for n, d in distance.items() if d > near and objects[n].support in GROUNDS):
        obj = next(o for o in out.objects if o.name == name)
        side = (np.asarray(obj.position[:2]) - centre) / max(d, 1e-9)
        if ground == "floor":
            side = np.asarray(sides[brought % len(sides)])
        there = aim(obj, side)
        if there > CLUTTER_RADIUS - CLUTTER_AIM / 2:  # it would not fit well inside the radius there
            continue
        step = rehomed(out, name, ground, centre + there * side)
        if step is not None:
            out, names = step[0], names + list(step[1])
        brought += 1
        if brought == need:
            break
    if brought < need:
        return None
    apart = separate(out, catalog, max_shift=CLUTTER_AIM / 2, spacing=True, fixed=frozenset({target.name}))
    names += [a.name for a, b in zip(apart.objects, out.objects, strict=True) if a != b]
    return apart, tuple(names)


def _height(catalog: Catalog, obj) -> float:
    """How far an object's top stands above the surface it rests on (m)."""
    asset = catalog.get(obj.asset)
    pose = obj.resting_pose
    return (asset.resting_poses[pose].height + layout.pose_top(asset, pose)) * obj.scale


def occluded(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """A required occluded: the tallest other object standing on the table or the floor (with its
    stack) set on the target's ground on the line from the target to the main camera, just clear of
    the target, where it hides most of it from the camera. A forbidden occluded: None."""
    if kind != "required":
        return None
    target = next(o for o in proposal.objects if o.name == proposal.target)
    candidates = [o for o in proposal.objects if o.name != target.name and o.support in GROUNDS]
    if not candidates:
        return None

    occluder = max(candidates, key=lambda o: (_height(catalog, o), o.name))
    towards = np.asarray(proposal.cameras[0].position[:2]) - np.asarray(target.position[:2])
    towards = towards / max(float(np.hypot(*towards)), 1e-9)
    radius = layout.footprint_radius
    gap = radius(catalog.get(target.asset), target.resting_pose) * target.scale
    gap += radius(catalog.get(occluder.asset), occluder.resting_pose) * occluder.scale + SLACK
    place = np.asarray(target.position[:2]) + gap * towards
    return rehomed(proposal, occluder.name, ground_of(proposal, target.name), place)


def low_light(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The lighting scaled to SLACK_LIGHT below the threshold (required) or above it (forbidden)."""
    if value <= 0:
        return None
    aim = threshold * (1 - SLACK_LIGHT if kind == "required" else 1 + SLACK_LIGHT)
    return lit(proposal, aim / value), ("lights",)


AIM_AWAY_DEG = 60.0  # a light turned off the target: its axis this far from the target (past the cutoff)


def low_light_aimed(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """Required: as the reference darkens a target, with its lights bright and aimed elsewhere: each
    spot light whose cone holds the target's top is turned ``AIM_AWAY_DEG`` off it (away from the
    target, about its foot), its intensity kept; only if the bound still lies above SLACK_LIGHT
    below the threshold is the lighting then scaled as :func:`low_light` does. Forbidden: as
    :func:`low_light` (recipe key ``proposer.light_projection: aim``)."""
    if kind != "required" or value <= 0:
        return low_light(proposal, kind, value, threshold, catalog)
    point, angle = _target_top(proposal, catalog), np.radians(AIM_AWAY_DEG)
    cos_cutoff = np.cos(np.radians(SPOT_CUTOFF_DEG))
    lights = []
    for light in proposal.lighting.lights:
        toward = point - np.asarray(light.position)
        toward /= np.linalg.norm(toward)
        if float(np.asarray(light.direction) @ toward) < cos_cutoff * np.linalg.norm(light.direction):
            lights.append(light)  # its cone misses the target already
            continue
        flat = np.hypot(*toward[:2]) > 1e-6  # horizontally from the target to the light, or any way
        away = np.array([-toward[0], -toward[1], 0.0]) if flat else np.array([1.0, 0.0, 0.0])
        side = away - (away @ toward) * toward
        turned = np.cos(angle) * toward + np.sin(angle) * side / np.linalg.norm(side)
        lights.append(light.model_copy(update={"direction": tuple(round(float(v), 6) for v in turned)}))
    lighting = proposal.lighting.model_copy(update={"lights": tuple(lights)})
    out = proposal.model_copy(update={"lighting": lighting})
    aim, bound = threshold * (1 - SLACK_LIGHT), irradiance_bound(out, catalog)
    return (out if bound <= aim else lit(out, aim / bound)), ("lights",)


def lit(proposal: SceneProposal, factor: float) -> SceneProposal:
    """The scene's ambient light and every light's intensity scaled by ``factor``."""
    lighting = proposal.lighting
    lights = tuple(
        light.model_copy(update={"intensity": round(min(light.intensity * factor, 3.0), 6)})
        for light in lighting.lights
    )
    ambient = tuple(round(min(a * factor, 1.0), 6) for a in lighting.ambient)
    scaled = lighting.model_copy(update={"lights": lights, "ambient": ambient})
    return proposal.model_copy(update={"lighting": scaled})


def edge_margin(catalog: Catalog, obj) -> float:
    """The near_edge predicate's value for ``obj`` as placed: the smallest distance from its convex
    parts' vertices to a table edge (m; negative past it)."""
    return layout.edge_margin(_placed_vertices(catalog, obj))


TOPPLED_DEG = 45.0  # the predicate's default (toppled_angle)


def _tilt(asset, pose: int) -> float:
    """The angle (rad) between world-up seen in the body frame in resting pose ``pose`` and in the
    nearest upright resting pose (pi when there is none): the toppled predicate's measure."""
    from scenegen.core.rotations import quat_to_matrix

    up = quat_to_matrix(asset.resting_poses[pose].quat)[2, :]
    uprights = [quat_to_matrix(p.quat)[2, :] for p in asset.resting_poses if p.upright]
    if not uprights:
        return float(np.pi)
    return float(min(np.arccos(np.clip(np.dot(up, u), -1.0, 1.0)) for u in uprights))


def toppled(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target laid in its likeliest resting pose that is not upright (required), or that is
    (forbidden), where it stands; None when it has none."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    asset = catalog.get(target.asset)
    want_upright = kind != "required"
    poses = [i for i, p in enumerate(asset.resting_poses) if p.upright == want_upright]
    if not want_upright:  # tilted well past the predicate's 45 degrees from every upright pose
        poses = [i for i in poses if _tilt(asset, i) > np.radians(TOPPLED_DEG + 10)]
    if not poses or asset.orientation_free:
        return None
    pose = max(poses, key=lambda i: (asset.resting_poses[i].probability, -i))
    surface_z = target.position[2] - asset.resting_poses[target.resting_pose].height * target.scale
    return resting(proposal, catalog, pose, target.support, target.position[:2], surface_z)


def on_floor(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target on the floor strip beside the table, level with where it was (required), or back on
    the table near that edge (forbidden)."""
    from scenegen.propose.moves import into

    target = next(o for o in proposal.objects if o.name == proposal.target)
    if kind == "required":
        xy = into(layout.FLOOR, (target.position[0], layout.FLOOR.center[1]))
        return resting(proposal, catalog, None, "floor", xy, layout.FLOOR.z)
    table = layout.support_surfaces(())["table"]
    xy = into(table, (target.position[0], table.half[1] - 0.1))
    return resting(proposal, catalog, None, "table", xy, layout.TABLE_TOP_Z)


def under_overhang(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target, with what carries it on the table, moved under the middle of the highest board of
    the scene's furniture when it fits beneath it (required), or out from under it toward the arm
    (forbidden)."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    base = root(proposal, target.name)
    boards = [box for piece in proposal.furniture for box in layout.furniture_boxes(piece)]
    if base is None or base in {p.name for p in proposal.furniture} or not boards:
        return None
    centre, rot, half = max(boards, key=lambda b: float(b[0][2] - b[2][2]))
    if kind != "required":
        radius = layout.footprint_radius(catalog.get(target.asset), target.resting_pose) * target.scale
        local = rot.T @ (np.asarray(target.position) - centre)
        local[0] = -(half[0] + radius + SLACK)  # the board's near side, toward the arm
        return moved(proposal, base, (centre + rot @ local)[:2] - np.asarray(target.position[:2]))
    asset = catalog.get(target.asset)
    top = target.position[2] + layout.pose_top(asset, target.resting_pose) * target.scale
    if top >= centre[2] - half[2] - SLACK:
        return None  # it would not fit beneath the board
    return moved(proposal, base, np.asarray(centre[:2]) - np.asarray(target.position[:2]))


# MuJoCo's spot light defaults, which sim/world.py keeps (diffusion/cost.py SPOT_CUTOFF, SPOT_EXPONENT)
SPOT_CUTOFF_DEG, SPOT_EXPONENT = 45.0, 10.0


def _target_top(proposal: SceneProposal, catalog: Catalog) -> np.ndarray:
    """The point the low_light predicate measures at: 1 mm over the target's top as placed."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    pts = _placed_vertices(catalog, target)
    return np.array([pts[:, 0].mean(), pts[:, 1].mean(), pts[:, 2].max() + 1e-3])


def irradiance_bound(proposal: SceneProposal, catalog: Catalog) -> float:
    """The low_light predicate's irradiance at the target's top as placed, with no light shadowed: an
    upper bound of what the predicate measures (a shadow only takes light away)."""
    point = _target_top(proposal, catalog)
    total = float(np.mean(proposal.lighting.ambient))
    for light in proposal.lighting.lights:
        to_light = np.asarray(light.position) - point
        direction = to_light / np.linalg.norm(to_light)
        axis = np.asarray(light.direction) / np.linalg.norm(light.direction)
        cos_spot = float(np.dot(-direction, axis))
        if cos_spot < np.cos(np.radians(SPOT_CUTOFF_DEG)):
            continue
        total += (
            float(np.mean(light.colour)) * light.intensity * cos_spot**SPOT_EXPONENT * max(0.0, direction[2])
        )
    return total


def before_check(proposal: SceneProposal, tag: str, catalog: Catalog) -> tuple[float, float, bool] | None:
    """(value, threshold, holds) of ``tag``'s predicate as the proposer can measure it on the scene as
    placed, before settling; None for a tag it cannot (occluded). The discrete tags read the
    placement: toppled a resting pose that is not upright, stacked a support that is an object,
    on_floor a stack standing on the floor; low_light uses :func:`irradiance_bound` and holds only
    when the bound does."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    objects = {o.name for o in proposal.objects}
    asset = catalog.get(target.asset)
    floor = layout.stack_ground(proposal, target.name) == "floor"
    if tag == "near_edge":
        if floor:
            return None
        value = edge_margin(catalog, target)
        return value, NEAR_EDGE, value <= NEAR_EDGE - SLACK
    if tag == "clutter":
        centre = np.asarray(target.position[:2])
        value = sum(
            float(np.hypot(*(np.asarray(o.position[:2]) - centre))) <= CLUTTER_RADIUS - 0.02
            for o in proposal.objects
            if o.name != target.name
        )
        return float(value), float(CLUTTER_COUNT), value >= CLUTTER_COUNT
    if tag == "low_light":
        value = irradiance_bound(proposal, catalog)
        return value, LOW_LIGHT, value < LOW_LIGHT * (1 - SLACK_LIGHT / 2)
    if tag == "toppled":
        flat = not asset.resting_poses[target.resting_pose].upright and not asset.orientation_free
        return float(flat), 0.5, flat
    if tag == "stacked":
        return float(target.support in objects), 0.5, target.support in objects
    if tag == "on_floor":
        return float(floor), 0.5, floor
    if tag == "under_overhang":
        value = overhang_cover(proposal, catalog)
        return value, OVERHANG_COVER, value >= OVERHANG_COVER
    return None


def overhang_cover(proposal: SceneProposal, catalog: Catalog) -> float:
    """The under_overhang predicate's value for the target as placed: the share of its convex parts'
    vertices that have a furniture box above its top."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    return layout.overhang_cover(_placed_vertices(catalog, target), proposal.furniture)


def _placed_vertices(catalog: Catalog, obj) -> np.ndarray:
    """The world-frame vertices (N, 3) of an object's convex parts as placed."""
    from scenegen.assets.catalog import convex_part_vertices
    from scenegen.core.rotations import quat_to_matrix

    rot = quat_to_matrix(obj.quat)
    return np.concatenate(convex_part_vertices(catalog, obj.asset)) * obj.scale @ rot.T + obj.position


LOW_LIGHT = 0.25  # the predicate's default (tags/predicates.py low_light_irradiance)
OVERHANG_COVER = 0.5  # the predicate's default (overhang_cover)
OCCLUDED = 0.5  # the predicate's default (occluded_fraction)
# Each tag's projection, in the order a scene's missed tags are projected: the target's place and pose
# first, then what is around it, then the light.
STEPS = {
    "on_floor": on_floor,
    "stacked": stacked,
    "toppled": toppled,
    "under_overhang": under_overhang,
    "near_edge": near_edge,
    "clutter": clutter,
    "occluded": occluded,
    "low_light": low_light,
}


def steps(light_projection: str = "scale") -> dict:
    """:data:`STEPS` with the low_light projection a recipe names (``scale`` or ``aim``)."""
    if light_projection not in ("scale", "aim"):
        raise ValueError(f"light_projection {light_projection!r}: use scale or aim")
    return STEPS if light_projection == "scale" else {**STEPS, "low_light": low_light_aimed}
