"""The stacked tag's projections: the target set on the nearest free stack base when a request
requires a stack the scene lacks (or set beside its carrier when one is forbidden), and, when the
target of a required stack fell off its carrier or did not come to rest on it, set on the free base
with the widest top (propose/project.py, after ``fell_off`` and ``unstable``). Pure: numpy, the layout,
the catalog and the schema.
"""

from __future__ import annotations

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.core import layout
from scenegen.propose.moves import GROUNDS, SLACK, ground_of, rehomed, resting
from scenegen.schema.scene import SceneProposal


def stacked(proposal: SceneProposal, kind: str, value: float, threshold: float, catalog: Catalog):
    """The target set on top of the nearest other object that can carry it (a stack base with nothing
    on it), at its top's centre (required): on the table one in the arm's reach; on the floor (the
    target lies there) one on the floor or brought down from the table to where the target lies, as
    the reachability check leaves a floor stack to another robot. Or, stacked against the request,
    the target set on the table beside what carries it (forbidden)."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    here = np.asarray(target.position[:2])
    if kind == "required":
        ground = "floor" if target.support == "floor" else "table"  # on_floor projected first
        bases = stack_bases(proposal, catalog, ground)
        if not bases:
            return None
        base = min(bases, key=lambda o: (float(np.hypot(*(np.asarray(o.position[:2]) - here))), o.name))
        brought = rehomed(proposal, base.name, "floor", here) if ground == "floor" else None
        out, names = brought or (proposal, ())
        base = next(o for o in out.objects if o.name == base.name)
        top = layout.object_top_surface(catalog, base)
        placed = resting(out, catalog, None, base.name, top.center, top.z)
        return None if placed is None else (placed[0], (*names, *placed[1]))
    carrier = next((o for o in proposal.objects if o.name == target.support), None)
    if carrier is None:
        return None
    away = here - np.asarray(layout.SHOULDER[:2])
    away = away / max(float(np.hypot(*away)), 1e-9)
    gap = layout.footprint_radius(catalog.get(carrier.asset), carrier.resting_pose) * carrier.scale
    gap += layout.footprint_radius(catalog.get(target.asset), target.resting_pose) * target.scale + SLACK
    xy = np.asarray(carrier.position[:2]) - gap * away  # toward the arm, off the carrier
    return resting(proposal, catalog, None, "table", xy, layout.TABLE_TOP_Z)


def stack_bases(proposal: SceneProposal, catalog: Catalog, ground: str) -> list:
    """What the target could be set on: stack bases with nothing on them, on the table within the arm's
    reach with the target on top (``ground`` table), or on the table or the floor (floor)."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    shoulder = np.asarray(layout.SHOULDER)
    asset = catalog.get(target.asset)
    height = asset.resting_poses[target.resting_pose].height * target.scale
    above = layout.pose_top(asset, target.resting_pose) * target.scale

    def reachable(base) -> bool:  # the target's centre or top on the base within the arm's reach
        top = layout.object_top_surface(catalog, base)
        centre = np.array([*top.center, top.z + height])
        near = min(np.linalg.norm(centre - shoulder), np.linalg.norm(centre + [0, 0, above] - shoulder))
        return float(near) <= layout.REACH[1] - 3 * SLACK

    return [
        o
        for o in proposal.objects
        if o.name != target.name
        and o.support in ((ground,) if ground == "table" else GROUNDS)
        and layout.is_stack_base(catalog.get(o.asset))
        and not any(p.support == o.name for p in proposal.objects)
        and (ground == "floor" or reachable(o))
    ]


def restacked(proposal: SceneProposal, catalog: Catalog):
    """A required stack whose target fell off its carrier or did not come to rest on it: the target set
    on the free base (``stack_bases``) whose top is widest, when it is wider than the carrier's; None
    otherwise."""
    target = next(o for o in proposal.objects if o.name == proposal.target)
    carrier = next((o for o in proposal.objects if o.name == target.support), None)
    if carrier is None or proposal.condition.tags.get("stacked") != "required":
        return None

    def width(o) -> float:
        return min(layout.object_top_surface(catalog, o).half)

    on = ground_of(proposal, target.name)
    bases = [o for o in stack_bases(proposal, catalog, on) if o.support == on]
    wider = [o for o in bases if width(o) > width(carrier)]
    if not wider:
        return None
    top = layout.object_top_surface(catalog, max(wider, key=lambda o: (width(o), o.name)))
    return resting(proposal, catalog, None, top.name, top.center, top.z)
