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
- ``condition_unmet``: each missed tag by its own projection (propose/tag_projection.py: a
  near_edge or low_light by its measured margin, clutter by the neighbours missing, occluded by an
  occluder set before the camera, toppled, stacked, on_floor and under_overhang by the discrete
  change that makes the predicate hold), None when one of them has none;
- ``fell_off`` or ``unstable`` naming the target of a required stack: the target set on the free
  stack base with the widest top, when it is wider than its carrier's
  (``stack_projection.restacked``).

An object moves with everything stacked on it, a piece of furniture with what rests on it
(propose/moves.py); each move adds its length to the objects' ``projection_distance``. Anything else
(an unstable or fallen object that is not such a target; nothing named) has no projection: None.
:func:`anticipated` applies the tag projections before the first check, where the proposer can
measure the tag itself.
The projected scene is checked again like any try. Pure: no torch, no MuJoCo, no files.
"""

from __future__ import annotations

import re

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.propose import tag_projection as tp
from scenegen.propose.moves import SLACK, in_workspace, into, moved, root
from scenegen.propose.separate import separate
from scenegen.propose.stack_projection import restacked
from scenegen.schema.scene import Rejection, SceneProposal

PROJECTED = (
    "out_of_workspace",
    "unsupported",
    "collision",
    "robot_overlap",
    "unreachable",
    "condition_unmet",
    "fell_off",
    "unstable",
)
_TAG = re.compile(r"(required|forbidden) (\w+) = (-?[\d.eE+-]+) \S+ \(threshold (-?[\d.eE+-]+)\)")


def project(
    proposal: SceneProposal,
    rejection: Rejection,
    catalog: Catalog,
    max_shift: float = 0.05,
    light: str = "scale",
) -> tuple[SceneProposal, tuple[str, ...]] | None:
    """(``proposal`` moved by what ``rejection`` measured, the names moved), or None when the
    rejection has no projection (see the module docstring) or it would move nothing. An object on
    the table or floor that the move took out of the workspace is put back inside it. ``light``:
    the low_light projection (``tp.steps``)."""
    made = _project(proposal, rejection, catalog, max_shift, light)
    return None if made is None else in_workspace(*made)


def _project(proposal: SceneProposal, rejection: Rejection, catalog: Catalog, max_shift: float, light: str):
    label = rejection.label
    if label not in PROJECTED:
        return None
    objects = {o.name: o for o in proposal.objects}
    named = rejection.detail.split(":")[0].split(" by ")[0].strip()
    if label == "out_of_workspace" and named in objects:
        obj = objects[named]
        region = layout.workspace_region(proposal, named)
        return moved(proposal, named, into(region, obj.position[:2]) - obj.position[:2])
    if label == "unsupported" and named in objects:
        return _supported(proposal, named, catalog)
    if label == "collision":
        pair = [n for n in rejection.detail.split("~") if n in objects]
        if not pair:
            return None
        apart = separate(proposal, catalog, max_shift=max_shift)
        names = tuple(a.name for a, b in zip(apart.objects, proposal.objects, strict=True) if a != b)
        return (apart, names) if names else None
    if label == "robot_overlap":
        return _away_from_arm(proposal, named, rejection)
    if label == "unreachable" and named == proposal.target:
        obj, base = objects[named], root(proposal, named)
        if base is None:
            return None
        shoulder = np.asarray(layout.SHOULDER)
        inward = float(np.linalg.norm(np.asarray(obj.position) - shoulder)) > sum(layout.REACH) / 2
        out = np.asarray(obj.position[:2]) - shoulder[:2]
        step = (abs(rejection.value or 0.0) + SLACK) * out / max(float(np.hypot(*out)), 1e-9)
        return tp.moved_under(proposal, base, -step if inward else step, tp.covering(proposal, catalog, base))
    if label == "condition_unmet":
        return _tags(proposal, rejection, catalog, light)
    if label in ("fell_off", "unstable") and rejection.detail.split(";")[0].strip() == proposal.target:
        return restacked(proposal, catalog)
    return None


def _supported(proposal: SceneProposal, name: str, catalog: Catalog):
    """The object's centre into its support's surface and its bottom onto the surface's height."""
    obj = next(o for o in proposal.objects if o.name == name)
    surfaces = layout.support_surfaces(proposal.furniture, proposal.objects, catalog)
    surface = surfaces.get(obj.support) if obj.support != name else None
    if surface is None:
        return None
    height = catalog.get(obj.asset).resting_poses[obj.resting_pose].height * obj.scale
    dxy = into(surface, obj.position[:2]) - obj.position[:2]
    return moved(proposal, name, dxy, dz=surface.z + height - obj.position[2])


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
    return moved(proposal, name, missing * out / max(float(np.hypot(*out)), 1e-9))


def _tags(proposal: SceneProposal, rejection: Rejection, catalog: Catalog, light: str = "scale"):
    """The request's missed tags, each projected by its measured value (tag_projection.py), in the
    order of ``tp.STEPS``; None when one of them has no projection."""
    tags = {m[1]: (m[0], float(m[2]), float(m[3])) for m in _TAG.findall(rejection.detail)}
    if not tags or set(tags) - set(tp.STEPS):
        return None
    out, names = proposal, ()
    for tag, step in tp.steps(light).items():
        if tag in tags:
            made = step(out, *tags[tag], catalog)
            if made is None:
                return None
            out, names = made[0], (*names, *made[1])
    return out, tuple(dict.fromkeys(names))


def anticipated(
    proposal: SceneProposal,
    catalog: Catalog,
    max_shift: float = 0.05,
    light: str = "scale",
    occluded: bool = False,
) -> SceneProposal:
    """``proposal`` projected before any check on what the proposer can measure itself
    (``tp.before_check``: each asked tag that the scene as placed does not meet is projected by the
    same step as its repair), then every object on the table or floor into the workspace, and, if
    anything moved, overlaps pushed apart with the target held. ``occluded`` (rays through the
    settled scene, which the proposer cannot measure) is left to the model and the checks, or, with
    ``occluded``, a required one is projected on every proposal (the occluder set before the
    camera, as its repair does). ``light``: the low_light projection (``tp.steps``)."""
    out, names = proposal, []
    for tag, step in tp.steps(light).items():
        state = proposal.condition.tags.get(tag, "unspecified")
        measured = tp.before_check(out, tag, catalog) if state != "unspecified" else None
        if measured is None and occluded and tag == "occluded" and state == "required":
            measured = (0.0, tp.OCCLUDED, False)
        if measured is None:
            continue
        value, threshold, holds = measured
        if holds == (state == "required"):
            continue
        made = step(out, state, value, threshold, catalog)
        if made is not None:
            out, names = made[0], [*names, *made[1]]
    out, _ = in_workspace(out, tuple(o.name for o in out.objects))
    if names:
        out = separate(out, catalog, max_shift=max_shift, spacing=True, fixed=frozenset({out.target}))
        out, _ = in_workspace(out, tuple(o.name for o in out.objects))
    return out
