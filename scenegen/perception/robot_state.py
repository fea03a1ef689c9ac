"""The robot's own state as it senses it (proprioception): the grip site's pose and the fingers'
opening, read from the robot's joints and sites, never from the objects."""

from __future__ import annotations

import numpy as np


def grip_site(env) -> tuple[np.ndarray, np.ndarray]:
    """The grip site's position (3,) and rotation (3, 3), from the robot's own state."""
    robot = env.robots[0]
    data = env.sim.data._data
    site = robot.eef_site_id["right"]
    return data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3).copy()


def finger_gap(env) -> float:
    """How far apart the fingers are (m, 0 when closed on nothing), from the finger joints
    (proprioception): a hand commanded closed that stays apart holds something."""
    robot = env.robots[0]
    qpos = env.sim.data._data.qpos[robot._ref_gripper_joint_pos_indexes["right"]]
    return float(np.abs(qpos).sum())
