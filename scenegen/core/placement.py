"""Snapping a raw pose onto a stable resting pose of its asset on a support surface: what every
proposer and the generator's decoding do to what they sample, recording how far it moved.

Pure: numpy, the schema, the catalog and the layout. wxyz quaternions (MuJoCo's order), metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from scenegen.assets.catalog import Asset
from scenegen.core.layout import Surface
from scenegen.schema.scene import ObjectPlacement


def yaw_quat(yaw: float) -> np.ndarray:
    """The wxyz quaternion of a rotation by ``yaw`` radians about world z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def snap_to_rest(
    asset: Asset, position: Sequence[float], quat: Sequence[float], surface: Surface, scale: float = 1.0
) -> tuple[tuple[float, ...], tuple[float, ...], int, float]:
    """Project a raw pose onto the nearest stable resting pose of ``asset`` on ``surface``.

    The nearest pose is the resting pose whose yaw-aligned rotation is closest (geodesic angle) to
    ``quat``; the height becomes the surface height plus the pose's centre-of-mass height.
    Returns (position, wxyz quat, resting-pose index, projection distance in metres).
    """
    q = np.asarray(quat, float) / np.linalg.norm(quat)
    best = (math.inf, 0, q)
    for i, pose in enumerate(asset.resting_poses):
        rest = np.asarray(pose.quat)
        # yaw that best aligns rest with q: the z rotation of q * rest^-1
        rel = quat_mul(q, rest * np.array([1, -1, -1, -1]))
        yaw = 2 * math.atan2(rel[3], rel[0])
        candidate = quat_mul(yaw_quat(yaw), rest)
        angle = 2 * math.acos(min(1.0, abs(float(np.dot(candidate, q)))))
        if angle < best[0] - 1e-9:
            best = (angle, i, candidate)
    _, index, snapped = best
    snapped = snapped if snapped[0] >= 0 else -snapped
    new_pos = (position[0], position[1], surface.z + asset.resting_poses[index].height * scale)
    distance = float(np.linalg.norm(np.subtract(new_pos, position)))
    return (
        tuple(round(float(v), 7) for v in new_pos),
        tuple(round(float(v), 7) for v in snapped),
        index,
        round(distance, 7),
    )


def placed_at_rest(
    name: str, asset: Asset, position: Sequence[float], quat: Sequence[float], surface: Surface, support: str
) -> ObjectPlacement:
    """An object of ``asset`` snapped (:func:`snap_to_rest`) from a raw pose onto ``surface``, resting on
    ``support``, with the projection distance recorded."""
    position, quat, pose, distance = snap_to_rest(asset, position, quat, surface)
    return ObjectPlacement(
        name=name,
        asset=asset.name,
        category=asset.category,
        position=position,
        quat=quat,
        support=support,
        resting_pose=pose,
        projection_distance=distance,
    )
