"""Overlap projection: small horizontal pushes that take a proposal's interpenetrating objects apart.

A learned proposer places objects to within a few millimetres to centimetres; most of its
collisions are shallow overlaps (measured on the default checkpoint: 3 mm to 5 cm) that the collision
check would reject. :func:`separate` resolves them the way the decoder snaps objects onto their
resting heights: as a projection onto the feasible set that moves objects as little as it can and
adds the distance to each object's ``projection_distance``.

Per round, every pair whose signed distance (the check's own, ``check.geometry.signed_distance``) is
below ``clearance`` is pushed apart along the line between their centres in the table plane, each
object taking half. Objects stacked on a moved object move with it; a stacked pair is left to the
support check. An object that hits a piece of furniture (a shelf leg or board, a bin wall) takes the
whole push, away from that board's centre. An object stops once it has moved ``max_shift``; what
still overlaps then is the collision check's to reject. The checks themselves are unchanged:
separating only changes what they are shown.
"""

from __future__ import annotations

import math

import numpy as np

from scenegen.assets.catalog import Catalog
from scenegen.check.geometry import Solid, _aabb_overlap, box_solid, object_solid, signed_distance
from scenegen.schema.scene import ObjectPlacement, SceneProposal
from scenegen.world import furniture_boxes


def _direction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit vector in the table plane from ``b`` to ``a`` (+x when they coincide)."""
    d = np.asarray(a[:2], float) - np.asarray(b[:2], float)
    n = float(np.hypot(*d))
    return d / n if n > 1e-9 else np.array([1.0, 0.0])


def separate(
    proposal: SceneProposal,
    catalog: Catalog,
    clearance: float = 0.002,
    max_shift: float = 0.05,
    rounds: int = 8,
) -> SceneProposal:
    """``proposal`` with interpenetrating objects pushed apart (see the module docstring)."""
    objects = list(proposal.objects)
    if not objects:
        return proposal
    names = [o.name for o in objects]
    furniture = [(box[0], box_solid(p.name, [box])) for p in proposal.furniture for box in furniture_boxes(p)]
    solids: list[Solid] = [object_solid(catalog, o) for o in objects]
    shift = np.zeros((len(objects), 2))

    def carried(i: int) -> list[int]:
        """Object i and everything stacked on it, transitively."""
        out, frontier = [i], [i]
        while frontier:
            base = names[frontier.pop()]
            above = [j for j, o in enumerate(objects) if o.support == base and j not in out]
            out += above
            frontier += above
        return out

    for _ in range(rounds):
        push = np.zeros_like(shift)
        for i, a in enumerate(solids):
            for j in range(i + 1, len(solids)):
                b = solids[j]
                if objects[i].support == names[j] or objects[j].support == names[i]:
                    continue  # one rests on the other: the support check's business
                if not _aabb_overlap(a, b, clearance):
                    continue
                gap = clearance - signed_distance(a, b)
                if gap > 0:
                    u = _direction(objects[i].position, objects[j].position)
                    push[i] += 0.5 * gap * u
                    push[j] -= 0.5 * gap * u
            for center, solid in furniture:
                if not _aabb_overlap(a, solid, clearance):
                    continue
                gap = clearance - signed_distance(a, solid)
                if gap > 0:
                    push[i] += gap * _direction(objects[i].position, center)
        if not push.any():
            break
        moved = False
        for i in range(len(objects)):
            room = max_shift - float(np.hypot(*shift[i]))
            step = push[i]
            norm = float(np.hypot(*step))
            if norm < 1e-9 or room <= 1e-9:
                continue
            step = step * min(1.0, room / norm)
            for k in carried(i):
                shift[k] += step
                x, y, z = objects[k].position
                objects[k] = objects[k].model_copy(update={"position": (x + step[0], y + step[1], z)})
                solids[k] = object_solid(catalog, objects[k])
            moved = True
        if not moved:
            break
    if not shift.any():
        return proposal
    placed = tuple(
        _moved(o, float(np.hypot(*s))) if np.any(s) else o for o, s in zip(objects, shift, strict=True)
    )
    return proposal.model_copy(update={"objects": placed})


def _moved(obj: ObjectPlacement, distance: float) -> ObjectPlacement:
    position = tuple(round(float(v), 6) for v in obj.position)
    total = math.hypot(obj.projection_distance, distance)  # snap is vertical, push horizontal
    return obj.model_copy(update={"position": position, "projection_distance": round(total, 6)})
