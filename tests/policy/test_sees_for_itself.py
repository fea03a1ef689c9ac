"""The learned closed loop reads no ground truth at decision time (issue 33, acceptance 1; issue 43,
point 5): under a guard on every object body, the head and the planners decide from frames, camera
parameters, the robot's own state and the requested category, and the episode makes the same
decisions and ends the same way as an unguarded run.

The guard (:class:`DecisionGuard`) holds from the start of every observation (``observe``, at a
decision point or a re-observation inside push_from_edge and pull_out) until the next physics step,
or the end of the primitive when none follows. While it holds, every object body's state in MuJoCo
(its free joint's qpos and qvel, the body's and its geoms' poses) is NaN, and the scene record's
objects raise on their pose or category, as do the target's name and segmentation id,
``env.target_pose`` and every segmentation image. The renderer (the camera), the scoring code and
the task monitor see the real state: the guard steps aside for them.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest

from scenegen.env.scenes import batch_scenes
from scenegen.perception.retrieval.perceive import RetrievalPerception
from scenegen.policy.network import PrimitivePolicy

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "assets" / "policy" / "baseline"
RETRIEVAL = ROOT / "assets" / "retrieval" / "instances"  # the default head (DEFAULT_HEAD)


class Forbidden:
    """Stands where a segmentation array was: any use of it raises."""

    def _refuse(self, *args, **kwargs):
        raise AssertionError("the segmentation was read outside the scoring and label code")

    __array__ = __getitem__ = __eq__ = __ne__ = __len__ = __iter__ = _refuse
    __getattr__ = _refuse


class GuardedObject:
    """An object of the scene record whose pose and category raise while a decision is made."""

    def __init__(self, placement, guard):
        self._placement, self._guard = placement, guard

    def __getattr__(self, name):
        if name in ("position", "quat", "category", "resting_pose"):
            raise AssertionError(f"an object's {name} was read at decision time")
        return getattr(self._placement, name)


class GuardedScene:
    """The scene record as the environment and the episode hold it: itself outside a decision;
    during one, its objects are :class:`GuardedObject` and its target's name and id raise."""

    def __init__(self, scene, guard):
        self._scene, self._guard = scene, guard

    def __getattr__(self, name):
        value = getattr(self._scene, name)
        if not self._guard.deciding:
            return value
        if name in ("target", "target_id"):
            raise AssertionError(f"the scene's {name} was read at decision time")
        if name == "objects":
            return tuple(GuardedObject(o, self._guard) for o in value)
        return value


class DecisionGuard:
    """See the module docstring. ``decisions`` counts the observations made under it."""

    def __init__(self, scene):
        self.scene = scene  # the real record, for the guard's own bookkeeping
        self.deciding = False
        self.decisions = 0
        self.saved: list | None = None
        self.env = None

    # ------------------------------------------------------------ object bodies in MuJoCo
    def _slots(self, env):
        model = env.sim.model._model
        bodies = np.array([model.body(o.name).id for o in self.scene.objects])
        joints = [model.body_jntadr[b] for b in bodies]
        qpos = np.concatenate([np.arange(model.jnt_qposadr[j], model.jnt_qposadr[j] + 7) for j in joints])
        qvel = np.concatenate([np.arange(model.jnt_dofadr[j], model.jnt_dofadr[j] + 6) for j in joints])
        geoms = np.nonzero(np.isin(model.geom_bodyid, bodies))[0]
        data = env.sim.data._data
        return [
            (data.qpos, qpos),
            (data.qvel, qvel),
            *((getattr(data, k), bodies) for k in ("xpos", "xquat", "xmat", "xipos", "ximat")),
            (data.geom_xpos, geoms),
            (data.geom_xmat, geoms),
        ]

    def poison(self, env):
        if self.saved is None:
            self.env = env
            self.saved = [(array, rows, array[rows].copy()) for array, rows in self._slots(env)]
            for array, rows, _ in self.saved:
                array[rows] = np.nan

    def restore(self):
        if self.saved is not None:
            for array, rows, values in self.saved:
                array[rows] = values
            self.saved = None

    # ------------------------------------------------------------ the decision's span
    def begin(self, env):
        self.deciding = True
        self.decisions += 1
        self.env = env

    def end(self):
        self.restore()
        self.deciding = False

    @contextlib.contextmanager
    def aside(self):
        """The real state for an allowed reader (the renderer, scoring, the task monitor)."""
        was, poisoned, env = self.deciding, self.saved is not None, self.env
        self.restore()
        self.deciding = False
        try:
            yield
        finally:
            self.deciding = was
            if was and poisoned:
                self.poison(env)


