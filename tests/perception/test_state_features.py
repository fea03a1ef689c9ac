"""The state-observation ablation's policy input (policy/observation.py ``state_features``) and the
policy network that reads it: what they encode, measured on real reference scenes in a real SceneEnv."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from scenegen.core.files import load_rows
from scenegen.env.robosuite_env import SceneEnv
from scenegen.env.scenes import reference_scene
from scenegen.perception.observation import CATEGORIES, STATE_SIZE, state_features
from scenegen.policy.labels import CAMERA_SIZE
from scenegen.policy.network import PrimitivePolicy

REFERENCE = Path("assets/reference/reference.parquet")


def test_state_features_say_category_uprightness_and_furniture_above():
    rows = load_rows(REFERENCE, "train")
    lying = next(r for r in rows if r["tag_toppled"] and r["target_category"] == "can")
    upright = next(r for r in rows if r["tag_nominal"] and r["target_category"] == "can")
    under = next(r for r in rows if r["tag_under_overhang"] and not r["tag_toppled"])
    scenes = [reference_scene(r) for r in (lying, upright, under)]
    env = SceneEnv(scenes[0], cameras=["front"], camera_size=CAMERA_SIZE, render_each_step=False)
    try:
        features = []
        for scene in scenes:
            env.reset_to(scene)
            features.append(state_features(env))
    finally:
        env.close()
    lying_f, upright_f, under_f = features
    assert all(f.shape == (STATE_SIZE,) and f.dtype == np.float32 for f in features)
    n = len(CATEGORIES)
    assert lying_f[CATEGORIES.index("can")] == 1 and lying_f[:n].sum() == 1
    assert upright_f[n + 3] > 0.9 and lying_f[n + 3] < 0.5  # the z of the target's own z axis
    assert under_f[n + 5] >= 1 and upright_f[n + 5] == 0  # furniture above the target
    assert 0 < under_f[n + 6] < 1  # its clearance (m)


def test_a_state_policy_saves_loads_and_chooses(tmp_path: Path):
    policy = PrimitivePolicy(["top_grasp", "side_grasp"], inputs="state")
    policy.save(tmp_path / "p")
    loaded = PrimitivePolicy.load(tmp_path / "p")
    assert loaded.inputs == "state"
    x = torch.zeros(STATE_SIZE)
    assert loaded.choose(x) in {"top_grasp", "side_grasp"}
    assert loaded.choose(x, exclude={"top_grasp"}) == "side_grasp"
