"""Off-screen rendering of settled scenes: RGB, depth and instance segmentation per camera.

One GL context per process (MUJOCO_GL=egl renders on the CPU through Mesa), created once and closed
explicitly; each scene gets its own MjrContext and MjvScene, which cost far less than a new
``mujoco.Renderer`` (shared/PITFALLS.md: 0.18 s per renderer, 0.06 + 0.07 s per context).

Outputs, per camera, as PNG bytes:
- ``rgb``: uint8 RGB under the scene's own lights and ambient;
- ``depth``: uint16 millimetres along the optical axis (not along the ray), 0 = no return;
- ``seg``: uint16 instance ids; 0 = background, ids listed in scene.json ``segmentation``.
Collision geoms (groups 0 and 3) and all sites are hidden; what is seen is what is segmented.
"""

from __future__ import annotations

import copy
import os
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from scenegen.sim import world

# Chosen by measurement (shared/PITFALLS.md): a 4096 shadow map made one shadowed 640x480 frame 41 ms,
# 1024 made it 16 ms; at 640x480 the difference in shadow edges is hard to see.
RENDER_SETTINGS = {
    "shadowsize": 1024,
    # The floor's planar reflection re-renders the scene: 0.035 s of 0.19 s per 640x480 frame.
    "reflections": False,
    "visible_geom_groups": [world.VISUAL_GROUP, 2],
    "sites": "hidden",
    "depth": "uint16 millimetres along the optical axis, 0 = no return",
    "segmentation": "uint16 instance id, 0 = background; ids in scene.json segmentation",
    "gl": "MUJOCO_GL",
}
MAX_SIZE = (1280, 960)  # largest camera (width, height) the shared framebuffer holds
ROBOT_BODY_PREFIXES = (*world.ROBOT_PREFIXES, "fixed_mount0_")


class RenderUnavailable(RuntimeError):
    """No usable off-screen GL: the message names MUJOCO_GL and what to do."""


def gl_problem() -> str | None:
    """Why off-screen rendering cannot work here, or None if a GL context can be made."""
    backend = os.environ.get("MUJOCO_GL", "")
    try:
        import mujoco

        with warnings.catch_warnings():  # glfw without a display warns (GLFWError) instead of failing
            warnings.simplefilter("ignore")
            context = mujoco.GLContext(64, 64)
            context.make_current()
            try:  # a context that cannot load GL fails here
                mujoco.MjrContext(
                    mujoco.MjModel.from_xml_string("<mujoco/>"), mujoco.mjtFontScale.mjFONTSCALE_100
                ).free()
            finally:
                context.free()
    except Exception as exc:  # noqa: BLE001 - any failure means the same thing to the user
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        loaded = getattr(getattr(sys.modules.get("mujoco"), "GLContext", None), "__module__", "none")
        return (
            f"off-screen rendering unavailable with MUJOCO_GL={backend or '(unset)'} "
            f"(mujoco's GL backend: {loaded.removeprefix('mujoco.')}): {reason}; "
            "use MUJOCO_GL=egl with Mesa's EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
            "or pass --no-render"
        )
    return None


def segmentation_ids(model, objects: Sequence[str], furniture: Sequence[str]) -> dict[str, int]:
    """Instance ids: arena (floor and walls) 1, table 2, robot 3, then furniture and objects in order."""
    ids = {"arena": 1, "table": 2, "robot": 3}
    for name in [*furniture, *objects]:
        ids[name] = len(ids) + 1
    return ids


def _geom_instance(model, ids: dict[str, int]) -> np.ndarray:
    """Instance id of every geom (0 for geoms that belong to no named instance)."""
    out = np.zeros(model.ngeom, dtype=np.int32)
    for g in range(model.ngeom):
        body = model.body(model.geom_bodyid[g]).name
        if body in ids:
            out[g] = ids[body]
        elif body.startswith(ROBOT_BODY_PREFIXES):
            out[g] = ids["robot"]
        elif model.geom_bodyid[g] == 0:
            out[g] = ids["arena"]
    return out


@dataclass(frozen=True)
class View:
    """A camera that is not in the model: ``pos`` (3,) world metres, ``xmat`` (3, 3) camera-to-world
    rotation (MuJoCo's convention: x right, y up, looking along -z), ``fovy`` vertical field of view
    (degrees). Rendered by overriding the scene's GL camera, so the model (and a stored scene.xml's
    sha256) stays as it is; a simulated sensor's imagers are views (render/stereo.py)."""

    pos: np.ndarray
    xmat: np.ndarray
    fovy: float


@dataclass
class Frames:
    """The images of one camera: rgb (H, W, 3) uint8 (None when not drawn), depth (H, W) float32
    metres (0 = none), seg (H, W)."""

    rgb: np.ndarray | None
    depth: np.ndarray
    seg: np.ndarray


