"""Candidate actions for a learned recovery proposal model (issue 63): sampled generically from what
the robot sees, executed through the controller, labelled by simulation and ranked by a model.

The hand planners (``primitives.py``) each encode a case: a toppled body is grasped across its lying
height, a target at an edge is pushed inward. The sampler here holds no such rule: for any view it
draws the same kinds of candidates from the target's visible points, and which of them work is left
to simulation (the labels) and to a model that learns from them. One code path serves an upright
can and a toppled one (tests/manipulation/test_proposals.py traces it).

Actions (``ACTIONS``; a candidate's parameters are plain JSON, on a :class:`PlanGrid` so that plans
that differ below the grid execute, and share, one stored attempt):

- ``grasp``: the grip site goes to ``position`` with the hand pointing down (``approach: top``,
  the fingers closing along ``heading``) or horizontally (``approach: side``, coming along
  ``heading``, the fingers closing across it), closes, lifts ``LIFT`` and holds; the gripper is
  binary (no width). Fingers that closed on nothing (the robot feels it) open and rise instead of
  lifting: the attempt is over, a third of its time saved. A top grasp closes across the visible
  points on a line along its axis: centred between their extremes, or inside the line's end where
  the hand cannot span it, never under the line's mid-height (sampler version 4; the pilots behind
  versions 3 and 4 are in docs/policy.md).
- ``push``: the closed hand comes down ``STANDOFF`` behind ``contact`` (against ``direction``) and
  pushes ``distance`` along ``direction``, then rises, open.
- ``pull``: the open hand comes in horizontally along ``approach`` to ``position``, closes, drags
  ``distance`` back against ``approach`` a centimetre off the table, lets go and backs off.

A push or a pull ends the decision: what follows is a new observation and a new proposal, never a
hand planner.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from scenegen.manipulation.motion import CLOSE, OPEN, down_grasp, hold, servo, side_grasp
from scenegen.manipulation.primitives import (
    APPROACH_HEIGHT,
    CLOSE_STEPS,
    HELD_GAP,
    MAX_GRASP_WIDTH,
    PlanGrid,
    close_at,
    lift_and_hold,
)
from scenegen.perception.observation import TargetView
from scenegen.perception.robot_state import finger_gap, grip_site

SAMPLER_VERSION = 4  # bump when what the sampler draws changes (labels are keyed by it)
APPROACHES = ("top", "side")
STANDOFF = 0.03  # m behind a push's contact point where the closed hand comes down
SIDE_STANDOFF = 0.15  # m back along a side approach where the open hand waits before moving in
TABLE_CLEARANCE = 0.01  # m: the grip site stays this far above the lowest visible point
SIDE_CLEARANCE = 0.02  # m: a horizontal hand's grip site this far up (its fingers reach lower)
STRIP = 0.01  # m: half-width of the line of visible points a top grasp closes across
EDGE_IN = 0.015  # m inside the end of a line wider than the hand spans where a top grasp closes (a rim)
REACH_IN = 0.05  # m: a horizontal approach ends up to this far past the visible point, inside the body
PULL_RISE = 0.01  # m a pulled target is raised while dragged
RETREAT = 0.08  # m the open hand backs off after a pull
RISE = 0.12  # m the hand rises after a push or pull
PUSH_SPEED = 1.0  # of the controller's step: slower, its force stays below a can's friction (measured)
PUSH_DISTANCES = (0.05, 0.10, 0.15)  # m
PULL_DISTANCES = (0.10, 0.20)  # m
FACING = np.pi / 2  # rad: a horizontal approach within this of the direction from the robot (reach)


@dataclass(frozen=True)
class Action:
    """``execute(env, params, step)``: the motion; ``version`` changes when it does."""

    name: str
    version: int
    execute: Callable[..., None]


ACTIONS: dict[str, Action] = {}


def action(name: str, version: int):
    def register(execute):
        ACTIONS[name] = Action(name, version, execute)
        return execute

    return register


@dataclass(frozen=True)
class Candidate:
    """One action with its parameters (JSON values: lists of floats, floats, strings)."""

    action: str
    params: dict = field(hash=False)

    def __post_init__(self):
        if self.action not in ACTIONS:
            raise ValueError(f"candidate action {self.action!r}: choose one of {', '.join(ACTIONS)}")

    def as_dict(self) -> dict:
        return {"action": self.action, **self.params}

    @classmethod
    def from_dict(cls, row: dict) -> Candidate:
        params = {k: v for k, v in row.items() if k != "action"}
        return cls(row["action"], params)


@dataclass(frozen=True)
class SamplerConfig:
    """How many candidates of each kind one view gets."""

    top: int = 12
    side: int = 8
    push: int = 6
    pull: int = 6

    @property
    def total(self) -> int:
        return self.top + self.side + self.push + self.pull


# ---------------------------------------------------------------------------------------- sampling
def _unit(angle: float) -> list[float]:
    return [float(np.cos(angle)), float(np.sin(angle))]


def _facing(view: TargetView, rng: np.random.Generator, at: np.ndarray) -> float:
    """A heading for a horizontal approach to ``at``: within ``FACING`` of the direction from the
    robot's base (the arm cannot come from behind what it reaches)."""
    outward = at[:2] - np.asarray(view.robot_base)
    return float(np.arctan2(outward[1], outward[0]) + rng.uniform(-FACING, FACING))


