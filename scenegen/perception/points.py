"""What a robot sees of its target in one RGB-D frame with the target's mask (the simulator's
instance mask in the oracle setting, the retrieval head's prediction otherwise).

``target_points`` back-projects the masked depth pixels into the world frame through the camera's
intrinsics and pose (depth is along the optical axis, in metres; images top row first, as the
environment returns them); ``estimate_target`` summarises the points as a grasp planner needs them:
centroid, top and bottom heights, and the footprint's principal axis (yaw) and extents. Everything
here is computed from the observation, never from the simulator's state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen.core.rotations import camera_rotation
from scenegen.schema.scene import Camera

MIN_POINTS = 20  # fewer masked pixels than this: the target is not seen


def target_points(depth: np.ndarray, seg: np.ndarray, target_id: int, cam: Camera) -> np.ndarray:
    """World points (N, 3) of the pixels whose instance id is ``target_id`` and that have depth.

    ``depth`` (H, W) metres, ``seg`` (H, W) instance ids, both top row first; ``cam`` the camera
    they came from, its ``width`` and ``height`` those of the frame."""
    return masked_points(depth, np.squeeze(seg) == target_id, cam)


def masked_points(depth: np.ndarray, mask: np.ndarray, cam: Camera) -> np.ndarray:
    """World points (N, 3) of the pixels of ``mask`` (H, W) bool that have depth (see
    :func:`target_points`)."""
    depth, mask = np.squeeze(depth), np.squeeze(mask)
    height, width = depth.shape
    if (cam.width, cam.height) != (width, height):
        cam = cam.model_copy(update={"width": width, "height": height})
    k = cam.intrinsics()
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(float)
    # pixel centres; image rows grow downwards, the camera's y axis points up
    x_cam = (u + 0.5 - k["cx"]) * z / k["fx"]
    y_cam = -(v + 0.5 - k["cy"]) * z / k["fy"]
    points = np.stack([x_cam, y_cam, -z], axis=1)
    return points @ camera_rotation(cam.position, cam.lookat).T + np.asarray(cam.position, float)


@dataclass(frozen=True)
class TargetEstimate:
    """The target as seen: ``centroid`` (3,) of the visible points; ``centre`` (3,): the middle of
    their x and y ranges, at the centroid's height (the visible points lean towards the cameras, but
    from above both sides of the top show: the ranges' middle is the footprint's centre); top and
    bottom z, footprint yaw (radians, the major axis of the points' xy spread) and extents (major,
    minor) in metres."""

    centroid: np.ndarray
    centre: np.ndarray
    top_z: float
    bottom_z: float
    yaw: float
    extent: tuple[float, float]
    points: int

    @property
    def height(self) -> float:
        return self.top_z - self.bottom_z


def estimate_target(points: np.ndarray) -> TargetEstimate | None:
    """A summary of the target's visible points; None when too few are seen (``MIN_POINTS``)."""
    if len(points) < MIN_POINTS:
        return None
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    eigenvalues, eigenvectors = np.linalg.eigh(np.cov(xy.T))
    major = eigenvectors[:, np.argmax(eigenvalues)]
    minor = np.array([-major[1], major[0]])
    along, across = xy @ major, xy @ minor
    low, high = np.percentile(points[:, 2], [2, 98])
    centroid = points.mean(axis=0)
    middle = 0.5 * (points[:, :2].min(axis=0) + points[:, :2].max(axis=0))
    return TargetEstimate(
        centroid=centroid,
        centre=np.array([middle[0], middle[1], centroid[2]]),
        top_z=float(high),
        bottom_z=float(low),
        yaw=float(np.arctan2(major[1], major[0])),
        extent=(float(np.ptp(along)), float(np.ptp(across))),
        points=len(points),
    )