class SceneRenderer:
    """Renders MuJoCo scenes in this process through one shared GL context."""

    def __init__(self):
        import mujoco

        problem = gl_problem()
        if problem:
            raise RenderUnavailable(problem)
        self._mujoco = mujoco
        self._context = mujoco.GLContext(*MAX_SIZE)
        self._context.make_current()
        self._con = None  # colour pass: multisampled (anti-aliased)
        self._seg_con = None  # segmentation and depth pass: one sample per pixel
        self._signature = None

    def close(self) -> None:
        self._free_contexts()
        if self._context is not None:
            self._context.free()
            self._context = None

    def _free_contexts(self) -> None:
        for con in (self._con, self._seg_con):
            if con is not None:
                con.free()
        self._con = self._seg_con = None

    def render(
        self,
        model,
        data,
        cameras: Sequence[str],
        ids: dict[str, int],
        size: Sequence[tuple[int, int]],
        robot_detail: float = 1.0,
        rgb: bool = True,
        lit: bool = True,
    ):
        """Frames for each camera (a name in the model, or a :class:`View`) at its (width, height);
        ``data`` must be forwarded.

        ``robot_detail`` < 1 draws the robot's visual meshes decimated to that share of their
        triangles (render/robot_mesh.py; the model itself is not changed); ``rgb=False`` skips the
        colour pass (multisampled, shadowed: the dearer one) for a caller that reads only depth and
        segmentation, which come from their own pass either way; ``lit=False`` draws the colour
        single-sampled and without shadows (about a tenth of the lit pass's CPU), for a caller that
        needs a luminance estimate rather than an image to look at."""
        mj = self._mujoco
        con, seg_con = self.prepare(model, robot_detail)
        scene = mj.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        scene.flags[mj.mjtRndFlag.mjRND_REFLECTION] = RENDER_SETTINGS["reflections"]
        option = mj.MjvOption()
        option.geomgroup[:] = 0
        for group in RENDER_SETTINGS["visible_geom_groups"]:
            option.geomgroup[group] = 1
        option.sitegroup[:] = 0
        instance = _geom_instance(model, ids)
        return [
            self._camera(model, data, (con, seg_con), scene, option, name, wh, instance, rgb, lit)
            for name, wh in zip(cameras, size, strict=True)
        ]

    def prepare(self, model, robot_detail: float = 1.0):
        """Make this renderer ready for ``model``'s meshes and textures (upload them, decimate the
        robot's at ``robot_detail``), as :meth:`render` does first; a worker calls it at its start."""
        self._context.make_current()
        model.vis.quality.shadowsize = RENDER_SETTINGS["shadowsize"]
        model.vis.global_.offwidth, model.vis.global_.offheight = MAX_SIZE
        return self._context_for(model, robot_detail)

    def _context_for(self, model, robot_detail: float = 1.0):
        """An MjrContext holding the model's meshes and textures, reused while they stay the same.

        Uploading robosuite's meshes and textures costs ~0.2 s per context; scenes built by
        world.build_world share one mesh and texture table, so one upload (and, with
        ``robot_detail`` < 1, one decimation of the robot's meshes) serves a whole batch.
        """
        signature = (
            model.mesh_vertnum.tobytes(),
            model.mesh_facenum.tobytes(),
            model.tex_width.tobytes(),
            model.tex_height.tobytes(),
            model.hfield_nrow.tobytes(),
            model.nskin,
            robot_detail,
        )
        if self._con is None or signature != self._signature:
            self._free_contexts()
            source = model
            if robot_detail < 1.0:
                from scenegen.render.robot_mesh import decimated_copy

                source = decimated_copy(model, ROBOT_BODY_PREFIXES, robot_detail)
            self._con = self._new_context(source)
            # The segmentation pass draws no edge blends, so a multisampled buffer only costs its
            # resolve: a second context without one (measured: ~10 ms less per camera on llvmpipe).
            single = copy.copy(source)
            single.vis.quality.offsamples = 0
            self._seg_con = self._new_context(single)
            self._signature = signature
        return self._con, self._seg_con

    def _new_context(self, model):
        mj = self._mujoco
        con = mj.MjrContext(model, mj.mjtFontScale.mjFONTSCALE_100)
        mj.mjr_setBuffer(mj.mjtFramebuffer.mjFB_OFFSCREEN, con)
        con.readDepthMap = mj.mjtDepthMap.mjDEPTH_ZEROFAR
        return con

    def _camera(
        self, model, data, contexts, scene, option, name, wh, instance, draw_rgb=True, lit=True
    ) -> Frames:
        mj = self._mujoco
        con, seg_con = contexts
        width, height = wh
        rect = mj.MjrRect(0, 0, width, height)
        camera = mj.MjvCamera()
        if isinstance(name, View):
            camera.type = mj.mjtCamera.mjCAMERA_FREE
        else:
            camera.type = mj.mjtCamera.mjCAMERA_FIXED
            camera.fixedcamid = model.camera(name).id
        mj.mjv_updateScene(model, data, option, None, camera, mj.mjtCatBit.mjCAT_ALL, scene)
        if isinstance(name, View):
            _place(scene, name, model)
        if not lit:
            con = seg_con  # single-sampled
            shadows = scene.flags[mj.mjtRndFlag.mjRND_SHADOW]
            scene.flags[mj.mjtRndFlag.mjRND_SHADOW] = False

        rgb = np.empty((height, width, 3), np.uint8) if draw_rgb else None
        depth_buffer = np.empty((height, width), np.float32)
        if draw_rgb:
            mj.mjr_setBuffer(mj.mjtFramebuffer.mjFB_OFFSCREEN, con)  # binds this context's framebuffer
            mj.mjr_render(rect, scene, con)
            mj.mjr_readPixels(rgb, None, rect, con)
        if not lit:
            scene.flags[mj.mjtRndFlag.mjRND_SHADOW] = shadows

        # Depth is read from the segmentation pass, which is not anti-aliased: read from the RGB pass it
        # came from one multisample, up to 0.4 px off the pixel centre (60 mm at object edges, measured).
        scene.flags[mj.mjtRndFlag.mjRND_SEGMENT] = True
        scene.flags[mj.mjtRndFlag.mjRND_IDCOLOR] = True
        segrgb = np.empty((height, width, 3), np.uint8)
        mj.mjr_setBuffer(mj.mjtFramebuffer.mjFB_OFFSCREEN, seg_con)
        mj.mjr_render(rect, scene, seg_con)
        mj.mjr_readPixels(segrgb, depth_buffer, rect, seg_con)
        scene.flags[mj.mjtRndFlag.mjRND_SEGMENT] = False
        scene.flags[mj.mjtRndFlag.mjRND_IDCOLOR] = False

        # segid + 1 is encoded in the colour; map it to the scene geom, then to our instance id.
        code = segrgb.astype(np.int64)
        segid = code[..., 0] + code[..., 1] * 256 + code[..., 2] * 65536
        lut = np.zeros(scene.ngeom + 2, dtype=np.int32)
        for i in range(scene.ngeom):
            g = scene.geoms[i]
            if g.segid >= 0 and g.objtype == mj.mjtObj.mjOBJ_GEOM:
                lut[g.segid + 1] = instance[g.objid]
        seg = lut[np.clip(segid, 0, len(lut) - 1)]

        extent = model.stat.extent
        near, far = model.vis.map.znear * extent, model.vis.map.zfar * extent
        # Reversed depth buffer (mjDEPTH_ZEROFAR: 1 at the near plane, 0 at the far plane) -> metres
        # along the optical axis.
        depth = near * far / (near + depth_buffer.astype(np.float64) * (far - near))
        depth[(seg == 0) | (depth_buffer <= 0.0)] = 0.0
        image = None if rgb is None else np.flipud(rgb).copy()
        return Frames(image, np.flipud(depth).astype(np.float32), np.flipud(seg).copy())


