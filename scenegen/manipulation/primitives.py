"""Grasp primitives: short parameterised motions executed through the environment's controller.

A primitive has a planner, which turns what the robot sees (:class:`TargetView`: the target's visible
points from RGB-D and its mask, the other objects' points, and the robot's own state) into
parameters, and an executor, which moves the grip site through those parameters with the controller
(no teleporting, no welding). Each is designed from the physics of its case:

- ``top_grasp``: from above, fingers closing across the footprint's minor axis. The Panda hand opens
  8 cm: a footprint wider than ``MAX_GRASP_WIDTH`` is taken by its edge nearest the robot (a bowl's
  or plate's rim), fingers closing across the edge.
- ``side_grasp``: horizontally, from the side with the most free space around the target (measured
  from the other objects' points), at a third of the target's height: for objects whose top is
  blocked (under a board) or too wide to span from above but graspable across the body.
- ``toppled_grasp``: a body lying on its side, grasped across the body at half its lying height, at
  the visible points' centroid along it (the mass leans to the wide end).
- ``push_from_edge_then_grasp``: the closed hand pushes a target near a table edge 10 cm inward, low
  on its body so it slides rather than tips; then a top grasp from a new observation.
- ``pull_out_then_grasp``: the hand comes in horizontally, low on the target's body, from the freest
  side facing the robot, closes across the body and drags the target 20 cm back along its approach (a
  centimetre off the table); if the fingers still hold it (proprioception) it is lifted there, else
  the hand lets go and top-grasps it in the open from a new observation. Under a shelf's board a
  grasp lifted where the target stands lifts it into the board.

``PRIMITIVES`` maps a name to its :class:`Primitive`; ``version`` changes whenever a primitive's
behaviour does (expert labels are cached by it). A :class:`PlanGrid` is the resolution a plan is
executed at (positions to a grid of metres, directions to one of degrees); none by default: the
closed loop may set one so that heads whose plans differ below it execute, and share, one attempt.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from scenegen.manipulation.motion import CLOSE, OPEN, down_grasp, hold, servo, side_grasp
from scenegen.perception.observation import TargetView, observe
from scenegen.perception.robot_state import finger_gap, grip_site

MAX_GRASP_WIDTH = 0.07  # m: what the 8 cm hand spans with a margin for the estimate's error
ROUND = 1.15  # a footprint whose extents differ by less than this ratio has no major axis
APPROACH_HEIGHT = 0.10  # m above the target's top for a top grasp's approach
LIFT = 0.15  # m the grip site rises after closing (the task asks 5 cm of the target)
CLOSE_STEPS, HOLD_STEPS = 15, 30  # control steps to close the hand; to hold the lift (1.5 s at 20 Hz)


@dataclass(frozen=True)
class Primitive:
    """``plan(view) -> params``; ``execute(env, params, step=None, look=None, grid=None)``: ``step``
    takes an action, ``look()`` re-observes (-> observation, view) for primitives that look again,
    and the plan made there is executed on ``grid`` (:class:`PlanGrid`)."""

    name: str
    version: int
    plan: Callable[[TargetView], dict]
    execute: Callable[..., None]


PRIMITIVES: dict[str, Primitive] = {}
# the plans' unit vectors in the table plane; strings are kept as they are, the rest is metres
DIRECTIONS = ("closing", "approach", "heading", "direction")


@dataclass(frozen=True)
class PlanGrid:
    """The resolution a plan is executed at: every position and height rounded to a multiple of
    ``metres``, every direction (``DIRECTIONS``) turned to a multiple of ``degrees`` of heading."""

    metres: float
    degrees: float

    def __post_init__(self):
        if not (self.metres > 0 and self.degrees > 0):
            raise ValueError(f"plan grid {self.metres} m, {self.degrees} deg: both must be above 0")

    def key(self) -> str:
        return f"grid{self.metres:g}m{self.degrees:g}deg"

    def snap(self, plan: dict | None) -> dict | None:
        """``plan`` on this grid (None stays None: the target was not seen)."""
        if plan is None:
            return None

        def metres(v):
            return round(round(float(v) / self.metres) * self.metres, 9)

        out = {}
        for name, value in plan.items():
            if isinstance(value, str):
                out[name] = value
            elif name in DIRECTIONS:
                step = np.radians(self.degrees)
                heading = round(float(np.arctan2(value[1], value[0])) / step) * step
                # + 0.0: -0.0 and 0.0 (a heading of -180 and 180 degrees) are one plan
                out[name] = [round(float(np.cos(heading)), 9) + 0.0, round(float(np.sin(heading)), 9) + 0.0]
            else:
                out[name] = [metres(v) for v in value] if isinstance(value, list) else metres(value)
        return out


def make_plan(name: str, view: TargetView, grid: PlanGrid | None = None) -> dict:
    """``name``'s plan for ``view``, on ``grid`` where one is given."""
    plan = PRIMITIVES[name].plan(view)
    return plan if grid is None else grid.snap(plan)


