"""The environment that resets into stored scenes and reference layouts: real robosuite controllers on
real MuJoCo, frames from the project's renderer, checked against the stored files with plain MuJoCo."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import mujoco
import numpy as np
import pytest

from scenegen.core.files import load_rows
from scenegen.env.scenes import EnvScene, batch_scenes, reference_scene
from scenegen.paths import PROJECT_ROOT

REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"
HOLD = np.array([0, 0, 0, 0, 0, 0, -1.0])  # OSC_POSE delta 0, gripper open
CONTROL_FREQ = 20  # Hz (SceneEnv's)


@pytest.fixture(scope="module")
def scenes(demo_batch: Path) -> list[EnvScene]:
    return batch_scenes(demo_batch)


@pytest.fixture(scope="module")
def env(scenes):
    from scenegen.env.robosuite_env import SceneEnv

    env = SceneEnv(scenes[0])
    yield env
    env.close()


def stored_state(scene: EnvScene) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The stored scene.xml at its keyframe 'settled', read with plain MuJoCo."""
    model = mujoco.MjModel.from_xml_path(str(scene.path / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return model, data


def body_positions(env, names) -> dict[str, np.ndarray]:
    model, data = env.sim.model._model, env.sim.data._data
    return {n: data.xpos[model.body(n).id].copy() for n in names}


def arm_qpos(env) -> np.ndarray:
    return env.sim.data._data.qpos[env.robots[0]._ref_joint_pos_indexes].copy()


def test_reset_puts_every_object_and_the_arm_at_the_stored_settled_state(env, scenes):
    for scene in scenes[:3]:
        env.reset_to(scene)
        model, data = stored_state(scene)
        here = body_positions(env, [o.name for o in scene.objects])
        for name, position in here.items():
            assert np.abs(position - data.xpos[model.body(name).id]).max() < 1e-3, name
        stored_arm = [data.qpos[model.joint(f"robot0_joint{i}").qposadr[0]] for i in range(1, 8)]
        np.testing.assert_allclose(arm_qpos(env), stored_arm, atol=1e-4)
        target = env.target_pose()[0]
        assert np.abs(target - data.xpos[model.body(scene.target).id]).max() < 1e-3


def test_holding_still_keeps_the_arm_and_the_objects_within_1_mm_for_2_s(env, scenes):
    obs = env.reset_to(scenes[1])
    names = [o.name for o in scenes[1].objects]
    before, eef = body_positions(env, names), obs["robot0_eef_pos"].copy()
    for _ in range(2 * CONTROL_FREQ):
        obs, *_ = env.step(HOLD)
    assert np.abs(obs["robot0_eef_pos"] - eef).max() < 1e-3
    after = body_positions(env, names)
    moved = {n: float(np.abs(after[n] - before[n]).max()) for n in names}
    assert max(moved.values()) < 1e-3, moved


def test_a_scripted_5_cm_move_along_x_arrives_within_1_cm(env, scenes):
    obs = env.reset_to(scenes[0])
    goal = obs["robot0_eef_pos"] + np.array([0.05, 0.0, 0.0])
    for _ in range(3 * CONTROL_FREQ):
        action = HOLD.copy()
        action[:3] = np.clip((goal - obs["robot0_eef_pos"]) / 0.05, -1, 1)
        obs, *_ = env.step(action)
    assert np.linalg.norm(obs["robot0_eef_pos"] - goal) < 0.01


@pytest.mark.parametrize("kind", ["generated", "reference"])
def test_a_random_rollout_of_200_steps_does_not_diverge(env, scenes, kind):
    scene = scenes[2] if kind == "generated" else reference_scene(load_rows(REFERENCE, "train")[0])
    obs = env.reset_to(scene)
    rng = np.random.default_rng(0)
    model, data = env.sim.model._model, env.sim.data._data
    for _ in range(200):
        obs, *_ = env.step(rng.uniform(-1, 1, 7))
    assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()
    assert np.abs(data.qvel).max() < 50.0  # rad/s or m/s: nothing flew off
    for obj in scene.objects:
        assert np.linalg.norm(data.xpos[model.body(obj.name).id]) < 3.0, obj.name  # still near the table
    # within the arm's reach and not inside its base (a folded Panda holds its hand 0.25-0.3 m from it)
    assert 0.2 < np.linalg.norm(obs["robot0_eef_pos"] - data.xpos[model.body("robot0_base").id]) < 1.2


def test_resetting_into_another_scene_leaks_nothing(env, scenes):
    first = env.reset_to(scenes[0])
    env.step(np.array([1.0, 0, 0, 0, 0, 0, 1.0]))  # move and close the fingers
    env.reset_to(scenes[1])
    for _ in range(5):
        env.step(np.array([0, 1.0, 0, 0, 0, 0, 1.0]))
    again = env.reset_to(scenes[0])
    for key in ("robot0_joint_pos", "robot0_eef_pos", "robot0_gripper_qpos", "target_id"):
        np.testing.assert_array_equal(first[key], again[key], err_msg=key)
    obs_a, *_ = env.step(HOLD)
    env.reset_to(scenes[0])
    obs_b, *_ = env.step(HOLD)
    np.testing.assert_array_equal(obs_a["robot0_eef_pos"], obs_b["robot0_eef_pos"])


def test_camera_frames_reproduce_the_stored_renders(scenes):
    """Under the scene's cameras and lights, at the stored size, the frames equal the stored PNGs;
    segmentation ids are scene.json's and the target's id is observed."""
    from scenegen.env.robosuite_env import SceneEnv

    scene = scenes[0]
    width, height = scene.cameras[0].width, scene.cameras[0].height
    env = SceneEnv(scene, cameras=[c.name for c in scene.cameras], camera_size=(width, height))
    try:
        obs = env.reset_to(scene)
        for cam in scene.cameras:
            seg = cv2.imread(str(scene.path / f"{cam.name}_seg.png"), cv2.IMREAD_UNCHANGED)
            rgb = cv2.imread(str(scene.path / f"{cam.name}_rgb.png"))[..., ::-1]
            assert obs[f"{cam.name}_image"].shape == (height, width, 3)
            assert (obs[f"{cam.name}_segmentation"][..., 0] == seg).mean() > 0.999
            assert np.abs(obs[f"{cam.name}_image"].astype(int) - rgb).mean() < 1.0
            depth = obs[f"{cam.name}_depth"][..., 0]
            assert depth.dtype == np.float32 and 0.3 < np.median(depth[depth > 0]) < 5.0
        ids = set(np.unique(obs[f"{scene.cameras[0].name}_segmentation"]))
        assert ids <= set(scene.segmentation.values()) | {0}
        assert obs["target_id"][0] == scene.segmentation[scene.target]
        assert scene.segmentation == json.loads((scene.path / "scene.json").read_text())["segmentation"]
    finally:
        env.close()


def test_a_camera_the_scene_lacks_is_refused(scenes):
    from scenegen.env.robosuite_env import SceneEnv

    with pytest.raises(ValueError, match="cameras \\['wrist'\\]"):
        SceneEnv(scenes[0], cameras=["wrist"])


def test_a_reference_row_becomes_a_scene_with_the_default_cameras():
    row = load_rows(REFERENCE, "train")[0]
    scene = reference_scene(row)
    assert scene.origin == "reference" and scene.target == row["target"]
    assert [c.name for c in scene.cameras] == ["front", "side"]
    assert len(scene.objects) == row["n_objects"] and scene.robot_pose == tuple(row["robot_pose"])
