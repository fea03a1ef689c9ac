"""End-effector motions through the environment's controller (robosuite's OSC_POSE, delta actions).

A motion is a goal pose of the grip site (position in metres, rotation matrix) and a gripper command;
:func:`servo` steps the environment until the site is there (or a step budget runs out), the way a
real robot's motion executor would, reading only the robot's own state (proprioception). Nothing here
moves an object or the robot other than through actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen.perception.robot_state import grip_site

OPEN, CLOSE = -1.0, 1.0  # robosuite gripper action
POS_STEP = 0.05  # m per unit action (OSC_POSE output_max, BASIC config)
ROT_STEP = 0.5  # rad per unit action


def down_grasp(closing: np.ndarray) -> np.ndarray:
    """Rotation of a grip site pointing straight down whose fingers close along ``closing`` (x, y)."""
    x = np.array([closing[0], closing[1], 0.0])
    x /= np.linalg.norm(x)
    z = np.array([0.0, 0.0, -1.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def side_grasp(approach: np.ndarray) -> np.ndarray:
    """Rotation of a grip site pointing horizontally along ``approach`` (x, y), fingers closing
    horizontally (across the approach)."""
    z = np.array([approach[0], approach[1], 0.0])
    z /= np.linalg.norm(z)
    # The site's y axis down, not up: with it up the Panda's wrist (joint 6) ran into its limit
    # before the hand came down to the table (measured).
    x = np.cross(z, [0.0, 0.0, 1.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def _rotation_error(current: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Axis-angle (3,) that takes ``current`` to ``goal`` in the world frame."""
    r = goal @ current.T
    angle = np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    norm = np.linalg.norm(axis)
    if norm < 1e-9:  # a half turn: any axis orthogonal to the rotation's plane
        axis = np.linalg.eigh(r + np.eye(3))[1][:, -1]
        return axis * angle
    return axis / norm * angle


@dataclass
class MotionResult:
    reached: bool
    steps: int
    position_error: float  # m
    rotation_error: float  # rad


def servo(
    env,
    position,
    rotation: np.ndarray | None = None,
    gripper: float = OPEN,
    max_steps: int = 60,
    tolerance: float = 0.005,
    speed: float = 1.0,
    step=None,
) -> MotionResult:
    """Move the grip site to ``position`` (and ``rotation``, if given) with the gripper commanded to
    ``gripper``, at most ``max_steps`` control steps; ``speed`` (0-1] caps the per-step action.
    ``step``: the function that takes an action (default ``env.step``; an EpisodeRecorder's step
    records it)."""
    step = step or env.step
    position = np.asarray(position, float)
    for n in range(1, max_steps + 1):
        here, rot = grip_site(env)
        dp = position - here
        dr = _rotation_error(rot, rotation) if rotation is not None else np.zeros(3)
        if np.linalg.norm(dp) < tolerance and np.linalg.norm(dr) < 0.05:
            return MotionResult(True, n - 1, float(np.linalg.norm(dp)), float(np.linalg.norm(dr)))
        action = np.zeros(7)
        action[:3] = np.clip(dp / POS_STEP, -speed, speed)
        action[3:6] = np.clip(dr / ROT_STEP, -speed, speed)
        action[6] = gripper
        step(action)
    here, rot = grip_site(env)
    dr = _rotation_error(rot, rotation) if rotation is not None else np.zeros(3)
    return MotionResult(False, max_steps, float(np.linalg.norm(position - here)), float(np.linalg.norm(dr)))


def hold(env, gripper: float, steps: int, step=None) -> None:
    """Keep the grip site where it is for ``steps`` control steps, commanding the gripper."""
    step = step or env.step
    for _ in range(steps):
        step(np.array([0, 0, 0, 0, 0, 0, gripper], dtype=float))
