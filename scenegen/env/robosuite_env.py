"""A robosuite environment that resets into a stored or reference scene (:class:`SceneEnv`).

The model is rebuilt from the scene's description through the project's world builder
(``sim.world.build_world``), on top of the robot-and-table model of this environment's own robosuite
robot, with robosuite's torque actuators and no gravity compensation (``hold=False``): the stored
scene.xml holds its arm with position servos and gravity compensation for settling, which robosuite's
controllers (they write torques and compensate gravity themselves) must not meet. Body and joint names
are robosuite's (``robot0_*``, ``gripper0_right_*``), so its robot classes and controllers work
unchanged; the sim is handed to robosuite through its own hook, ``_initialize_sim``.

Reset puts the objects at their settled poses and the robot at the scene's initial pose (fingers open
as when the scene settled), zero velocities. Observations are robosuite's robot observations
(``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``, ``robot0_joint_pos``, ...) plus,
for each requested camera of the scene, ``<cam>_image`` (H, W, 3) uint8, ``<cam>_depth`` (H, W, 1)
float32 metres along the optical axis (0: no return) and ``<cam>_segmentation`` (H, W, 1) int32
instance ids as in scene.json, rendered by the project's renderer under the scene's lights, top row
first; and ``target_id``, the target's instance id.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

from scenegen.assets.catalog import Catalog, load_catalog, load_catalogs
from scenegen.core.layout import TABLE_SIZE, TABLE_TOP_Z
from scenegen.env.control import lean_control
from scenegen.env.physics import DEFAULT_PHYSICS, ControlPhysics, physics_named
from scenegen.env.scenes import EnvScene, target_category
from scenegen.render.offscreen import MAX_SIZE, SceneRenderer
from scenegen.render.sensor import Sight
from scenegen.sim import world

DEFAULT_CONTROLLER = "BASIC"  # robosuite's composite controller: OSC_POSE arm + gripper, 7-D action
CONTROL_FREQ = 20  # Hz: one action per 50 ms (10 physics steps of 5 ms under dt5, 25 of 2 ms under exact)
FINGER_OPEN = 0.04  # m: finger joint opening of a settled scene (world.GRIPPER_OPEN)


def _robosuite():
    world._quiet_robosuite()
    from robosuite.controllers import load_composite_controller_config
    from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
    from robosuite.models.arenas import TableArena
    from robosuite.models.tasks import ManipulationTask
    from robosuite.utils.binding_utils import MjSim

    return ManipulationEnv, TableArena, ManipulationTask, MjSim, load_composite_controller_config


ManipulationEnv, TableArena, ManipulationTask, MjSim, load_composite_controller_config = _robosuite()


class SceneEnv(ManipulationEnv):
    """robosuite's Panda on the scene's table, reset into :class:`EnvScene` values.

    ``scene``: the first scene (``reset_to`` switches); ``controller_config``: a robosuite composite
    controller config (default: ``load_composite_controller_config(controller="BASIC")``, OSC_POSE
    arm with delta actions + gripper); ``cameras``: scene camera names to observe (default none: no
    rendering), at ``camera_size`` (width, height) pixels; ``lean_control``: the default
    controller's torques through :mod:`scenegen.env.control` (bit-identical, a fraction of the CPU;
    False: robosuite's own path, what the benchmarks compare it with); ``physics``: what the model
    is compiled with, a name of ``env.physics.PHYSICS`` or a :class:`ControlPhysics` (solver,
    timestep, collision geometry; the control rate stays 20 Hz).
    """

    def __init__(
        self,
        scene: EnvScene,
        controller_config: dict | None = None,
        cameras: Sequence[str] = (),
        camera_size: tuple[int, int] = (128, 128),
        horizon: int = 400,
        catalog: Catalog | None = None,
        seed: int | None = None,
        render_each_step: bool = True,
        lean_control: bool = True,
        physics: str | ControlPhysics = DEFAULT_PHYSICS,
    ):
        self.physics = physics_named(physics)
        self.scene = scene
        self.lean_control = lean_control
        self._control = None  # the LeanControl of this reset's robot, or None: robosuite's path
        self._built_for: EnvScene | None = None  # the scene the loaded model was built for
        # the task's request ("retrieve the mug"): what a learned perception is told to look for
        self.requested_category = target_category(scene)
        self.render_each_step = render_each_step
        self.catalog = catalog or load_catalog()
        self.cameras = tuple(cameras)
        self.camera_size = tuple(camera_size)
        if not (0 < self.camera_size[0] <= MAX_SIZE[0] and 0 < self.camera_size[1] <= MAX_SIZE[1]):
            raise ValueError(f"camera_size {self.camera_size}: must be positive and at most {MAX_SIZE}")
        self._robot_spec: mujoco.MjSpec | None = None
        self._renderer: SceneRenderer | None = None
        # (sensor, decision point): depth frames as that sensor returns them there (None: exact;
        # render/sensor.py); cleared by every reset, set by the caller per decision point
        self.depth_sensor: tuple | None = None
        self._check_cameras(scene)
        super().__init__(
            robots="Panda",
            controller_configs=controller_config
            or load_composite_controller_config(controller=DEFAULT_CONTROLLER),
            initialization_noise=None,
            use_camera_obs=False,  # camera frames come from the project's renderer, below
            has_renderer=False,
            has_offscreen_renderer=False,
            renderer="mujoco",  # no robosuite viewer: frames come from SceneRenderer
            render_camera=None,
            control_freq=CONTROL_FREQ,
            horizon=horizon,
            ignore_done=False,
            hard_reset=True,
            seed=seed,
        )

    # ------------------------------------------------------------------ scenes
    def _check_cameras(self, scene: EnvScene) -> None:
        names = {c.name for c in scene.cameras}
        missing = [c for c in self.cameras if c not in names]
        if missing:
            raise ValueError(
                f"cameras {missing}: scene {scene.scene_id} has only {sorted(names)}; pick from those"
            )

    def reset_to(self, scene: EnvScene) -> OrderedDict:
        """Reset into ``scene``: objects settled, robot at the scene's initial pose. A new model is
        built unless the model loaded was built for an equal scene: then robosuite's soft reset
        (``mj_resetData`` on the same model, controllers made anew) gives the same state, bit for bit
        (tests/env/test_control.py), without the compile."""
        self._check_cameras(scene)
        self.scene = scene
        # the task's request ("retrieve the mug"): what a learned perception is told to look for
        self.requested_category = target_category(scene)
        self.hard_reset = scene != self._built_for
        self.depth_sensor = None
        try:
            return self.reset()
        finally:
            self.hard_reset = True

    # ------------------------------------------------------------------ robosuite hooks
    def _load_model(self):
        if self._robot_spec is None:  # robosuite's robot and table, loaded once per environment
            super()._load_model()
            robot = self.robots[0].robot_model
            robot.set_base_xpos(robot.base_xpos_offset["table"](TABLE_SIZE[0]))
            arena = TableArena(table_full_size=TABLE_SIZE, table_offset=(0, 0, TABLE_TOP_Z))
            arena.set_origin([0, 0, 0])
            self.model = ManipulationTask(mujoco_arena=arena, mujoco_robots=[robot])
            self._robot_spec = world.robot_world_spec(self.model.get_xml(), hold=False)

    def _initialize_sim(self, xml_string=None):
        scene = self.scene
        catalog = load_catalogs(list(map(Path, scene.catalogs))) if scene.catalogs else self.catalog
        spec = world.build_world(
            catalog,
            scene.objects,
            scene.furniture,
            scene.lighting,
            scene.cameras,
            base=self._robot_spec.copy(),
            floor=scene.floor,
            table_rolling_friction=scene.table_rolling_friction,
        )
        self.physics.apply(spec, catalog, scene.objects)
        self.sim = MjSim(spec.compile())
        self._built_for = scene
        self.sim.forward()
        self.initialize_time(self.control_freq)

    def initialize_time(self, control_freq):
        # robosuite takes the physics step from its macros (2 ms); this model's is the physics'
        super().initialize_time(control_freq)
        self.model_timestep = self.physics.timestep

    def _reset_internal(self):
        robot = self.robots[0]
        robot.init_qpos = np.asarray(self.scene.robot_pose, dtype=float)
        super()._reset_internal()
        model, data = self.sim.model._model, self.sim.data._data
        for obj in self.scene.objects:
            adr = model.joint(f"{obj.name}_joint").qposadr[0]
            data.qpos[adr : adr + 3] = obj.position
            data.qpos[adr + 3 : adr + 7] = obj.quat
        for j in range(model.njnt):
            name = model.joint(j).name
            if name.startswith("gripper0_") and name.endswith(("finger_joint1", "finger_joint2")):
                data.qpos[model.jnt_qposadr[j]] = FINGER_OPEN if name.endswith("1") else -FINGER_OPEN
        data.qvel[:] = 0.0
        data.act[:] = 0.0
        data.ctrl[:] = 0.0
        self.sim.forward()
        self._control = lean_control(robot) if self.lean_control else None

    def _pre_action(self, action, policy_step=False):
        if self._control is None:
            return super()._pre_action(action, policy_step)
        if policy_step and len(action) != 7:
            raise ValueError(f"action of length {len(action)}: this environment takes 7 (arm 6, gripper 1)")
        self._control.control(action, policy_step)

    def _destroy_sim(self):
        # robosuite's MjSim.free() ends in gc.collect(): a full collection per reset, 0.16 s in a
        # process that holds torch and a head (measured in a closed-loop evaluation); the model and
        # data are freed when their last reference goes, and the collector runs on its own schedule
        self.sim = None

    def _setup_references(self):
        super()._setup_references()
        model = self.sim.model._model
        self.target_body_id = model.body(self.scene.target).id

    def _update_observables(self, force=False):
        # robosuite samples each observable when its own clock, advanced by the physics step at every
        # substep, passes 1/control_freq; under a 5 ms step ten steps add up to 0.04999... s, so the
        # sample fell a substep late and an observation returned the state of the step before (up to
        # 0.047 rad off, measured). Observables are sampled here once, at the end of each control step
        # (_get_observations), the instant they described under the 2 ms step; the substeps skip them.
        if force:
            super()._update_observables(force=True)

    def _get_observations(self, force_update=False):
        obs = super()._get_observations(force_update=True)  # now: see _update_observables
        if self.cameras and self.render_each_step:
            obs.update(self.camera_observations())
        obs["target_id"] = np.array([self.scene.target_id], dtype=np.int32)
        return obs

    def camera_observations(self, segmentation: bool = True, image: bool = True) -> dict[str, np.ndarray]:
        """``<cam>_image``, ``<cam>_depth``, ``<cam>_segmentation`` of each observed camera, now.

        ``segmentation=False``: what a robot has without the simulator's instance masks: no
        ``<cam>_segmentation``, and instead ``<cam>_robot_mask`` (H, W, 1) bool, the robot's own
        pixels, as a self-filter computes them from its known geometry and joint angles (here the
        renderer's robot instance: the visible pixels of the robot's own meshes). ``image=False``:
        no ``<cam>_image`` (its colour pass is not drawn), for a caller that reads depth and masks
        only. With ``depth_sensor`` set, the depth is that sensor's at that decision point."""
        if self._renderer is None:  # one GL context per environment, made on first use
            self._renderer = SceneRenderer()
        model, data = self.sim.model._model, self.sim.data._data
        frames = self._renderer.render(
            model,
            data,
            self.cameras,
            self.scene.segmentation,
            [self.camera_size] * len(self.cameras),
            rgb=image,
        )
        out = {}
        robot = self.scene.segmentation["robot"]
        for name, f in zip(self.cameras, frames, strict=True):
            if image:
                out[f"{name}_image"] = f.rgb
            depth = f.depth
            if self.depth_sensor is not None:
                sensor, point = self.depth_sensor
                sight = Sight(self._renderer, model, data, name, self.camera_size, self.scene.segmentation,
                              f.depth, f.rgb)  # fmt: skip
                depth = sensor.measure(sight, point)
            out[f"{name}_depth"] = depth[..., None]
            if segmentation:
                out[f"{name}_segmentation"] = f.seg.astype(np.int32)[..., None]
            else:
                out[f"{name}_robot_mask"] = (f.seg == robot)[..., None]
        return out

    def reward(self, action=None) -> float:
        """No task here: 0. The recovery task (scenegen/policy/) defines reward and success."""
        return 0.0

    def _check_success(self) -> bool:
        return False

    def target_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The target's position (m) and wxyz quaternion, now."""
        data = self.sim.data._data
        return data.xpos[self.target_body_id].copy(), data.xquat[self.target_body_id].copy()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()