def _place(scene, view: View, model) -> None:
    """Point the scene's GL camera (both eyes) and its headlight along ``view``, with its field of view
    and the model's near and far planes (which the depth conversion reads)."""
    extent = model.stat.extent
    near, far = model.vis.map.znear * extent, model.vis.map.zfar * extent
    top = near * np.tan(np.radians(view.fovy) / 2)
    xmat = np.asarray(view.xmat, np.float64).reshape(3, 3)
    for eye in scene.camera:
        eye.pos[:] = view.pos
        eye.forward[:] = -xmat[:, 2]
        eye.up[:] = xmat[:, 1]
        eye.frustum_center = 0.0
        eye.frustum_width = 0.0  # 0: from the viewport's aspect ratio
        eye.frustum_bottom, eye.frustum_top = -top, top
        eye.frustum_near, eye.frustum_far = near, far
        eye.orthographic = 0
    for i in range(scene.nlight):  # a headlight rides with the camera
        if scene.lights[i].headlight:
            scene.lights[i].pos[:] = view.pos
            scene.lights[i].dir[:] = -xmat[:, 2]


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 or single-channel uint16 image (deterministic)."""
    import cv2

    if image.ndim == 3:
        image = image[..., ::-1]  # RGB -> BGR for OpenCV
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def depth_png(depth: np.ndarray) -> bytes:
    """PNG bytes of a depth frame (H, W) metres as uint16 millimetres (0 = no return)."""
    return encode_png(np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16))


def frames_to_files(camera: str, frames: Frames) -> dict[str, bytes]:
    """{file name: PNG bytes} of one camera's frames."""
    return {
        f"{camera}_rgb.png": encode_png(frames.rgb),
        f"{camera}_depth.png": depth_png(frames.depth),
        f"{camera}_seg.png": encode_png(frames.seg.astype(np.uint16)),
    }


_PROCESS_RENDERER: SceneRenderer | None = None


def process_renderer() -> SceneRenderer:
    """This process's renderer, created on first use and closed at exit."""
    global _PROCESS_RENDERER
    if _PROCESS_RENDERER is None:
        import atexit

        _PROCESS_RENDERER = SceneRenderer()
        atexit.register(close_process_renderer)
    return _PROCESS_RENDERER


def close_process_renderer() -> None:
    global _PROCESS_RENDERER
    if _PROCESS_RENDERER is not None:
        _PROCESS_RENDERER.close()
        _PROCESS_RENDERER = None
