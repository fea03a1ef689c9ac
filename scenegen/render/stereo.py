"""An active stereo depth camera simulated from how it works (issue 62; docs/sensor.md).

An Intel RealSense D4xx measures depth by matching two infrared images: a projector between two IR
imagers throws a fixed pattern of dots onto the scene, each imager sees the dots (and ambient light)
on the surfaces in front of it, and a semi-global matcher finds each left pixel's shift in the right
image, the disparity ``d``; depth is ``f B / d`` (``f`` the imagers' focal length in pixels, ``B``
the baseline). Its errors follow from that, in the places they occur on a real one:

- pixels beside an occluding edge have no depth: the right imager or the projector does not see the
  background there (a band ``f B (1/z_near - 1/z_far)`` pixels wide, docs/sensor.md derives it);
- thin parts (a spoon's handle) are narrower than the matching window and fail its checks;
- the depth error grows with the square of range (``z^2 s / (f B)`` for a disparity error ``s``),
  and dark, far or grazing surfaces return fewer dots, hence more noise and more holes.

:class:`ActiveStereo` simulates it with MuJoCo's renderer on the CPU. For a scene camera (the colour
camera), three extra views are rendered from poses placed beside it (:class:`~scenegen.render.
offscreen.View`: the model and a stored scene.xml are not touched): the left and right imagers and
the projector, all looking the way the colour camera looks. Each imager's IR image is the projector's
seeded dot pattern reprojected onto the surfaces that imager sees (dark where the projector's own
depth says the surface is hidden from it), attenuated with range and incidence, plus the colour
render's luminance as ambient light and sensor noise; the pair is matched with OpenCV's StereoSGBM
(its left-right check and speckle filter on), disparity is turned into depth in the left imager and
registered to the colour camera. The noise is drawn from a seed made of the decision point (or
scene) and the camera, so the same frame comes out in any process; OpenCV runs on one thread while
matching, so the bytes do not follow the thread count.

Geometry (defaults: a D415's): along the colour camera's x axis (right), the left imager sits
``colour_offset`` to the left of the colour camera, the projector ``projector_offset`` and the right
imager ``baseline`` to the right of the left imager.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from dataclasses import dataclass

import numpy as np

SEEDING = 1  # the version of how a frame's noise is drawn from (point, camera)
DISPARITY_SCALE = 16  # StereoSGBM returns disparities in 1/16 px


@dataclass(frozen=True)
class ActiveStereo:
    """The sensor's settings. Lengths in metres, angles in degrees, intensities in the IR image's
    digital numbers (0-255)."""

    baseline: float = 0.055  # D415 (D435: 0.050)
    colour_offset: float = 0.015  # the colour camera's place right of the left imager (depth-to-colour)
    projector_offset: float = 0.0275  # the projector's place right of the left imager (between them)
    fovy: float = 40.0  # the imagers' vertical field of view: D415 depth 65 x 40 deg (H x V)
    aspect: float = 848 / 480  # the imagers' width / height (D4xx modes 1280x720, 848x480, 424x240)
    # the imagers' rows whatever the colour frame's size (848 x 480, a D4xx mode: a smaller colour
    # frame keeps the sensor's precision, as a real camera's depth is decimated after matching, not
    # matched small); 0: the colour frame's rows
    imager_rows: int = 480
    projector_fovy: float = 46.0  # wider than the imagers, so their views are lit to the edge
    # The projected pattern: dots per projector pixel, their blur (px) and the pattern's seed (fixed:
    # one projector, one pattern).
    dot_density: float = 0.09
    dot_sigma: float = 0.7
    pattern_seed: int = 415
    dot_peak: float = 150.0  # a dot's brightness on a white surface facing the projector at 1 m
    ambient: float = 0.05  # the colour render's luminance (0-255) times this is the IR ambient
    exposure_target: float = 160.0  # DN: auto-exposure puts the 99th percentile of the image here...
    max_gain: float = 8.0  # ... with at most this gain (and at least 1 / this)
    albedo: float = 0.8  # the surfaces' IR reflectance (IR shows little of visible colour)
    read_noise: float = 2.0  # DN, Gaussian
    shot_noise: float = 0.35  # DN per sqrt(DN): the photon noise of a signal of I DN is k sqrt(I)
    shadow_tolerance: float = 0.004  # m (+ 1 % of range): a point this far behind the projector's
    # depth is hidden from it
    # The matcher (OpenCV StereoSGBM, 3-way): window, smoothness P1/P2 = p1, p2 x window^2, the checks.
    block: int = 7
    p1: int = 8
    p2: int = 32
    uniqueness: int = 10
    left_right: int = 1  # px: the left-right check (disp12MaxDiff)
    speckle_window: int = 100  # px: disparity regions smaller than this are removed (at 480 rows)
    speckle_range: int = 2  # px: ... where the disparity varies by less than this inside them
    min_range: float = 0.5  # m: the nearest depth matched (sets the disparity search range)
    refinements: int = 2  # Lucas-Kanade steps after the matcher (its own subpixel fit locks to pixels)

    def key(self) -> str:
        """What decides the frames (the settings and the seeding's version): part of an
        observation's key, so a changed sensor never serves frames the old one made."""
        return f"active_stereo{SEEDING}:{dataclasses.astuple(self)}"

    def imager_size(self, height: int) -> tuple[int, int]:
        """(width, height) of the IR images for a colour frame ``height`` rows tall: ``imager_rows``
        (or the colour frame's) rows at the imagers' own aspect (848 x 480 by default)."""
        rows = self.imager_rows or height
        return round(rows * self.aspect), rows

    def focal(self, height: int) -> float:
        """The imagers' focal length in pixels at ``height`` rows."""
        return 0.5 * height / np.tan(np.radians(self.fovy) / 2)

    def disparities(self, height: int) -> int:
        """StereoSGBM's search range: a multiple of 16 covering depths down to ``min_range``."""
        d = self.focal(height) * self.baseline / self.min_range
        return int(np.ceil(d / 16.0)) * 16

    def measure(self, sight, point: str) -> np.ndarray:
        """The depth of ``sight``'s frame (a ``render.sensor.Sight``) at ``point``: :meth:`sense`."""
        return self.sense(sight.renderer, sight.model, sight.data, sight.camera, sight.size, sight.ids,
                          point, rgb=sight.rgb)  # fmt: skip

    def sense(self, renderer, model, data, camera: str, size: tuple[int, int], ids: dict, point: str,
              rgb: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """Depth (H, W) float32 metres along the colour camera's optical axis, 0 = no return, as the
        sensor beside ``camera`` (a camera of ``model``) measures it now, registered to that camera at
        ``size`` (width, height). ``renderer``: a :class:`~scenegen.render.offscreen.SceneRenderer`;
        ``data`` forwarded; ``ids`` the scene's instance ids; ``point`` names the scene and decision
        (it seeds the noise with ``camera``); ``rgb`` (H, W, 3) the colour frame if already drawn (its
        luminance is the ambient light; without it an unlit colour pass is drawn)."""
        from scenegen.render.offscreen import View

        cid = model.camera(camera).id
        pos, xmat = data.cam_xpos[cid].copy(), data.cam_xmat[cid].reshape(3, 3).copy()
        colour = Pinhole.of(float(model.cam_fovy[cid]), *size)
        ir_w, ir_h = self.imager_size(size[1])
        imager = Pinhole.of(self.fovy, ir_w, ir_h)
        projector = Pinhole.of(self.projector_fovy, ir_w, ir_h)
        x = xmat[:, 0]
        at = {  # x offsets in the colour camera's frame
            "left": -self.colour_offset,
            "right": self.baseline - self.colour_offset,
            "projector": self.projector_offset - self.colour_offset,
        }
        views = [View(pos + at[n] * x, xmat, self.fovy) for n in ("left", "right")]
        views.append(View(pos + at["projector"] * x, xmat, self.projector_fovy))
        frames = renderer.render(model, data, views, ids, [(ir_w, ir_h)] * 3, rgb=False)
        if rgb is None:
            (drawn,) = renderer.render(model, data, [camera], ids, [size], lit=False)
            rgb = drawn.rgb
        luminance = _luminance(rgb)
        rng = np.random.default_rng(_seed(point, camera))
        pattern = dot_pattern(self.dot_density, self.dot_sigma, self.pattern_seed, ir_w, ir_h)
        ir = [
            self.infrared(
                frames[i].depth,
                at[name] - at["projector"],
                imager,
                frames[2].depth,
                projector,
                pattern,
                luminance,
                at[name],
                colour,
                rng,
            )  # fmt: skip
            for i, name in enumerate(("left", "right"))
        ]
        disparity = self.match(*ir)
        depth_left = np.where(disparity > 0, imager.f * self.baseline / np.maximum(disparity, 1e-6), 0.0)
        return register(depth_left, imager, -at["left"], colour)

    def infrared(self, depth, to_projector, imager, projector_depth, projector, pattern, luminance,
                 to_colour, colour, rng) -> np.ndarray:  # fmt: skip
        """One imager's IR image (H, W) uint8 from its exact ``depth`` (H, W) m. ``to_projector``:
        the imager's x offset from the projector (m, the camera frame); ``to_colour``: its offset
        from the colour camera, whose ``luminance`` (0-255) is the ambient light."""
        import cv2

        z = depth.astype(np.float32)
        seen = z > 0
        a, b = imager.rays()
        x, y = a * z, b * z  # the points, OpenCV frame: x right, y down, z forward
        # the dots: where the projector sees the point, its pattern there, at the projector's range
        # and the surface's incidence
        px = x + np.float32(to_projector)
        u, v = projector.pixel(px, y, z)
        ui, vi = u.astype(np.int32), v.astype(np.int32)  # truncation = floor where it matters (>= 0)
        inside = seen & (u >= 0) & (v >= 0) & (ui < projector.width) & (vi < projector.height)
        blocker = projector_depth[np.where(inside, vi, 0), np.where(inside, ui, 0)]
        visible = inside & (blocker > 0) & (z <= blocker * 1.01 + self.shadow_tolerance)
        dots = cv2.remap(pattern, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        distance2 = px * px + y * y + z * z
        incidence = np.abs(surface_cosine(z, a, b, imager.f, px, y))
        gain = np.float32(self.dot_peak * self.albedo)
        signal = np.where(visible, gain * dots * incidence / np.maximum(distance2, 1e-6), 0.0)
        # ambient: the colour camera's luminance where this imager's point appears in it
        cu, cv_ = colour.pixel(x + np.float32(to_colour), y, z)
        ambient = cv2.remap(luminance, cu, cv_, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        clean = signal + np.float32(self.ambient) * np.where(seen, ambient, 0.0)
        level = float(np.percentile(clean, 99)) if clean.any() else 0.0
        exposure = np.clip(self.exposure_target / max(level, 1e-6), 1 / self.max_gain, self.max_gain)
        clean *= np.float32(exposure)
        sigma = np.sqrt(np.float32(self.read_noise**2) + np.float32(self.shot_noise**2) * clean)
        noise = rng.standard_normal(z.shape, dtype=np.float32) * sigma
        return np.clip(np.rint(clean + noise), 0, 255).astype(np.uint8)

    def match(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Disparity (H, W) float px of the left image (0 = no match): 3-way semi-global matching
        with the left-right check and the speckle filter, on one thread (the bytes do not follow
        OpenCV's thread count)."""
        import cv2

        height = left.shape[0]
        matcher = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=self.disparities(height),
            blockSize=self.block,
            P1=self.p1 * self.block**2,
            P2=self.p2 * self.block**2,
            disp12MaxDiff=self.left_right,
            uniquenessRatio=self.uniqueness,
            speckleWindowSize=round(self.speckle_window * (height / 480) ** 2),
            speckleRange=self.speckle_range * DISPARITY_SCALE,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            raw = matcher.compute(left, right)
        finally:
            cv2.setNumThreads(threads)
        disparity = np.where(raw > 0, raw.astype(np.float32) / DISPARITY_SCALE, np.float32(0.0))
        for _ in range(self.refinements):
            disparity = refine(left, right, disparity, self.block)
        return disparity


def refine(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window: int) -> np.ndarray:
    """One Lucas-Kanade step on each valid disparity (H, W) float32 px: the shift that best explains
    the left image by the right one over a ``window``-pixel square, to first order. StereoSGBM's own
    subpixel step fits a parabola to 1/16-px costs and pulls disparities towards whole pixels
    (measured: a plane at 22.67 px read as 23.0 in most pixels); this removes that bias, leaving the
    error the images' noise makes."""
    import cv2

    height, width = left.shape
    lf, rf = left.astype(np.float32), right.astype(np.float32)
    gradient = cv2.Sobel(rf, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)  # dR/du, central difference
    u = np.arange(width, dtype=np.float32)[None, :] - disparity
    v = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    shifted = cv2.remap(rf, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    slope = cv2.remap(gradient, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    valid = (disparity > 0).astype(np.float32)
    error = (lf - shifted) * valid
    box = (window, window)
    num = cv2.boxFilter(error * slope, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(slope * slope * valid, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    step = np.where(den > 1e-3, -num / np.maximum(den, 1e-3), 0.0)
    step = np.clip(step, -0.5, 0.5)  # the matcher is right to the pixel; keep the step inside it
    return np.where(disparity > 0, disparity + step, 0.0).astype(np.float32)


@dataclass(frozen=True)
class Pinhole:
    """A camera's intrinsics as MuJoCo renders them: square pixels, the principal point at the
    image centre, pixel (u, v) centred at (u + 0.5, v + 0.5). Points are in the OpenCV frame (x
    right, y down, z forward along the optical axis), in metres."""

    f: float
    width: int
    height: int

    @classmethod
    def of(cls, fovy: float, width: int, height: int) -> Pinhole:
        return cls(0.5 * height / np.tan(np.radians(fovy) / 2), width, height)

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """(x/z, y/z) of every pixel centre, each (H, W) float32."""
        return _rays(self.f, self.width, self.height)

    def pixel(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous pixel coordinates (u, v) float32 (pixel centres at integers) of the points;
        points at z <= 0 land at -1, outside every image."""
        ok = z > 0
        scale = np.float32(self.f) / np.where(ok, z, np.float32(1.0))
        u = np.where(ok, x * scale + np.float32(self.width / 2 - 0.5), np.float32(-1.0))
        v = np.where(ok, y * scale + np.float32(self.height / 2 - 0.5), np.float32(-1.0))
        return u.astype(np.float32), v.astype(np.float32)

    def points(self, depth: np.ndarray) -> np.ndarray:
        """(H, W, 3) points of ``depth`` (H, W) metres along the optical axis."""
        a, b = self.rays()
        z = depth.astype(np.float32)
        return np.stack([a * z, b * z, z], axis=-1)


@functools.lru_cache(maxsize=16)
def _rays(f: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    a = (np.arange(width, dtype=np.float32) + np.float32(0.5 - width / 2)) / np.float32(f)
    b = (np.arange(height, dtype=np.float32) + np.float32(0.5 - height / 2)) / np.float32(f)
    a2, b2 = np.broadcast_to(a[None, :], (height, width)), np.broadcast_to(b[:, None], (height, width))
    return np.ascontiguousarray(a2), np.ascontiguousarray(b2)


SURFACE = 0.02  # m: registration keeps the samples within this of a colour pixel's nearest one


def register(depth: np.ndarray, imager: Pinhole, offset: float, colour: Pinhole) -> np.ndarray:
    """The left imager's ``depth`` (H, W) m seen from the colour camera ``offset`` m to its right
    (both looking the same way): each valid pixel moved to the colour pixel it falls in; where
    several fall in one, the nearest surface wins (samples more than ``SURFACE`` behind the nearest
    are hidden from the colour camera) and, of its samples, the one whose point lands nearest the
    pixel's centre (no bias from taking the least of several noisy depths). Colour pixels none
    reaches (beside an edge the imager saw round, or outside its view) have no depth. The imager's
    pixels are at least as dense as the colour frame's (its field of view is narrower), so a
    surface leaves no gaps."""
    a, b = imager.rays()
    z = depth.astype(np.float32)
    valid = z > 0
    u, v = colour.pixel(a * z - np.float32(offset), b * z, z)
    ui, vi = np.rint(u).astype(np.int32), np.rint(v).astype(np.int32)
    keep = valid & (ui >= 0) & (vi >= 0) & (ui < colour.width) & (vi < colour.height)
    pixel = (vi * colour.width + ui)[keep]
    z, u, v, ui, vi = z[keep], u[keep], v[keep], ui[keep], vi[keep]
    nearest = np.full(colour.height * colour.width, np.inf, np.float32)
    np.minimum.at(nearest, pixel, z)
    front = z <= nearest[pixel] + np.float32(SURFACE)
    pixel, z = pixel[front], z[front]
    off_centre = ((u - ui) ** 2 + (v - vi) ** 2)[front].astype(np.float32)  # compared in float32 below
    closest = np.full_like(nearest, np.inf)
    np.minimum.at(closest, pixel, off_centre)
    chosen = off_centre == closest[pixel]
    out = np.zeros(colour.height * colour.width, np.float32)
    out[pixel[chosen]] = z[chosen]  # ties (equal distances) are left to the last; they agree in place
    return out.reshape(colour.height, colour.width)


def surface_cosine(z, a, b, f, x, y) -> np.ndarray:
    """Cosine (H, W) between the surface seen at each pixel of a depth image (``z`` (H, W) m, pixel
    rays ``a`` = x/z, ``b`` = y/z, focal length ``f`` px) and the direction (``x``, y, z) from a
    light to it. The surface's normal from the depth's central differences: for X = z (a, b, 1),
    dX/du x dX/dv is parallel to (-z_u, -z_v, a z_u + b z_v + z / f)."""
    zu = np.zeros_like(z)
    zv = np.zeros_like(z)
    zu[:, 1:-1] = 0.5 * (z[:, 2:] - z[:, :-2])
    zv[1:-1] = 0.5 * (z[2:] - z[:-2])
    nz = a * zu + b * zv + z / np.float32(f)
    dot = -zu * x - zv * y + nz * z
    norm = np.sqrt((zu * zu + zv * zv + nz * nz) * (x * x + y * y + z * z))
    return dot / np.maximum(norm, np.float32(1e-12))


@functools.lru_cache(maxsize=8)
def dot_pattern(density: float, sigma: float, seed: int, width: int, height: int) -> np.ndarray:
    """The projector's pattern (H, W) float32 in [0, 1]: ``density`` dots per pixel at seeded
    sub-pixel places, each a Gaussian of ``sigma`` px (drawn at 4x and averaged down, so a dot is
    the light that falls in a pixel). Fixed by its arguments: a projector has one pattern."""
    import cv2

    over = 4
    rng = np.random.default_rng(seed)
    n = rng.poisson(density * width * height)
    x = rng.uniform(0, width * over, n).astype(int)
    y = rng.uniform(0, height * over, n).astype(int)
    fine = np.zeros((height * over, width * over), np.float32)
    np.add.at(fine, (y, x), 1.0)
    fine = cv2.GaussianBlur(fine, (0, 0), sigma * over)
    coarse = cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA)
    coarse /= max(float(coarse.max()), 1e-9)
    coarse.setflags(write=False)
    return coarse


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return (rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.float32)


def _seed(point: str, camera: str) -> int:
    return int.from_bytes(hashlib.sha256(f"stereo|{point}|{camera}".encode()).digest()[:8], "little")