def install(guard: DecisionGuard, monkeypatch) -> None:
    """Put the guard around every decision-time path of the learned closed loop."""
    import scenegen.manipulation.primitives as primitives
    import scenegen.manipulation.rollout as rollout
    import scenegen.perception.observation as observation
    import scenegen.perception.retrieval.evaluate as scoring
    import scenegen.policy.evaluate as episodes
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.manipulation.task import RetrieveMonitor

    state = {"scoring": False}
    render, step, pose = SceneEnv.camera_observations, SceneEnv.step, SceneEnv.target_pose
    original_observe, original_run = observation.observe, rollout.run_primitive
    original_score = scoring.score_observation
    monitor_init, monitor_update = RetrieveMonitor.__init__, RetrieveMonitor.update

    def camera_observations(self, segmentation: bool = True, image: bool = True):
        deciding = guard.deciding
        with guard.aside():  # the camera sees the world as it is
            out = render(self, segmentation=True, image=image)
            if not segmentation:
                out = {k: v for k, v in out.items() if not k.endswith("_segmentation")}
                out |= {
                    k: v for k, v in render(self, segmentation=False).items() if k.endswith("_robot_mask")
                }
        if not state["scoring"]:  # ... but only scoring may read the instance masks
            out = {k: Forbidden() if k.endswith("_segmentation") else v for k, v in out.items()}
        if deciding:
            guard.poison(self)
        return out

    def stepped(self, action):
        guard.end()  # acting: the decision is over
        return step(self, action)

    def target_pose(self):
        if guard.deciding:
            raise AssertionError("env.target_pose() was read at decision time")
        return pose(self)

    def observe(env, perception=None, image=True):
        guard.begin(env)
        return original_observe(env, perception, image)

    def run_primitive(*args, **kwargs):
        try:
            return original_run(*args, **kwargs)
        finally:
            guard.end()

    def score_observation(env, obs):
        with guard.aside():
            state["scoring"] = True
            try:
                return original_score(env, obs)
            finally:
                state["scoring"] = False

    def monitored(method):
        def allowed(self, *args, **kwargs):
            with guard.aside():
                return method(self, *args, **kwargs)

        return allowed

    monkeypatch.setattr(SceneEnv, "camera_observations", camera_observations)
    monkeypatch.setattr(SceneEnv, "step", stepped)
    monkeypatch.setattr(SceneEnv, "target_pose", target_pose)
    for module in (observation, rollout, primitives):
        monkeypatch.setattr(module, "observe", observe)
    monkeypatch.setattr(rollout, "run_primitive", run_primitive)
    monkeypatch.setattr(episodes, "run_primitive", run_primitive)
    monkeypatch.setattr(scoring, "score_observation", score_observation)
    monkeypatch.setattr(RetrieveMonitor, "__init__", monitored(monitor_init))
    monkeypatch.setattr(RetrieveMonitor, "update", monitored(monitor_update))


@pytest.fixture(scope="module")
def env(demo_batch: Path):
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.perception.observation import CAMERA_SIZE, CAMERAS

    env = SceneEnv(
        batch_scenes(demo_batch)[0],
        cameras=CAMERAS,
        camera_size=CAMERA_SIZE,
        render_each_step=False,
        horizon=6000,
    )
    yield env
    env.close()


def _episode(env, scene, guarded: bool, monkeypatch):
    from scenegen.policy.evaluate import run_episode

    guard = DecisionGuard(scene)
    if guarded:
        install(guard, monkeypatch)
        scene = GuardedScene(scene, guard)
    perception = RetrievalPerception.load(RETRIEVAL)
    try:
        episode = run_episode(env, PrimitivePolicy.load(POLICY), scene, "e", perception=perception)
    finally:
        guard.end()
        monkeypatch.undo()
    return episode, guard.decisions


def test_the_learned_path_reads_no_ground_truth_at_decision_time(env, demo_batch: Path, monkeypatch):
    scene = batch_scenes(demo_batch)[1]
    normal, _ = _episode(env, scene, False, monkeypatch)
    guarded, decisions = _episode(env, scene, True, monkeypatch)
    assert decisions >= 1
    assert [d.choice for d in guarded.decisions] == [d.choice for d in normal.decisions]
    assert guarded.success == normal.success and guarded.info == normal.info
    for key in ("time", "target_pos", "eef_pos"):
        np.testing.assert_array_equal(np.asarray(guarded.trace[key]), np.asarray(normal.trace[key]))
    first = normal.decisions[0].observation
    assert not any(k.endswith("_segmentation") for k in first)  # the record holds the prediction instead
    assert "front_predicted_target" in first and normal.info["perception_kind"] == "learned"
    scored = normal.info["perception"][0]["cameras"]
    assert any(m["predicted"] for m in scored.values()) and 0.0 <= scored["front"]["iou"] <= 1.0
    assert normal.info["perception_rules"] == 2