def close_at_exit(close) -> None:
    """Run ``close`` (freeing an environment's GL context) at interpreter exit, before EGL's own
    teardown. MuJoCo's EGL module registers ``eglTerminate`` with atexit when it opens its display,
    at the first context; exit handlers run last-registered first, so a handler registered before
    that would free its context on a terminated display (an EGLError printed at every worker's exit).
    Opening the display first puts ``close`` ahead of it."""
    import atexit
    import os

    if os.environ.get("MUJOCO_GL") == "egl":
        from mujoco.egl import GLContext

        GLContext(1, 1).free()
    atexit.register(close)


def close_quietly(env) -> None:
    """Close a worker's environment at exit, where EGL may already be torn down (then nothing is
    left to free: the process ends anyway)."""
    try:
        env.close()
    except Exception:  # noqa: BLE001 - EGL's own errors at teardown
        pass


# ------------------------------------------------------------------------- a worker process's environments
_WORKER_ENVS: dict[str, SceneEnv] = {}


def worker_env(scene, **options) -> SceneEnv:
    """This process's environment made with ``options`` (one per distinct set, made at first use,
    closed at exit once :func:`init_worker` ran); the caller resets it into its scene."""
    key = repr(sorted(options.items()))
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = SceneEnv(scene, **options)
    return _WORKER_ENVS[key]


def init_worker() -> None:
    """A process that renders: EGL unless told otherwise, its environments closed before EGL's
    teardown at exit."""
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    close_at_exit(close_worker_envs)


def close_worker_envs() -> None:
    """Close this process's environments (at exit, or when a single-process run is done)."""
    for env in _WORKER_ENVS.values():
        close_quietly(env)
    _WORKER_ENVS.clear()
