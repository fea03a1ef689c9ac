"""The moves projections are made of (propose/project.py, propose/tag_projection.py,
propose/stack_projection.py): an object moved with what rests on it, the object that carries another
on the table, a point kept inside a region, the target re-placed in a resting pose on a support.
Pure: numpy, the layout and the schema.
"""

from __future__ import annotations

import math

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.schema.scene import SceneProposal

SLACK = 0.01  # m past the threshold a projection aims for


def in_workspace(proposal: SceneProposal, names: tuple[str, ...]):
    """(``proposal`` with each moved object on the table or floor whose centre left its region moved
    back ``SLACK`` inside it, ``names``)."""
    for name in names:
        obj = next((o for o in proposal.objects if o.name == name), None)
        if obj is None or obj.support not in ("table", "floor"):
            continue
        region = layout.workspace_region(proposal, name)
        if region.margin(obj.position[:2]) < 0:
            proposal = moved(proposal, name, into(region, obj.position[:2]) - obj.position[:2])[0]
    return proposal, names


def into(region: layout.Surface, xy) -> np.ndarray:
    """The nearest point to ``xy`` that lies ``SLACK`` inside ``region`` (its centre if it is smaller)."""
    local = region.local_xy(xy)
    half = np.maximum(np.asarray(region.half) - SLACK, 0.0)
    local = np.clip(local, -half, half)
    c, s = math.cos(region.yaw), math.sin(region.yaw)
    return np.asarray(region.center) + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])


GROUNDS = {"table": layout.TABLE_TOP_Z, "floor": layout.FLOOR.z}  # the surfaces a stack can stand on


def ground_of(proposal: SceneProposal, name: str) -> str:
    """Where object ``name``'s stack stands: "floor", or "table" (on it or on furniture on it)."""
    return "floor" if layout.stack_ground(proposal, name) == "floor" else "table"


def rehomed(proposal: SceneProposal, name: str, ground: str, xy):
    """``proposal`` with object ``name`` (on the table or the floor) and its stack moved to ``xy`` on
    ``ground`` (``GROUNDS``): kept inside the floor strip there, lowered or raised by the surfaces'
    height difference; (proposal, names moved), or None for no move."""
    obj = next(o for o in proposal.objects if o.name == name)
    if ground == "floor":
        xy = into(layout.FLOOR, xy)
    dxy = np.asarray(xy, float) - obj.position[:2]
    out = moved(proposal, name, dxy, GROUNDS[ground] - GROUNDS[obj.support])
    if out is None or obj.support == ground:
        return out
    there, names = out
    objects = tuple(o.model_copy(update={"support": ground}) if o.name == name else o for o in there.objects)
    return there.model_copy(update={"objects": objects}), names


def root(proposal: SceneProposal, name: str) -> str | None:
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
def moved(proposal: SceneProposal, name: str, dxy, dz: float = 0.0):
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


def resting(proposal: SceneProposal, catalog: Catalog, pose: int | None, support: str, xy, surface_z: float):
    """The target re-placed: resting pose ``pose`` (None: its own) at its yaw, on ``support`` at
    ``xy``, its centre at the surface's height plus the pose's; None when something rests on it."""
    from scenegen.core.placement import quat_mul, yaw_quat

    target = next(o for o in proposal.objects if o.name == proposal.target)
    if any(o.support == target.name for o in proposal.objects):
        return None
    asset = catalog.get(target.asset)
    pose = target.resting_pose if pose is None else pose
    rest_now = np.asarray(asset.resting_poses[target.resting_pose].quat)
    rel = quat_mul(np.asarray(target.quat), rest_now * np.array([1, -1, -1, -1]))
    yaw = 2 * np.arctan2(rel[3], rel[0])
    quat = quat_mul(yaw_quat(float(yaw)), np.asarray(asset.resting_poses[pose].quat))
    quat = quat if quat[0] >= 0 else -quat
    position = (float(xy[0]), float(xy[1]), surface_z + asset.resting_poses[pose].height * target.scale)
    distance = float(np.linalg.norm(np.subtract(position, target.position)))
    placed = target.model_copy(
        update={
            "position": tuple(round(v, 6) for v in position),
            "quat": tuple(round(float(v), 7) for v in quat),
            "resting_pose": pose,
            "support": support,
            "projection_distance": round(float(np.hypot(target.projection_distance, distance)), 6),
        }
    )
    objects = tuple(placed if o.name == target.name else o for o in proposal.objects)
    return proposal.model_copy(update={"objects": objects}), (target.name,)