def _points(view: TargetView) -> np.ndarray:
    if view.target_points is None or len(view.target_points) == 0:
        raise ValueError("the view holds no target points: observe() with this version fills them")
    return np.asarray(view.target_points, float)


def _antipodal_top(points: np.ndarray, rng: np.random.Generator) -> dict:
    """A top grasp whose fingers close along a random axis across the visible points on a
    ``STRIP`` line through a random visible point: centred midway between the line's extremes, or,
    where the line is wider than the hand spans (``MAX_GRASP_WIDTH``), ``EDGE_IN`` inside its end
    nearer the drawn point (a rim, an edge). The fingers meet what is seen from both sides, whatever
    the body is and however it lies. The grip site goes 0-4 cm under the line's top, never under the
    line's mid-height (a flat utensil lies wholly under ``TABLE_CLEARANCE``: a floor of the lowest
    point + the clearance, sampler version 3's, put the fingers over it)."""
    axis = np.array(_unit(rng.uniform(0, np.pi)))
    across = np.array([-axis[1], axis[0]])
    p = points[rng.integers(len(points))]
    line = points[np.abs((points[:, :2] - p[:2]) @ across) < STRIP]  # p itself is on it
    along = line[:, :2] @ axis
    lo, hi, at = float(along.min()), float(along.max()), float(p[:2] @ axis)
    if hi - lo <= MAX_GRASP_WIDTH:
        middle = 0.5 * (lo + hi)
    else:
        middle = lo + EDGE_IN if at - lo <= hi - at else hi - EDGE_IN
    centre = p[:2] + axis * (middle - at)
    top = float(np.percentile(line[:, 2], 98))
    z = max(0.5 * (float(np.percentile(line[:, 2], 2)) + top), top - rng.uniform(0.0, 0.04))
    return {
        "approach": "top",
        "position": [float(centre[0]), float(centre[1]), float(z)],
        "heading": axis.tolist(),
    }


def sample_candidates(
    view: TargetView,
    rng: np.random.Generator,
    config: SamplerConfig = SamplerConfig(),
    grid: PlanGrid | None = None,
) -> list[Candidate]:
    """``config``'s candidates for ``view``, drawn from ``rng``, snapped to ``grid`` (duplicates
    on the grid kept once, in order). Every draw starts from a visible point of the target and its
    seen height range; none looks at what the target is or how it lies."""
    points = _points(view)
    low = float(np.percentile(points[:, 2], 2)) + TABLE_CLEARANCE
    top = max(low, float(np.percentile(points[:, 2], 98)))  # a fork lies lower than the clearance

    def point() -> np.ndarray:
        return points[rng.integers(len(points))]

    def height(p: np.ndarray, clearance: float = TABLE_CLEARANCE) -> float:  # at or below p, above the lowest
        floor = low + clearance - TABLE_CLEARANCE
        return float(max(floor, min(p[2], rng.uniform(floor, max(floor, top)))))

    def inside(p: np.ndarray, heading: list[float]) -> list[float]:  # past the surface, along the approach
        reach = rng.uniform(0.0, REACH_IN)
        return [float(p[0] + heading[0] * reach), float(p[1] + heading[1] * reach), height(p, SIDE_CLEARANCE)]

    out = [Candidate("grasp", _antipodal_top(points, rng)) for _ in range(config.top)]
    for _ in range(config.side):
        p = point()
        heading = _unit(_facing(view, rng, p))
        params = {"approach": "side", "position": inside(p, heading), "heading": heading}
        out.append(Candidate("grasp", params))
    for _ in range(config.push):
        p = point()
        params = {"contact": [float(p[0]), float(p[1]), height(p)]}
        params["direction"] = _unit(rng.uniform(0, 2 * np.pi))
        params["distance"] = float(rng.choice(PUSH_DISTANCES))
        out.append(Candidate("push", params))
    for _ in range(config.pull):
        p = point()
        approach = _unit(_facing(view, rng, p))
        params = {"position": inside(p, approach), "approach": approach}
        params["distance"] = float(rng.choice(PULL_DISTANCES))
        out.append(Candidate("pull", params))
    if grid is None:
        return out
    snapped, seen = [], set()
    for c in out:
        s = Candidate(c.action, grid.snap(c.params))
        key = repr(sorted(s.as_dict().items()))
        if key not in seen:
            seen.add(key)
            snapped.append(s)
    return snapped


