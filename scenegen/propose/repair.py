"""Repair instead of reject: which part of a failed proposal to re-sample, and in which order to try.

A rejection names what failed: the colliding pair (``obj2_mug~obj5_bowl``), the object that moved
or fell, the unreachable target, the request's missing tags. :func:`resampled_for` turns it into
the parts a repair re-denoises with the rest of the scene held fixed (the diffusion proposer's
``repair``: RePaint-style inpainting, scenegen/diffusion/sample.py ``Inpaint``):

- a named object (a collision, out of the workspace, unsupported, unstable, fallen, too close to
  the arm): that object; of a colliding pair, the one that is not the target;
- furniture too close to the arm: the furniture;
- an unreachable target, or a missing tag of the target's own pose or place (near_edge,
  under_overhang, toppled, stacked, on_floor): the target;
- a missing occluded or clutter: every other object; a missing low_light: the lights; a forbidden
  tag that holds: the target;
- nothing named (the scene never came to rest): every object but the target.

An unrealistic scene or a failed render is not repaired. :class:`RepairSearch` orders the tries of
one proposal index: with ``width`` 1 a chain (each repair repairs the last), wider a best-first
search over the tree of repairs, the rejection's :func:`severity` as the cost. It decides only when
every child of an expansion has come back, and ties go to the lower attempt number, so the tries
and their order do not depend on which worker answers first. Pure: no torch, no files.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from scenegen.schema.scene import Rejection, RepairStep, SceneProposal

FURNITURE, LIGHTS = "furniture", "lights"
TARGET_TAGS = ("near_edge", "under_overhang", "toppled", "stacked", "on_floor")
OTHERS_TAGS = ("occluded", "clutter")
NAMED = ("out_of_workspace", "unsupported", "collision", "unstable", "fell_off", "robot_overlap")
NOT_REPAIRED = ("unrealistic", "render_failed")
STAGE_COST = {"check": 3.0, "settle": 2.0, "tag": 1.0}


def _named(detail: str, names: list[str]) -> list[str]:
    return [n for n in names if re.search(rf"(?<![\w]){re.escape(n)}(?![\w])", detail)]


def resampled_for(rejection: Rejection, proposal: SceneProposal) -> tuple[str, ...]:
    """The parts of ``proposal`` a repair of ``rejection`` re-samples (object names, ``furniture``,
    ``lights``; see the module docstring); () when it is not repaired."""
    if rejection.label in NOT_REPAIRED:
        return ()
    objects = [o.name for o in proposal.objects]
    others = [n for n in objects if n != proposal.target]
    parts: list[str] = []
    if rejection.label == "unreachable":
        parts = [proposal.target]
    elif rejection.label == "condition_unmet":
        unmet = set(re.findall(r"required (\w+) =", rejection.detail))
        present = set(re.findall(r"forbidden (\w+) =", rejection.detail))
        if unmet & {*TARGET_TAGS} or present:  # a forbidden tag that holds: the target moves
            parts.append(proposal.target)
        if unmet & {*OTHERS_TAGS}:
            parts += others
        if "low_light" in unmet:
            parts.append(LIGHTS)
    elif rejection.label in NAMED:
        named = _named(rejection.detail, objects)
        if len(named) > 1:
            named = [n for n in named if n != proposal.target] or named
        parts = named
        if not named and _named(rejection.detail, [f.name for f in proposal.furniture]):
            parts = [FURNITURE]
    if not parts:  # nothing named: every object but the target, or the target alone
        parts = others or [proposal.target]
    return tuple(dict.fromkeys(parts))


def severity(rejection: Rejection) -> float:
    """A rejection's cost for the search (lower is closer to accepted): geometry 3, settling 2, the
    request's tags 1 plus a tenth per unmet tag."""
    cost = STAGE_COST.get(rejection.stage, 4.0)
    if rejection.label == "condition_unmet":
        cost += 0.1 * (rejection.value or 0.0)
    return cost


def repair_step(
    rejection: Rejection, parent: SceneProposal, attempt: int, resampled, method: str = "denoise"
) -> RepairStep:
    """The row of a repair path that re-samples (``method`` denoise) or moves (project) ``resampled``
    of ``parent`` for ``rejection``."""
    return RepairStep(
        attempt=attempt,
        parent=parent.attempt,
        label=rejection.label,
        check=rejection.check,
        detail=rejection.detail[:200],
        resampled=tuple(resampled),
        method=method,
    )


@dataclass
class RepairSearch:
    """The tries of one proposal index. ``budget``: repairs allowed after the first pass; ``width``:
    repairs made per expansion (1: a chain); ``labels``: the rejection labels that are repaired (None:
    every one but those of ``NOT_REPAIRED``). :meth:`next_parents` is called when every try sent out
    has come back; it returns the next tries' parents, or [] when the search is over."""

    budget: int
    width: int = 1
    labels: tuple[str, ...] | None = None
    used: int = 0
    frontier: list = field(default_factory=list)  # (severity, attempt, proposal, rejection)

    def add(self, proposal: SceneProposal, rejection: Rejection) -> None:
        """A try came back rejected."""
        if self.labels is not None and rejection.label not in self.labels:
            return
        if rejection.label not in NOT_REPAIRED:
            self.frontier.append((severity(rejection), proposal.attempt, proposal, rejection))

    def next_parents(self) -> list[tuple[SceneProposal, Rejection, int]]:
        """(parent, its rejection, attempt number) of each repair to make next: ``width`` repairs of
        the best try not yet expanded (with width 1: of the latest try), numbered in order."""
        if self.used >= self.budget or not self.frontier:
            return []
        if self.width == 1:
            pick = max(self.frontier, key=lambda f: f[1])  # the chain goes on from its last try
        else:
            pick = min(self.frontier, key=lambda f: (f[0], f[1]))
        self.frontier.remove(pick)
        n = min(self.width, self.budget - self.used)
        out = [(pick[2], pick[3], self.used + 1 + k) for k in range(n)]
        self.used += n
        return out
