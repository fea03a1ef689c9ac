"""The learned closed loop reads no segmentation at decision time (issue 33, acceptance 1): an
episode in which every segmentation the environment returns raises on access, except in the scoring
code, makes the same decisions and ends the same way as a normal run of the learned path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.env.scenes import batch_scenes
from scenegen.perception.retrieval.perceive import RetrievalPerception
from scenegen.policy.network import PrimitivePolicy

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "assets" / "policy" / "baseline"
RETRIEVAL = ROOT / "assets" / "retrieval" / "baseline"


class Forbidden:
    """Stands where a segmentation array was: any use of it raises."""

    def _refuse(self, *args, **kwargs):
        raise AssertionError("the segmentation was read outside the scoring and label code")

    __array__ = __getitem__ = __eq__ = __ne__ = __len__ = __iter__ = _refuse
    __getattr__ = _refuse


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
    import scenegen.perception.retrieval.evaluate as scoring
    from scenegen.policy.evaluate import run_episode

    if guarded:
        state = {"scoring": False}
        render = type(env).camera_observations

        def camera_observations(self, segmentation: bool = True):
            out = render(self, segmentation=True)  # the simulator always has it ...
            if not state["scoring"]:  # ... but only scoring may read it
                out = {k: Forbidden() if k.endswith("_segmentation") else v for k, v in out.items()}
            if not segmentation:  # the robot's own pixels, as the environment gives them
                out |= {
                    k: v for k, v in render(self, segmentation=False).items() if k.endswith("_robot_mask")
                }
            return out

        original = scoring.score_observation

        def score_observation(env, obs):
            state["scoring"] = True
            try:
                return original(env, obs)
            finally:
                state["scoring"] = False

        monkeypatch.setattr(type(env), "camera_observations", camera_observations)
        monkeypatch.setattr(scoring, "score_observation", score_observation)
    perception = RetrievalPerception.load(RETRIEVAL)
    episode = run_episode(env, PrimitivePolicy.load(POLICY), scene, "e", perception=perception)
    monkeypatch.undo()
    return episode


def test_the_learned_path_reads_no_segmentation_at_decision_time(env, demo_batch: Path, monkeypatch):
    scene = batch_scenes(demo_batch)[1]
    normal = _episode(env, scene, False, monkeypatch)
    guarded = _episode(env, scene, True, monkeypatch)
    assert [d.choice for d in guarded.decisions] == [d.choice for d in normal.decisions]
    assert guarded.success == normal.success and guarded.info == normal.info
    for key in ("time", "target_pos", "eef_pos"):
        np.testing.assert_array_equal(np.asarray(guarded.trace[key]), np.asarray(normal.trace[key]))
    first = normal.decisions[0].observation
    assert not any(k.endswith("_segmentation") for k in first)  # the record holds the prediction instead
    assert "front_predicted_target" in first and normal.info["perception_kind"] == "learned"
    scored = normal.info["perception"][0]["cameras"]
    assert any(m["predicted"] for m in scored.values()) and 0.0 <= scored["front"]["iou"] <= 1.0
