"""Rotations as numbers: wxyz quaternions (MuJoCo's order) and yaw angles to 3x3 matrices."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def quat_to_matrix(quat: Sequence[float]) -> np.ndarray:
    """Rotation matrix (3, 3) of a wxyz quaternion."""
    w, x, y, z = np.asarray(quat, float) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation matrix (3, 3) about world z by ``yaw`` radians."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_rotation(position: Sequence[float], lookat: Sequence[float]) -> np.ndarray:
    """Camera-to-world rotation (3, 3) of a camera at ``position`` looking at ``lookat``, in the
    MuJoCo/OpenGL convention: x right, y up, looking along -z (the image's up is world +z)."""
    forward = np.asarray(lookat, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward], axis=1)