def primitive(name: str, version: int):
    """Register a (plan, execute) pair under ``name``: decorate the planner, pass the executor."""

    def register(plan):
        def with_executor(execute):
            PRIMITIVES[name] = Primitive(name, version, plan, execute)
            return execute

        return with_executor

    return register


def close_at(env, position, rotation, step, approach=None) -> None:
    """Approach (if given), move to the grasp pose open and close the hand."""
    if approach is not None:
        servo(env, approach, rotation, OPEN, max_steps=100, step=step)
    servo(env, position, rotation, OPEN, max_steps=80, speed=0.4, step=step)
    hold(env, CLOSE, CLOSE_STEPS, step=step)


def lift_and_hold(env, rotation, step) -> None:
    """Raise the closed hand ``LIFT`` from where it is and hold it there."""
    here, _ = grip_site(env)
    servo(env, here + np.array([0.0, 0.0, LIFT]), rotation, CLOSE, max_steps=60, speed=0.4, step=step)
    hold(env, CLOSE, HOLD_STEPS, step=step)


def _grasp_and_lift(env, position, rotation, step, approach=None) -> None:
    """Approach (if given), move to the grasp pose open, close, lift ``LIFT`` and hold."""
    close_at(env, position, rotation, step, approach)
    lift_and_hold(env, rotation, step)


# ------------------------------------------------------------------------------------------ top grasp
def plan_top_grasp(view: TargetView) -> dict:
    t = view.target
    major = np.array([np.cos(t.yaw), np.sin(t.yaw)])
    minor = np.array([-major[1], major[0]])
    centre = t.centre[:2]
    closing = minor
    if t.extent[0] < ROUND * t.extent[1]:  # a round footprint has no axis: keep the hand's
        closing = np.asarray(view.hand_closing, float)
    if closing @ np.asarray(view.hand_closing) < 0:  # the hand is symmetric: turn it the short way
        closing = -closing
    if t.extent[1] > MAX_GRASP_WIDTH:  # too wide to span: take the edge nearest the robot
        inward = centre - np.asarray(view.robot_base)
        inward /= np.linalg.norm(inward)
        radius = 0.5 * t.extent[1]
        centre = centre - inward * (radius - 0.015)
        closing = inward
    grasp_z = max(t.top_z - 0.03, t.bottom_z + 0.01)
    return {
        "position": [float(centre[0]), float(centre[1]), float(grasp_z)],
        "closing": [float(closing[0]), float(closing[1])],
        "approach_z": float(t.top_z + APPROACH_HEIGHT),
    }


@primitive("top_grasp", version=1)(plan_top_grasp)
def execute_top_grasp(env, params: dict, step=None, look=None, grid=None) -> None:
    rotation = down_grasp(np.asarray(params["closing"]))
    position = np.asarray(params["position"])
    approach = np.array([position[0], position[1], params["approach_z"]])
    _grasp_and_lift(env, position, rotation, step, approach=approach)


# ----------------------------------------------------------------------------------------- side grasp
SIDE_DIRECTIONS = 8  # candidate approach directions, every 45 degrees
SIDE_STANDOFF = 0.12  # m from the target's centre where the hand waits before moving in


def _clearance(view: TargetView, direction: np.ndarray) -> float:
    """Free distance (m) along the corridor the hand sweeps when approaching along ``-direction``
    towards the target (the hand comes from ``centre + direction * standoff``)."""
    t = view.target
    if len(view.others) == 0:
        return np.inf
    rel = view.others[:, :2] - t.centre[:2]
    along = rel @ direction
    across = np.abs(rel @ np.array([-direction[1], direction[0]]))
    band = (view.others[:, 2] > t.bottom_z - 0.01) & (view.others[:, 2] < t.top_z + 0.10)
    in_corridor = band & (along > 0) & (across < 0.06)
    return float(along[in_corridor].min()) if in_corridor.any() else np.inf