@pytest.mark.parametrize("primitive", ["push_from_edge_then_grasp", "pull_out_then_grasp"])
def test_a_re_observation_inside_a_primitive_reads_no_ground_truth(demo_batch: Path, primitive, monkeypatch):
    """``closed_loop.simulate`` (the transfer experiment's physics) runs a primitive that looks
    again half way; guarded and unguarded, its store rows (plans, re-observation, outcome, state)
    are the same."""
    from scenegen.env.robosuite_env import close_worker_envs
    from scenegen.experiment.closed_loop import simulate

    scene = batch_scenes(demo_batch)[1]
    try:
        normal = simulate(scene, (primitive,), RETRIEVAL)
        guard = DecisionGuard(scene)
        install(guard, monkeypatch)
        try:
            guarded = simulate(GuardedScene(scene, guard), (primitive,), RETRIEVAL)
        finally:
            guard.end()
            monkeypatch.undo()
    finally:
        close_worker_envs()
    assert guard.decisions == 2  # the decision and the re-observation inside the primitive
    assert normal[0]["regrasp"] is not None and normal[0]["regrasp"]["plan"] != "unseen"
    assert guarded == normal


def _tiny_proposal_model(folder: Path) -> Path:
    from scenegen.policy.proposal_model import CHANNELS, CROP, FEATURES, train_model

    rng = np.random.default_rng(0)
    crops = rng.random((16, CHANNELS, CROP, CROP), dtype=np.float32)
    features = rng.random((16, FEATURES), dtype=np.float32)
    train_model(crops, features, np.arange(16) % 2, steps=2, batch=4, width=4).save(folder)
    return folder


def _store_guard(monkeypatch) -> None:
    """Any read of a sequence or observation store raises: a decision must not look an outcome up."""
    from scenegen.experiment.sequences import ObservationStore, PathStore

    def refuse(*args, **kwargs):
        raise AssertionError("a store was opened or read at decision time")

    for cls, names in (
        (PathStore, ("__init__", "get", "candidates")),
        (ObservationStore, ("__init__", "get", "meta")),
    ):
        for name in names:
            monkeypatch.setattr(cls, name, refuse)


def test_the_proposal_models_decision_reads_no_ground_truth_and_no_store(
    demo_batch: Path, tmp_path, monkeypatch
):
    """Issue 63, point 4: the sampler and the model decide from frames, cameras, the robot's state
    and the requested category, under the object guard and with every store closed to them; a copy
    of the decision that looks up a stored outcome is caught, and so is one that reads where the
    objects are."""
    from scenegen.env.physics import DEFAULT_PHYSICS, physics_named
    from scenegen.env.robosuite_env import close_worker_envs
    from scenegen.experiment.proposal_labels import LabelConfig
    from scenegen.experiment.proposal_loop import decide
    from scenegen.experiment.sequences import NOMINAL, PathStore
    from scenegen.manipulation.proposals import SamplerConfig

    scene = batch_scenes(demo_batch)[1]
    model = _tiny_proposal_model(tmp_path / "model")
    config, physics = LabelConfig(sampler=SamplerConfig(4, 2, 1, 1)), physics_named(DEFAULT_PHYSICS)
    args = (None, [], [], model, RETRIEVAL, NOMINAL, config, physics)
    try:
        normal = decide(scene, *args)
        guard = DecisionGuard(scene)
        install(guard, monkeypatch)
        _store_guard(monkeypatch)
        try:
            guarded = decide(GuardedScene(scene, guard), *args)
            guard.end()  # as the attempt's first step would

            def cheating(scene, *rest):  # the same decision, then a look at what happened before
                decision = decide(scene, *rest)
                PathStore(tmp_path / "paths.jsonl").get("sha", ["token"])
                return decision

            with pytest.raises(AssertionError, match="store was opened or read"):
                cheating(GuardedScene(scene, guard), *args)
            guard.end()

            def peeking(scene, *rest):  # the same decision, then a look at where the objects are
                decision = decide(scene, *rest)
                return decision, [o.position for o in scene.objects]

            with pytest.raises(AssertionError, match="an object's position was read at decision time"):
                peeking(GuardedScene(scene, guard), *args)
        finally:
            guard.end()
            monkeypatch.undo()
    finally:
        close_worker_envs()
    assert guard.decisions == 3 and normal["candidate"] is not None and normal["proposed"] >= 4
    assert guarded == normal
