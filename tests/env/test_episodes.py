"""The episode record, filled by a scripted rollout in the real environment, written and read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.env.episodes import TRACE_KEYS, EpisodeError, EpisodeRecorder, read_episode, write_episode
from scenegen.env.scenes import batch_scenes


@pytest.fixture(scope="module")
def episode(demo_batch: Path):
    from scenegen.env.robosuite_env import SceneEnv

    scene = batch_scenes(demo_batch)[0]
    env = SceneEnv(scene, cameras=["front"], camera_size=(32, 24))
    try:
        obs = env.reset_to(scene)
        recorder = EpisodeRecorder(env, "scripted_0", observation_kind="rgbd", trace_every=5)
        for leg in ([1.0, 0, 0], [0, 0, -1.0]):  # two decisions: forward, then down
            recorder.decide(obs, {"action": leg})
            for _ in range(12):
                obs, _, _ = recorder.step([*leg, 0, 0, 0, -1.0])
        yield recorder.finish(success=False, note="scripted")
    finally:
        env.close()


def test_the_record_holds_decisions_actions_and_a_subsampled_trace(episode):
    assert episode.length == 24 and len(episode.rewards) == 24
    assert [d.step for d in episode.decisions] == [0, 12]
    assert episode.decisions[1].observation["front_image"].shape == (24, 32, 3)
    assert len(episode.trace["time"]) == 1 + 24 // 5 + 1  # the start, every 5 steps, the end
    eef = np.asarray(episode.trace["eef_pos"])
    assert eef[len(eef) // 2, 0] > eef[0, 0] + 0.01  # moved forward, then down
    assert eef[-1, 2] < eef[len(eef) // 2, 2] - 0.01
    assert episode.scene["target"] and episode.observation_kind == "rgbd"


def test_an_episode_round_trips_through_its_folder(episode, tmp_path: Path):
    back = read_episode(write_episode(tmp_path / "ep", episode))
    assert back.episode_id == episode.episode_id and back.info == {"note": "scripted"}
    np.testing.assert_array_equal(np.asarray(back.actions), np.asarray(episode.actions, dtype=np.float32))
    for key in TRACE_KEYS:
        np.testing.assert_array_equal(np.asarray(back.trace[key]), np.asarray(episode.trace[key]), key)
    for mine, theirs in zip(episode.decisions, back.decisions, strict=True):
        assert mine.choice == theirs.choice and mine.step == theirs.step
        for key, value in mine.observation.items():
            np.testing.assert_array_equal(theirs.observation[key], value)


def test_an_episode_without_an_action_round_trips(episode, tmp_path: Path):
    """A learned perception that never sees the target acts not at all: the record still writes."""
    import dataclasses

    idle = dataclasses.replace(episode, actions=[], rewards=[], decisions=episode.decisions[:1])
    back = read_episode(write_episode(tmp_path / "idle", idle))
    assert back.length == 0 and len(back.decisions) == 1


def test_a_damaged_episode_folder_is_one_clear_error(episode, tmp_path: Path):
    folder = write_episode(tmp_path / "ep", episode)
    (folder / "arrays.npz").write_bytes(b"not a zip")
    with pytest.raises(EpisodeError, match="unreadable episode"):
        read_episode(folder)
    with pytest.raises(EpisodeError, match="missing episode.json"):
        read_episode(tmp_path / "nothing")
