"""Depth sensors: what a camera's depth frame holds when a real sensor, not the renderer, makes it.

Two sensors, by name in :data:`SENSORS`: ``structured_light``, a parametric noise model laid over the
exact depth (below), and ``active_stereo``, a RealSense-like sensor simulated from how it works
(render/stereo.py: an IR dot pattern, two imagers, semi-global matching). Both answer
``measure(sight, point)``: the depth (H, W) metres of one camera's frame (:class:`Sight`: the
renderer, the model and data at that instant, the camera and its exact frames) at the decision point
``point``, whose string (with the camera's name) seeds the sensor's randomness.

The parametric model (issue 45; docs/transfer.md):

The renderer's depth is exact. A structured-light camera's is not: its error grows with range and
it loses pixels where the surface jumps (the projector's pattern is shadowed there).
:class:`StructuredLight` corrupts a rendered depth frame the way such a sensor would: Gaussian noise
of standard deviation ``sigma(z) = sigma0 + k (z - z0)^2`` metres, and a share of the pixels within
``edge_px`` pixels of a depth edge (a jump of more than ``edge_jump`` between neighbours) missing
(depth 0, which every reader of depth already skips). Its randomness is drawn from a seed made of
the decision point and the camera (:meth:`StructuredLight.corrupt`), so the same scene, decision
and camera give the same noisy frame to the head, the planner and the oracle alike, in any process.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from scenegen.render.stereo import ActiveStereo

SEEDING = 1  # the version of how a frame's noise is drawn from (decision point, camera)


@dataclass(frozen=True)
class StructuredLight:
    """The noise model (defaults: issue 45's; a Kinect-class sensor at tabletop range)."""

    sigma0: float = 0.0012  # m at z0
    k: float = 0.0019  # m per m^2 away from z0
    z0: float = 0.4  # m
    edge_missing: float = 0.2  # share of the pixels near an edge that return no depth
    edge_px: int = 2  # "near": within this many pixels of an edge
    edge_jump: float = 0.01  # m between 4-neighbours: an edge

    def key(self) -> str:
        """What decides the noise (the settings and the seeding's version): part of an observation's
        key, so a changed model never serves frames the old one made."""
        return f"structured_light{SEEDING}:{dataclasses.astuple(self)}"

    def sigma(self, z: np.ndarray) -> np.ndarray:
        return self.sigma0 + self.k * (z - self.z0) ** 2

    def edges(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) bool: the pixels within ``edge_px`` of a depth edge of ``depth`` (H, W)."""
        import cv2

        jump = np.zeros(depth.shape, bool)
        rows = np.abs(np.diff(depth, axis=0)) > self.edge_jump
        cols = np.abs(np.diff(depth, axis=1)) > self.edge_jump
        jump[1:] |= rows
        jump[:-1] |= rows
        jump[:, 1:] |= cols
        jump[:, :-1] |= cols
        size = 2 * self.edge_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        return cv2.dilate(jump.astype(np.uint8), kernel).astype(bool)

    def measure(self, sight: Sight, point: str) -> np.ndarray:
        """The depth (H, W) of ``sight``'s frame as this sensor returns it at ``point``."""
        return self.corrupt(sight.depth, point, sight.camera)

    def corrupt(self, depth: np.ndarray, point: str, camera: str) -> np.ndarray:
        """``depth`` (H, W[, 1]) metres as the sensor returns it at the decision point ``point`` (a
        string naming the scene and the decision) from ``camera``; the input is not changed."""
        clean = np.asarray(depth)
        flat = np.squeeze(clean, -1) if clean.ndim == 3 else clean
        rng = np.random.default_rng(_seed(point, camera))
        valid = flat > 0
        noisy = flat + rng.standard_normal(flat.shape).astype(flat.dtype) * self.sigma(flat).astype(
            flat.dtype
        )
        noisy = np.where(valid, np.maximum(noisy, 0.0), 0.0).astype(flat.dtype)
        missing = self.edges(flat) & (rng.random(flat.shape) < self.edge_missing)
        noisy[missing] = 0.0
        return noisy.reshape(clean.shape)


def _seed(point: str, camera: str) -> int:
    return int.from_bytes(hashlib.sha256(f"{point}|{camera}".encode()).digest()[:8], "little")


@dataclass(frozen=True)
class Sight:
    """One camera's frame at an instant, as a sensor may look at it: ``renderer`` (a
    ``render.offscreen.SceneRenderer``), ``model`` and ``data`` (MuJoCo's, forwarded), ``camera`` (a
    camera of the model), ``size`` (width, height), ``ids`` (the scene's instance ids), the exact
    ``depth`` (H, W) metres and the ``rgb`` (H, W, 3) colour frame when it was drawn (else None)."""

    renderer: Any
    model: Any
    data: Any
    camera: str
    size: tuple[int, int]
    ids: dict
    depth: np.ndarray
    rgb: np.ndarray | None = None


SENSORS = {"structured_light": StructuredLight(), "active_stereo": ActiveStereo()}
SENSOR_NAMES = ("exact", *SENSORS)  # what a recipe's or a command's ``sensor`` may say
