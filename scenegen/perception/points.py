"""What a robot sees of its target in one RGB-D frame with the target's mask (the simulator's
instance mask in the oracle setting, the retrieval head's prediction otherwise).

``masked_points`` back-projects the masked depth pixels into the world frame through the camera's
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
# A depth sensor's frame (render/sensor.py) is read by a robust rule (``robust=True``): a stereo pair's
# depth at a mask's edge mixes the object and what lies behind it, and a mismatched block can put a
# pixel metres along its ray. Exact depth keeps the plain rule, so its plans keep their bytes.
SENSED_POINTS = 2  # the rule's version (1: the plain rule); keys the decisions made through a sensor
SENSOR_ERODE = 1  # px: the mask shrunk by this before back-projection, where MIN_POINTS stay
SENSOR_REACH = 0.2  # m (xy) from the points' median beyond which a sensed point is an error
SENSOR_RANGE = (2.0, 98.0)  # percentiles of the footprint's spread taken as its extent


def masked_points(depth: np.ndarray, mask: np.ndarray, cam: Camera, robust: bool = False) -> np.ndarray:
    """World points (N, 3) of the pixels of ``mask`` (H, W) bool that have depth (metres along the
    optical axis, top row first; ``cam`` the camera they came from). ``robust`` (a sensor's depth):
    the mask eroded by ``SENSOR_ERODE`` px first, where enough pixels remain."""
    depth, mask = np.squeeze(depth), np.squeeze(mask)
    if robust and SENSOR_ERODE > 0:
        import cv2

        size = 2 * SENSOR_ERODE + 1
        inner = cv2.erode(mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
        if np.count_nonzero(inner & (depth > 0)) >= MIN_POINTS:
            mask = inner
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


def inliers(points: np.ndarray) -> np.ndarray:
    """The points within ``SENSOR_REACH`` (xy) of their median: a sensed target's, its errors gone."""
    if len(points) == 0:
        return points
    near = np.linalg.norm(points[:, :2] - np.median(points[:, :2], axis=0), axis=1) <= SENSOR_REACH
    return points[near]


def estimate_target(points: np.ndarray, robust: bool = False) -> TargetEstimate | None:
    """A summary of the target's visible points; None when too few are seen (``MIN_POINTS``).
    ``robust`` (a sensor's depth): points beyond ``SENSOR_REACH`` of the median dropped, the
    footprint's extents and middle from the ``SENSOR_RANGE`` percentiles, not the extremes."""
    if robust:
        points = inliers(points)
    if len(points) < MIN_POINTS:
        return None
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    eigenvalues, eigenvectors = np.linalg.eigh(np.cov(xy.T))
    major = eigenvectors[:, np.argmax(eigenvalues)]
    minor = np.array([-major[1], major[0]])
    along, across = xy @ major, xy @ minor
    low, high = np.percentile(points[:, 2], [2, 98])
    centroid = points.mean(axis=0)
    if robust:
        span = lambda v: float(np.subtract(*np.percentile(v, SENSOR_RANGE[::-1])))  # noqa: E731
        lo, hi = np.percentile(points[:, :2], SENSOR_RANGE, axis=0)
        middle, extent = 0.5 * (lo + hi), (span(along), span(across))
    else:
        middle = 0.5 * (points[:, :2].min(axis=0) + points[:, :2].max(axis=0))
        extent = (float(np.ptp(along)), float(np.ptp(across)))
    return TargetEstimate(
        centroid=centroid,
        centre=np.array([middle[0], middle[1], centroid[2]]),
        top_z=float(high),
        bottom_z=float(low),
        yaw=float(np.arctan2(major[1], major[0])),
        extent=extent,
        points=len(points),
    )