def plan_side_grasp(view: TargetView, max_angle: float = np.pi / 2) -> dict:
    """Approach directions within ``max_angle`` of the robot's side (the hand cannot come from behind
    the target); the freest one, ties to the one facing the robot."""
    t = view.target
    centre = t.centre[:2]
    to_robot = np.asarray(view.robot_base) - centre
    best, best_score = None, -np.inf
    for k in range(SIDE_DIRECTIONS):
        angle = 2 * np.pi * k / SIDE_DIRECTIONS
        direction = np.array([np.cos(angle), np.sin(angle)])
        if direction @ to_robot < np.cos(max_angle) * np.linalg.norm(to_robot) - 1e-9:
            continue
        clearance = min(_clearance(view, direction), 1.0)
        score = clearance + 0.05 * direction @ to_robot / np.linalg.norm(to_robot)
        if score > best_score:
            best, best_score = direction, score
    grasp_z = t.bottom_z + max(0.02, min(0.05, t.height / 3))
    radius = 0.5 * t.extent[1]
    position = centre + best * max(radius - 0.02, 0.0)
    standoff = centre + best * (radius + SIDE_STANDOFF)
    return {
        "position": [float(position[0]), float(position[1]), float(grasp_z)],
        "standoff": [float(standoff[0]), float(standoff[1]), float(grasp_z)],
        "approach": [float(-best[0]), float(-best[1])],
    }


def _side_standoff(env, params: dict, step) -> np.ndarray:
    """Rise, turn the hand horizontal above the stand-off point, come down beside the target; the
    hand's rotation."""
    rotation = side_grasp(np.asarray(params["approach"]))
    standoff = np.asarray(params["standoff"])
    here, _ = grip_site(env)
    servo(env, [standoff[0], standoff[1], max(here[2], standoff[2] + 0.15)], rotation, OPEN, 100, step=step)
    servo(env, standoff, rotation, OPEN, max_steps=150, step=step)
    return rotation


@primitive("side_grasp", version=1)(plan_side_grasp)
def execute_side_grasp(env, params: dict, step=None, look=None, grid=None) -> None:
    rotation = _side_standoff(env, params, step)
    _grasp_and_lift(env, np.asarray(params["position"]), rotation, step)


# ------------------------------------------------------------------------------------ toppled grasp
def plan_toppled_grasp(view: TargetView) -> dict:
    """A body lying on its side: fingers close across the body (the footprint's minor axis) at half
    its lying height, at the points' centroid along the body (the mass leans to the wide end, not
    the neck): no rim to pinch, and the body is narrower than the hand."""
    t = view.target
    major = np.array([np.cos(t.yaw), np.sin(t.yaw)])
    minor = np.array([-major[1], major[0]])
    along = (t.centroid[:2] - t.centre[:2]) @ major
    point = t.centre[:2] + along * major
    closing = minor if minor @ np.asarray(view.hand_closing) >= 0 else -minor
    grasp_z = t.bottom_z + 0.5 * t.height
    return {
        "position": [float(point[0]), float(point[1]), float(grasp_z)],
        "closing": [float(closing[0]), float(closing[1])],
        "approach_z": float(t.top_z + APPROACH_HEIGHT),
    }


@primitive("toppled_grasp", version=1)(plan_toppled_grasp)
def execute_toppled_grasp(env, params: dict, step=None, look=None, grid=None) -> None:
    execute_top_grasp(env, params, step)


# ---------------------------------------------------------------------- push from the edge, then grasp
TABLE_HALF = (0.4, 0.5)  # m: the table top's half extents around the origin (the robot's map)
PUSH = 0.10  # m the target is pushed inward


