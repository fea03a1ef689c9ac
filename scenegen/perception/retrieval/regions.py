"""The regions of a frame that may be objects: the foreground above the table, and the candidate
design's split of it where depth jumps (docs/retrieval.md). Shared by the candidate design
(candidates.py) and the learned separation (separation.py)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from scenegen.perception.points import masked_points

EDGE = 0.04  # m: a jump in depth between neighbouring pixels that separates two regions (measured: 1 cm cut
# the sides of objects seen at a grazing angle into pieces; docs/retrieval.md)
MIN_PIXELS = 20  # a smaller region is no candidate (as the planner's MIN_POINTS)
TABLE_TOP, TABLE_HALF, TABLE_MARGIN = 0.8, (0.4, 0.5), 0.05
ABOVE_TABLE = 0.0015  # m: a fork lies 3 mm high; simulated depth is exact (a real sensor needs more)


def foreground(
    depth: np.ndarray,
    robot_mask: np.ndarray,
    camera,
    above: float = ABOVE_TABLE,
    robot_margin: int = 0,
    table_fit: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The frame's foreground, (H, W) bool: the depth pixels whose world points lie more than
    ``above`` metres above the table within its edges and that are not the robot's own pixels; and
    (H, W) the points' height above the table top in metres. For a sensor's depth (docs/sensor.md):
    ``robot_margin`` px around the robot's pixels are the robot's too (its measured depth spreads past
    its rendered mask), and ``table_fit`` measures heights from a plane fitted to the frame's table
    points (the sensor's depth of the table is tilted and offset a little, not the true top)."""
    height, width = depth.shape
    everything = np.ones_like(depth, bool)
    points = masked_points(np.where(depth > 0, depth, 1.0), everything, camera).reshape(height, width, 3)
    if robot_margin > 0:
        import cv2

        size = 2 * robot_margin + 1
        robot_mask = cv2.dilate(robot_mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    on_table = (
        (depth > 0)
        & ~robot_mask
        & (np.abs(points[..., 0]) <= TABLE_HALF[0] + TABLE_MARGIN)
        & (np.abs(points[..., 1]) <= TABLE_HALF[1] + TABLE_MARGIN)
    )
    top = np.full((height, width), TABLE_TOP)
    if table_fit:
        top = _table_plane(points, on_table)
    lift = points[..., 2] - top
    return on_table & (lift > above), lift


RAYS_MARGIN = 0.3  # m past the table's edges where a pixel's ray may meet its plane (a tall object's top)


def table_rays(camera, shape: tuple[int, int], margin: float = RAYS_MARGIN) -> np.ndarray:
    """(H, W) bool: the pixels whose viewing rays meet the table top's plane within ``margin`` of
    its edges, in front of the camera: where an object on the table can appear, whatever its depth
    reads (a tall object near the far edge rises above the table's own image; the margin keeps it)."""
    height, width = shape
    ones = np.ones(shape, np.float32)
    far = masked_points(ones, ones > 0, camera).reshape(height, width, 3)  # 1 m along the optical axis
    origin = np.asarray(camera.position, float)
    ray = far - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (TABLE_TOP - origin[2]) / ray[..., 2]
    hit = origin[:2] + t[..., None] * ray[..., :2]
    return (
        (t > 0)
        & (np.abs(hit[..., 0]) <= TABLE_HALF[0] + margin)
        & (np.abs(hit[..., 1]) <= TABLE_HALF[1] + margin)
    )


def _table_plane(points: np.ndarray, on_table: np.ndarray, band: float = 0.02) -> np.ndarray:
    """(H, W) the height of the plane fitted (least squares, twice: the second time without the
    points more than 2.5 sigma off the first) to the points within ``band`` m of the table top, at
    every pixel's (x, y); the true top where too few points are near it."""
    near = on_table & (np.abs(points[..., 2] - TABLE_TOP) < band)
    if near.sum() < 100:
        return np.full(points.shape[:2], TABLE_TOP)
    xyz = points[near]
    design = np.c_[xyz[:, 0], xyz[:, 1], np.ones(len(xyz))]
    coef, *_ = np.linalg.lstsq(design, xyz[:, 2], rcond=None)
    residual = xyz[:, 2] - design @ coef
    inliers = np.abs(residual) <= 2.5 * residual.std()
    coef, *_ = np.linalg.lstsq(design[inliers], xyz[inliers, 2], rcond=None)
    return coef[0] * points[..., 0] + coef[1] * points[..., 1] + coef[2]


@dataclass(frozen=True)
class DepthRule:
    """How a frame's depth becomes the region step's foreground: first mended (``fill``: a pixel
    without depth takes its nearest valid neighbour's; ``median``: a median filter of that aperture,
    0 for none), then :func:`foreground`'s options (``above``, ``robot_margin``, ``table_fit``). The
    default is exact depth's rule, and leaves a frame as it is; a head trained through a sensor
    records its rule in its checkpoint (config.json ``depth_rule``) and applies it at decision time
    (docs/sensor.md, "The region step through the sensor")."""

    fill: bool = False
    median: int = 0
    above: float = ABOVE_TABLE
    robot_margin: int = 0
    table_fit: bool = False
    learned: bool = False  # no height threshold: every table pixel is the separator's to call object or table
    table_rays: bool = False  # a learned field also holds the pixels whose rays meet the table (wrong depth)

    def __post_init__(self):
        if self.median not in (0, 3, 5):
            raise ValueError(f"depth_rule median {self.median!r}: 0 (none), 3 or 5")
        if not 0 <= self.above <= 0.05 or not 0 <= self.robot_margin <= 16:
            raise ValueError(
                f"depth_rule above {self.above!r} m, robot_margin {self.robot_margin!r} px: 0-0.05 and 0-16"
            )

    @property
    def mends(self) -> bool:
        return self.fill or self.median > 0

    def mend(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float32 depth with its holes filled and smoothed as the rule says (``depth`` itself
        when it says nothing)."""
        if not self.mends:
            return depth
        out = depth.astype(np.float32)
        if self.fill and (out <= 0).any() and (out > 0).any():
            from scipy.ndimage import distance_transform_edt

            _, (rows, cols) = distance_transform_edt(out <= 0, return_indices=True)
            out = out[rows, cols]
        if self.median:
            import cv2

            out = cv2.medianBlur(out, self.median)
        return out

    def mend_frames(self, frames):
        """``frames`` (``frames.Frames``) with every camera's depth mended."""
        if not self.mends:
            return frames
        return replace(frames, depth=np.stack([self.mend(d) for d in frames.depth]))

    def foreground(self, depth: np.ndarray, robot_mask: np.ndarray, camera):
        """:func:`foreground` of an already mended ``depth`` under this rule; a ``learned`` rule's is
        every pixel on the table (the separator's object map then says which are objects)."""
        above = -np.inf if self.learned else self.above
        keep, lift = foreground(depth, robot_mask, camera, above, self.robot_margin, self.table_fit)
        if self.learned and self.table_rays:  # where the sensed point is off the table, the ray may not be
            keep = keep | (table_rays(camera, depth.shape) & ~robot_mask)
        return keep, lift

    def config(self) -> dict:
        return asdict(self)

    @classmethod
    def from_config(cls, spec, where) -> DepthRule:
        """The rule a checkpoint's config.json states (ValueError naming ``where`` when malformed)."""
        kinds = {f.name: type(f.default) for f in fields(cls)}  # bool, int or float
        if not isinstance(spec, dict) or set(spec) - set(kinds):
            raise ValueError(f"{where}: depth_rule must be an object with keys {', '.join(kinds)}")
        for key, value in spec.items():
            ok = isinstance(value, kinds[key]) or (kinds[key] is float and type(value) is int)
            if not ok or (kinds[key] is int and type(value) is bool):
                raise ValueError(f"{where}: depth_rule {key} {value!r} is not a {kinds[key].__name__}")
        try:
            return cls(**spec)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None


# The rules a head can be trained under (`scenegen retrieval train --depth-rule`): exact depth's, and
# those measured for a sensor's depth on the validation side (docs/sensor.md).
DEPTH_RULES = {
    "exact": DepthRule(),
    "mended_5mm": DepthRule(fill=True, median=5, above=0.005, robot_margin=4, table_fit=True),
    "mended_8mm": DepthRule(fill=True, median=5, above=0.008, robot_margin=4, table_fit=True),
    "learned": DepthRule(fill=True, median=5, table_fit=True, learned=True, table_rays=True),
}
SENSOR_RULE = "learned"  # the rule `retrieval train --sensor` uses unless told (chosen on validation)


def rule_name_for(sensor: str) -> str:
    """The name of the depth rule a head trained through ``sensor`` uses unless told."""
    return "exact" if sensor == "exact" else SENSOR_RULE


def candidate_regions(depth: np.ndarray, robot_mask: np.ndarray, camera, **rule) -> list[np.ndarray]:
    """(H, W) bool masks of the candidate regions of one frame (depth in metres, the robot's own
    pixels, the scene's :class:`~scenegen.schema.scene.Camera`): the foreground (``rule``: its
    options, :func:`foreground`) split where neighbouring depths jump by more than ``EDGE``."""
    import cv2

    keep, _ = foreground(depth, robot_mask, camera, **rule)
    edge = np.zeros_like(keep)
    edge[:, 1:] |= np.abs(np.diff(depth, axis=1)) > EDGE
    edge[1:, :] |= np.abs(np.diff(depth, axis=0)) > EDGE
    count, regions = cv2.connectedComponents((keep & ~edge).astype(np.uint8), connectivity=4)
    sizes = np.bincount(regions.ravel(), minlength=count)
    return [regions == k for k in range(1, count) if sizes[k] >= MIN_PIXELS]


def depth_edge_regions(rgb, depth, robot_mask, camera) -> list[np.ndarray]:
    """The ``candidates`` design's split, with the signature of a region split (``frame_candidates``)."""
    return candidate_regions(depth, robot_mask, camera)


def robot_pixels(frames, scene) -> np.ndarray:
    """(K, H, W) bool: the robot's own pixels in a scene's rendered frames, from their segmentation
    (training and offline scoring; at decision time the environment's self-filter gives them)."""
    return frames.seg == scene.segmentation["robot"]
