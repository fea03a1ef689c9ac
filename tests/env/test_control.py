"""The lean controller (scenegen/env/control.py) against robosuite's own: two environments on the same
reference layout, stepped side by side with the same actions (random deltas, gripper flips, contact
with the table), must hold bit-identical joint positions, velocities and commands at every step."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen.core.files import load_rows
from scenegen.env.scenes import reference_scene
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.rollout import run_primitive
from scenegen.paths import PROJECT_ROOT

REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def scenes():
    rows = [r for r in load_rows(REFERENCE, "train") if r["tag_nominal"]][:2]
    return [reference_scene(r) for r in rows]


@pytest.fixture(scope="module")
def pair(scenes):
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON

    options = {"cameras": CAMERAS, "camera_size": CAMERA_SIZE, "render_each_step": False, "horizon": HORIZON}
    lean, robosuite = SceneEnv(scenes[0], **options), SceneEnv(scenes[0], lean_control=False, **options)
    yield lean, robosuite
    lean.close()
    robosuite.close()


def state(env) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    data = env.sim.data._data
    return data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()


def test_the_lean_path_is_taken_by_default_and_robosuites_on_request(pair, scenes):
    lean, robosuite = pair
    lean.reset_to(scenes[0])
    robosuite.reset_to(scenes[0])
    assert lean._control is not None
    assert robosuite._control is None


def test_random_actions_give_bit_identical_states_at_every_step(pair, scenes):
    lean, robosuite = pair
    rng = np.random.default_rng(0)
    for scene in scenes:
        lean.reset_to(scene)
        robosuite.reset_to(scene)
        down = np.array([0, 0, -1.0, 0, 0, 0, -1.0])  # into the table and the objects: contacts
        actions = [down] * 15 + [
            np.concatenate([rng.uniform(-1, 1, 6), [rng.choice([-1.0, 1.0])]]) for _ in range(45)
        ]
        for n, action in enumerate(actions):
            lean.step(action)
            robosuite.step(action)
            for a, b, what in zip(state(lean), state(robosuite), ("qpos", "qvel", "ctrl"), strict=True):
                assert np.array_equal(a, b), f"{scene.scene_id} step {n}: {what} differs"


def test_a_primitive_ends_in_the_same_state_and_outcome(pair, scenes):
    lean, robosuite = pair
    outcomes = []
    for env in pair:
        env.reset_to(scenes[0])
        outcome, params = run_primitive(env, next(iter(PRIMITIVES)))
        outcomes.append((outcome, params, state(env), env.timestep))
    (a, pa, sa, ta), (b, pb, sb, tb) = outcomes
    assert a == b and ta == tb
    assert all(np.array_equal(x, y) for x, y in zip(sa, sb, strict=True))
    assert a.time > 1.0  # it moved the arm for a while


def test_a_wrong_action_length_is_one_clear_error(pair, scenes):
    lean, _ = pair
    lean.reset_to(scenes[0])
    with pytest.raises(ValueError, match="takes 7"):
        lean.step(np.zeros(6))


def test_a_second_reset_into_the_same_scene_reuses_the_model_and_gives_the_same_run(pair, scenes):
    lean, robosuite = pair
    lean.reset_to(scenes[0])
    model = lean.sim.model._model
    for _ in range(10):
        lean.step(np.array([0, 0, -1.0, 0, 0, 0, 1.0]))
    lean.reset_to(scenes[0])  # soft: the same model, its data reset
    assert lean.sim.model._model is model
    robosuite.reset_to(scenes[1])
    robosuite.reset_to(scenes[0])  # hard: a model built anew
    assert robosuite.sim.model._model is not model
    for env in pair:
        run_primitive(env, "side_grasp")
    assert all(np.array_equal(a, b) for a, b in zip(state(lean), state(robosuite), strict=True))
    lean.reset_to(scenes[1])
    assert lean.sim.model._model is not model