def plan_push_from_edge(view: TargetView) -> dict:
    """A target close to a table edge: a top grasp there has the hand's outer finger over the edge and
    the target tipping off when touched. Push it inward first: the closed hand comes down beside the
    target on the edge side, a finger-width above the table, and pushes ``PUSH`` towards the table's
    middle; then a top grasp from a new observation."""
    t = view.target
    x, y = t.centre[:2]
    gaps = {  # distance to each edge the hand can work from (the robot stands behind x = -0.4)
        (1.0, 0.0): TABLE_HALF[0] - x,
        (0.0, 1.0): TABLE_HALF[1] - y,
        (0.0, -1.0): TABLE_HALF[1] + y,
    }
    outward = np.asarray(min(gaps, key=gaps.get))
    radius = 0.5 * t.extent[1]
    start = t.centre[:2] + outward * (radius + 0.03)
    end = start - outward * PUSH
    z = t.bottom_z + min(0.015, 0.5 * t.height)  # low: a push high up a tall body tips it over
    return {
        "position": [float(end[0]), float(end[1]), float(z)],
        "start": [float(start[0]), float(start[1]), float(z)],
        "closing": [float(outward[1]), float(-outward[0])],  # fingers along the edge: a flat pusher
    }


@primitive("push_from_edge_then_grasp", version=1)(plan_push_from_edge)
def execute_push_from_edge(env, params: dict, step=None, look=None, grid=None) -> None:
    rotation = down_grasp(np.asarray(params["closing"]))
    start = np.asarray(params["start"])
    servo(env, start + np.array([0, 0, 0.12]), rotation, CLOSE, max_steps=100, step=step)
    servo(env, start, rotation, CLOSE, max_steps=60, speed=0.4, step=step)
    servo(env, params["position"], rotation, CLOSE, max_steps=80, speed=0.3, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([0, 0, 0.12]), rotation, OPEN, max_steps=40, step=step)
    _regrasp(env, step, look, grid)


def _regrasp(env, step, look=None, grid=None) -> None:
    """Re-observe (a new decision point's frames, through ``look``: the episode's perception, by
    default the oracle's) and top-grasp from there, the plan on ``grid``."""
    _, view = look() if look is not None else observe(env)
    if view is not None:
        execute_top_grasp(env, make_plan("top_grasp", view, grid), step)


# --------------------------------------------------------------------------- pull out, then grasp
PULL = 0.20  # m the target is dragged towards the robot: a can under the board's middle comes clear
PULL_RISE = 0.01  # m the held target is raised while dragged: it slides without scraping the table
RETREAT = 0.08  # m the open hand backs off along the pull before rising


def plan_pull_out(view: TargetView) -> dict:
    """A target under an overhang or hemmed in by clutter: a hand from above meets the board or the
    neighbours, and a grasp lifted where the target stands lifts it into the board. The hand comes in
    horizontally, low on the target's body, from the freest side that faces the robot (a shelf is open
    towards the robot), closes across the body and drags it ``PULL`` back along its approach, a
    centimetre off the table. Still held (the fingers stay apart), it is lifted there; lost on the way,
    the hand lets go, backs off, and a top grasp from a new observation takes the target in the open
    (a held target needs no new observation). The horizontal hand is 6.5 cm thick: it fits under a
    shelf's board above a low body, where an upright hand (20 cm tall across its fingers' travel)
    does not."""
    side = plan_side_grasp(view, max_angle=np.pi / 4)
    back = -np.asarray(side["approach"])
    end = np.asarray(side["position"]) + np.array([*(back * PULL), PULL_RISE])
    side["pulled"] = [float(v) for v in end]
    return side


HELD_GAP = 0.01  # m: fingers commanded closed but this far apart hold the target


@primitive("pull_out_then_grasp", version=3)(plan_pull_out)
def execute_pull_out(env, params: dict, step=None, look=None, grid=None) -> None:
    rotation = _side_standoff(env, params, step)
    close_at(env, params["position"], rotation, step)
    servo(env, params["pulled"], rotation, CLOSE, max_steps=120, speed=0.3, step=step)
    if finger_gap(env) > HELD_GAP:  # still held, out in the open: lift it as it is
        lift_and_hold(env, rotation, step)
        return
    hold(env, OPEN, CLOSE_STEPS, step=step)  # lost on the way: let go, back off, grasp it anew
    here, _ = grip_site(env)
    back = -np.asarray(params["approach"]) * RETREAT
    servo(env, here + np.array([back[0], back[1], 0.0]), rotation, OPEN, max_steps=40, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([0.0, 0.0, 0.15]), rotation, OPEN, max_steps=60, step=step)
    _regrasp(env, step, look, grid)
