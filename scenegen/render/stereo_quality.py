"""The active stereo sensor measured as a real one is (issue 62; docs/sensor.md "Measured").

Scenes built for a measurement and the figures Intel's Depth Quality Tool reports, against what the
sensor's arrangement predicts:

- :func:`bare_table`: the table alone, seen straight down from ``height`` m; :func:`plane_rms`:
  the RMS of the depth about a plane fitted to the table-top pixels of the frame's central 40 %
  (Intel's region of interest), against ``z^2 s / (f B)`` (:func:`predicted_rms`); :func:`fill_rate`:
  the share of the table top, inside the sensor's measurable field, that has depth;
- :func:`box_edge`: an upright box seen straight down; :func:`edge_bands`: the widths of the
  pixel runs without depth beside its left and right edges, against :func:`predicted_bands`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenegen.render.stereo import ActiveStereo, Pinhole

SUBPIXEL_RMS = 0.08  # px: a D415's typical subpixel RMS error on a textured target (Intel's tuning
# guide, "Tuning depth cameras for best performance", Grunnet-Jepsen, Sweetser, Woodfill)
ROI = 0.4  # the central share of the frame's width and height a plane is fitted in (the DQT's default)
CAMERA = "down"
SIZE = (640, 480)
FOVY = 45.0  # the scene cameras' field of view


@dataclass
class Frame:
    """One measured frame: ``exact`` and ``sensed`` depth (H, W) m, ``seg`` (H, W) instance ids,
    ``ids`` the scene's instance ids, ``colour`` the colour camera's intrinsics."""

    exact: np.ndarray
    sensed: np.ndarray
    seg: np.ndarray
    ids: dict
    colour: Pinhole


def _measure(renderer, objects, height: float, sensor: ActiveStereo, point: str) -> Frame:
    import mujoco

    from scenegen.assets.catalog import active_catalog
    from scenegen.render.offscreen import segmentation_ids
    from scenegen.schema.scene import Camera
    from scenegen.sim import world

    top = world.TABLE_TOP_Z
    # straight down onto the table's middle (a hair off vertical: the look-at rotation needs a
    # horizontal direction)
    cam = Camera(name=CAMERA, position=(0.1, 0.0, top + height), lookat=(0.1001, 0.0, top), fovy=FOVY)
    model = world.build_world(active_catalog(), objects, (), None, [cam]).compile()
    data = mujoco.MjData(model)
    for obj in objects:
        adr = model.joint(f"{obj.name}_joint").qposadr[0]
        data.qpos[adr : adr + 3] = obj.position
        data.qpos[adr + 3 : adr + 7] = obj.quat
    mujoco.mj_forward(model, data)
    ids = segmentation_ids(None, [o.name for o in objects], [])
    (frame,) = renderer.render(model, data, [CAMERA], ids, [SIZE])
    sensed = sensor.sense(renderer, model, data, CAMERA, SIZE, ids, point, rgb=frame.rgb)
    return Frame(frame.depth, sensed, frame.seg, ids, Pinhole.of(FOVY, *SIZE))


def bare_table(renderer, height: float, sensor: ActiveStereo | None = None, point: str = "bare") -> Frame:
    """The bare table seen straight down from ``height`` m above its top."""
    return _measure(renderer, (), height, sensor or ActiveStereo(), point)


def box_edge(renderer, height: float = 0.8, sensor: ActiveStereo | None = None, point: str = "edge") -> Frame:
    """An upright cereal box (20 cm tall, its long side across the image) on the table, seen straight
    down from ``height`` m above the table top: two straight vertical edges, each a 20 cm jump."""
    from scenegen.schema.scene import ObjectPlacement
    from scenegen.sim import world

    box = ObjectPlacement(
        name="obj0", asset="cereal_box", category="box", position=(0.1, 0.0, world.TABLE_TOP_Z + 0.1),
        quat=(1.0, 0.0, 0.0, 0.0),
    )  # fmt: skip
    return _measure(renderer, (box,), height, sensor or ActiveStereo(), point)


def predicted_rms(z: float, sensor: ActiveStereo, height_px: int = SIZE[1], s: float = SUBPIXEL_RMS) -> float:
    """``z^2 s / (f B)`` metres: the depth RMS a disparity error of ``s`` px makes at range ``z`` (``f``
    the imagers' focal length for a colour frame ``height_px`` rows tall)."""
    return z * z * s / (sensor.focal(sensor.imager_size(height_px)[1]) * sensor.baseline)


def _roi(shape) -> np.ndarray:
    h, w = shape
    mask = np.zeros(shape, bool)
    dh, dw = round(h * (1 - ROI) / 2), round(w * (1 - ROI) / 2)
    mask[dh : h - dh, dw : w - dw] = True
    return mask


def plane_rms(frame: Frame) -> float:
    """RMS (m) of the sensed depth about the least-squares plane through the sensed table-top points
    of the central region (float depth, before any millimetre file)."""
    table = _roi(frame.seg.shape) & (frame.seg == frame.ids["table"]) & (frame.sensed > 0)
    points = frame.colour.points(frame.sensed)[table].astype(np.float64)
    design = np.c_[points[:, 0], points[:, 1], np.ones(len(points))]
    coef, *_ = np.linalg.lstsq(design, points[:, 2], rcond=None)
    return float(np.sqrt(np.mean((points[:, 2] - design @ coef) ** 2)))


def measurable(frame: Frame, sensor: ActiveStereo) -> np.ndarray:
    """(H, W) bool: the colour pixels whose surface (exact depth) falls inside both imagers' frames,
    right of the left image's first ``disparities`` columns, which no match can reach."""
    z = frame.exact.astype(np.float32)
    a, b = frame.colour.rays()
    ir_w, ir_h = sensor.imager_size(frame.seg.shape[0])
    imager = Pinhole.of(sensor.fovy, ir_w, ir_h)
    ok = z > 0
    for at in (sensor.colour_offset, sensor.colour_offset - sensor.baseline):  # colour -> left, right
        u, v = imager.pixel(a * z + np.float32(at), b * z, z)
        lo = sensor.disparities(ir_h) if at == sensor.colour_offset else 0
        ok &= (u >= lo) & (u <= ir_w - 1) & (v >= 0) & (v <= ir_h - 1)
    return ok


def fill_rate(frame: Frame, sensor: ActiveStereo) -> float:
    """The share of the table-top pixels in the sensor's measurable field that have depth."""
    table = (frame.seg == frame.ids["table"]) & measurable(frame, sensor)
    return float((frame.sensed[table] > 0).mean())


def predicted_bands(frame: Frame, sensor: ActiveStereo) -> tuple[float, float]:
    """(left, right) widths in colour pixels of the depth-less runs beside an object's vertical
    edges (docs/sensor.md derives them): left, the background the right imager (and, nearer, the
    projector) cannot see, ``f_c (B - o) (1/z_near - 1/z_far)``; right, the background the colour
    camera sees but the left imager (``o`` to its left) does not, ``f_c o (1/z_near - 1/z_far)``."""
    near, far = _ranges(frame)
    jump = 1 / near - 1 / far
    f = frame.colour.f
    return f * (sensor.baseline - sensor.colour_offset) * jump, f * sensor.colour_offset * jump


def _ranges(frame: Frame) -> tuple[float, float]:
    obj = frame.seg == frame.ids["obj0"]
    return float(np.median(frame.exact[obj])), float(np.median(frame.exact[frame.seg == frame.ids["table"]]))


def edge_bands(frame: Frame, sensor: ActiveStereo) -> tuple[float, float]:
    """(left, right) median widths (colour pixels) over the rows through the box's middle of the
    depth-less pixels within twice the predicted width (plus 4 px) beside its left and right edges."""
    obj = frame.seg == frame.ids["obj0"]
    rows = np.nonzero(obj.sum(1) > 10)[0]
    rows = rows[len(rows) // 5 : -len(rows) // 5]  # away from the corners
    reach = [int(2 * p + 4) for p in predicted_bands(frame, sensor)]
    left, right = [], []
    for y in rows:
        xs = np.nonzero(obj[y])[0]
        x0, x1 = xs.min(), xs.max()
        left.append(int((frame.sensed[y, max(0, x0 - reach[0]) : x0] == 0).sum()))
        right.append(int((frame.sensed[y, x1 + 1 : x1 + 1 + reach[1]] == 0).sum()))
    return float(np.median(left)), float(np.median(right))
