"""The gymnasium face of the environment: gymnasium's own checker passes, draws are seeded, and a
mixture recipe decides which sources the resets come from."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from scenegen.core.files import load_rows
from scenegen.env.mixture import MixtureEntry, MixtureRecipe
from scenegen.env.scenes import batch_scenes, reference_scene
from scenegen.paths import PROJECT_ROOT

REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def gym_env(demo_batch: Path):
    from scenegen.env.gym_env import SceneGymEnv

    scenes = batch_scenes(demo_batch)[:3] + [reference_scene(r) for r in load_rows(REFERENCE, "train")[:3]]
    recipe = MixtureRecipe(
        entries=[MixtureEntry(source="batch", weight=0.8), MixtureEntry(source="reference", weight=0.2)]
    )
    env = SceneGymEnv(scenes, recipe, cameras=["front"], camera_size=(48, 32), horizon=5)
    yield env
    env.close()


def test_gymnasiums_checker_passes(gym_env):
    check_env(gym_env, skip_render_check=True)


def test_the_same_seed_draws_the_same_scenes_and_the_recipe_weights_them(gym_env):
    def draws(seed):
        gym_env.reset(seed=seed)
        return [gym_env._draw() for _ in range(400)]

    first, again = draws(3), draws(3)
    assert first == again and draws(4) != first
    sources = Counter(gym_env.scenes[i].source for i in first)
    assert sources["batch"] / 400 == pytest.approx(0.8, abs=3 * np.sqrt(0.8 * 0.2 / 400))


def test_reset_returns_the_observation_its_space_declares_and_names_the_scene(gym_env):
    obs, info = gym_env.reset(seed=0, options={"scene_index": 4})
    assert info["origin"] == "reference" and info["scene_index"] == 4
    assert gym_env.observation_space.contains(obs)
    assert obs["front_image"].shape == (32, 48, 3)
    truncated = False
    for _ in range(5):
        obs, reward, terminated, truncated, info = gym_env.step(gym_env.action_space.sample())
    assert truncated and not terminated  # the horizon ends it; the plain environment has no task


def test_a_scene_index_out_of_range_is_refused(gym_env):
    with pytest.raises(ValueError, match="options.scene_index 6"):
        gym_env.reset(options={"scene_index": 6})
