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

``PRIMITIVES`` maps a name to its :class:`Primitive`; ``version`` changes whenever a primitive's
behaviour does (expert labels are cached by it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from scenegen.policy.motion import CLOSE, OPEN, down_grasp, grip_site, hold, servo, side_grasp
from scenegen.policy.perception import TargetEstimate

MAX_GRASP_WIDTH = 0.07  # m: what the 8 cm hand spans with a margin for the estimate's error
ROUND = 1.15  # a footprint whose extents differ by less than this ratio has no major axis
APPROACH_HEIGHT = 0.10  # m above the target's top for a top grasp's approach
LIFT = 0.15  # m the grip site rises after closing (the task asks 5 cm of the target)
CLOSE_STEPS, HOLD_STEPS = 15, 30  # control steps to close the hand; to hold the lift (1.5 s at 20 Hz)


@dataclass(frozen=True)
class TargetView:
    """What a planner may use. ``target``: the target as seen; ``others``: (N, 3) world points of the
    other objects and furniture; ``robot_base``: (x, y) of the robot's base (it faces +x)."""

    target: TargetEstimate
    others: np.ndarray
    robot_base: tuple[float, float] = (-0.56, 0.0)
    hand_closing: tuple[float, float] = (0.0, 1.0)  # the fingers' closing axis now, (x, y) (proprioception)


@dataclass(frozen=True)
class Primitive:
    name: str
    version: int
    plan: Callable[[TargetView], dict]
    execute: Callable[..., None]


PRIMITIVES: dict[str, Primitive] = {}


def primitive(name: str, version: int):
    """Register a (plan, execute) pair under ``name``: decorate the planner, pass the executor."""

    def register(plan):
        def with_executor(execute):
            PRIMITIVES[name] = Primitive(name, version, plan, execute)
            return execute

        return with_executor

    return register


def _grasp_and_lift(env, position, rotation, step, approach=None) -> None:
    """Approach (if given), move to the grasp pose open, close, lift ``LIFT`` and hold."""
    if approach is not None:
        servo(env, approach, rotation, OPEN, max_steps=100, step=step)
    servo(env, position, rotation, OPEN, max_steps=80, speed=0.4, step=step)
    hold(env, CLOSE, CLOSE_STEPS, step=step)
    here, _ = grip_site(env)
    servo(env, here + np.array([0.0, 0.0, LIFT]), rotation, CLOSE, max_steps=60, speed=0.4, step=step)
    hold(env, CLOSE, HOLD_STEPS, step=step)


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
def execute_top_grasp(env, params: dict, step=None) -> None:
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


def plan_side_grasp(view: TargetView) -> dict:
    t = view.target
    centre = t.centre[:2]
    to_robot = np.asarray(view.robot_base) - centre
    best, best_score = None, -np.inf
    for k in range(SIDE_DIRECTIONS):
        angle = 2 * np.pi * k / SIDE_DIRECTIONS
        direction = np.array([np.cos(angle), np.sin(angle)])
        if direction @ to_robot < 0:  # the hand cannot come from behind the target
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


@primitive("side_grasp", version=1)(plan_side_grasp)
def execute_side_grasp(env, params: dict, step=None) -> None:
    rotation = side_grasp(np.asarray(params["approach"]))
    standoff = np.asarray(params["standoff"])
    here, _ = grip_site(env)
    # rise, turn the hand horizontal above the stand-off point, then come down beside the target
    servo(env, [standoff[0], standoff[1], max(here[2], standoff[2] + 0.15)], rotation, OPEN, 100, step=step)
    servo(env, standoff, rotation, OPEN, max_steps=150, step=step)
    _grasp_and_lift(env, np.asarray(params["position"]), rotation, step)