# --------------------------------------------------------------------------------------- execution
def _grasp_rotation(params: dict) -> np.ndarray:
    heading = np.asarray(params["heading"], float)
    return down_grasp(heading) if params["approach"] == "top" else side_grasp(heading)


@action("grasp", version=1)
def execute_grasp(env, params: dict, step=None) -> None:
    """Approach, close; if the fingers closed on nothing (proprioception: ``HELD_GAP``), open and
    rise, the attempt over; else lift and hold."""
    rotation = _grasp_rotation(params)
    position = np.asarray(params["position"], float)
    if params["approach"] == "top":
        approach = position + np.array([0.0, 0.0, APPROACH_HEIGHT])
        close_at(env, position, rotation, step, approach=approach)
    else:
        _side_in(env, position, np.asarray(params["heading"], float), rotation, step)
        hold(env, CLOSE, CLOSE_STEPS, step=step)
    if finger_gap(env) <= HELD_GAP:  # nothing between the fingers: lifting would lift nothing
        hold(env, OPEN, CLOSE_STEPS, step=step)
        here, _ = grip_site(env)
        servo(env, here + np.array([0.0, 0.0, RISE]), rotation, OPEN, max_steps=40, step=step)
        return
    lift_and_hold(env, rotation, step)


def _side_in(env, position: np.ndarray, heading: np.ndarray, rotation: np.ndarray, step) -> None:
    """Rise, turn horizontal above the stand-off point back along ``heading``, come down beside the
    target and move in, open."""
    standoff = position - np.array([*(heading * SIDE_STANDOFF), 0.0])
    here, _ = grip_site(env)
    servo(env, [standoff[0], standoff[1], max(here[2], standoff[2] + 0.15)], rotation, OPEN, 100, step=step)
    servo(env, standoff, rotation, OPEN, max_steps=150, step=step)
    servo(env, position, rotation, OPEN, max_steps=80, speed=0.4, step=step)


@action("push", version=1)
def execute_push(env, params: dict, step=None) -> None:
    direction = np.asarray(params["direction"], float)
    rotation = down_grasp(np.array([direction[1], -direction[0]]))  # fingers across the push: a flat pusher
    contact = np.asarray(params["contact"], float)
    start = contact - np.array([*(direction * STANDOFF), 0.0])
    end = contact + np.array([*(direction * params["distance"]), 0.0])
    servo(env, start + np.array([0, 0, RISE]), rotation, CLOSE, max_steps=100, step=step)
    servo(env, start, rotation, CLOSE, max_steps=60, speed=0.4, step=step)
    servo(env, end, rotation, CLOSE, max_steps=80, speed=PUSH_SPEED, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([0, 0, RISE]), rotation, OPEN, max_steps=40, step=step)


@action("pull", version=1)
def execute_pull(env, params: dict, step=None) -> None:
    approach = np.asarray(params["approach"], float)
    rotation = side_grasp(approach)
    position = np.asarray(params["position"], float)
    _side_in(env, position, approach, rotation, step)
    hold(env, CLOSE, CLOSE_STEPS, step=step)
    end = position + np.array([*(-approach * params["distance"]), PULL_RISE])
    servo(env, end, rotation, CLOSE, max_steps=120, speed=0.3, step=step)
    hold(env, OPEN, CLOSE_STEPS, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([*(-approach * RETREAT), 0.0]), rotation, OPEN, max_steps=40, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([0.0, 0.0, RISE]), rotation, OPEN, max_steps=60, step=step)


def execute(env, candidate: Candidate, step=None) -> None:
    """Run ``candidate`` from the environment's current state through the controller."""
    ACTIONS[candidate.action].execute(env, candidate.params, step=step)
