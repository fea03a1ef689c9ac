"""The LeRobot exporter: two recorded episodes written through lerobot's own writer (format v3.0) and
read back with ``LeRobotDataset(repo_id, root=...)`` offline; without lerobot, one clear error.

The round trip needs the exporters (`make install-exporters`) and is skipped without them; the
missing-exporter test runs everywhere."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # read back from the local folder only, never the Hub

from scenegen.core.files import sha256_file  # noqa: E402
from scenegen.env.episodes import EpisodeRecorder, write_episode  # noqa: E402
from scenegen.env.scenes import batch_scenes  # noqa: E402
from scenegen.export.lerobot import ExporterMissing, export_lerobot, task_string  # noqa: E402

# The round trip needs lerobot; skipped at collection where it is missing (before any episode is made).
needs_lerobot = pytest.mark.skipif(
    importlib.util.find_spec("lerobot") is None,
    reason="the LeRobot exporter is not installed (make install-exporters)",
)
STEPS, EVERY = 12, 4  # 12 control steps per episode, a decision every 4 (LeRobot fps = 20 / 4 = 5)


@pytest.fixture(scope="module")
def episode_folders(demo_batch: Path, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two scripted episodes on two scenes of the demo batch, a 32x24 front camera; the second ends
    with an observation no action followed (a decision the exporter leaves out)."""
    from scenegen.env.robosuite_env import SceneEnv

    scenes = batch_scenes(demo_batch)[:2]
    root = tmp_path_factory.mktemp("episodes")
    env = SceneEnv(scenes[0], cameras=["front"], camera_size=(32, 24))
    folders = []
    try:
        for n, scene in enumerate(scenes):
            obs = env.reset_to(scene)
            recorder = EpisodeRecorder(env, f"scripted_{n}", observation_kind="rgbd", trace_every=EVERY)
            for step in range(STEPS):
                if step % EVERY == 0:
                    recorder.decide(obs, {"action": [0.5, 0, 0]})
                sign = 1.0 if n == 0 else -1.0
                obs, _, _ = recorder.step([sign * 0.5, 0.1 * step, -0.2, 0, 0, 0.05 * n, -1.0])
            if n == 1:
                recorder.decide(obs, {"action": [0, 0, 0]})  # the final observation: no action follows
            episode = recorder.finish(success=n == 0, note=f"scripted {n}")
            folders.append(write_episode(root / f"ep{n}", episode))
    finally:
        env.close()
    return folders


@pytest.fixture(scope="module")
def exported(episode_folders: list[Path], tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("lerobot") / "dataset"
    summary = export_lerobot(episode_folders, out, repo_id="scenegen/test")
    return out, summary


def _back(out: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # loaded by export_lerobot already

    return LeRobotDataset("scenegen/test", root=out)


@needs_lerobot
def test_the_export_is_a_v3_dataset_with_one_frame_per_decision(exported, episode_folders):
    out, summary = exported
    assert summary["episodes"] == 2 and summary["frames"] == 6 and summary["dropped_decisions"] == 1
    assert summary["format_version"] == "v3.0" and summary["fps"] == 5 and summary["path"] == str(out)
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 5
    assert info["features"]["observation.images.front"]["dtype"] == "image"
    assert not list(out.parent.glob(".dataset.*"))  # the temporary folder is gone
    back = _back(out)
    assert back.num_episodes == 2 and back.num_frames == 6
    assert [back.meta.episodes[i]["length"] for i in range(2)] == [3, 3]


@needs_lerobot
def test_values_round_trip(exported, episode_folders):
    from scenegen.env.episodes import read_episode

    out, _ = exported
    back = _back(out)
    index = 0
    for n, folder in enumerate(episode_folders):
        episode = read_episode(folder)
        actions = np.asarray(episode.actions, dtype=np.float32)
        kept = [d for d in episode.decisions if d.step < episode.length]
        assert len(kept) == 3 and len(episode.decisions) == 3 + n
        for i, decision in enumerate(kept):
            item = back[index]
            index += 1
            assert int(item["episode_index"]) == n and int(item["frame_index"]) == i
            assert item["action"].dtype.is_floating_point and item["action"].numpy().dtype == np.float32
            np.testing.assert_array_equal(item["action"].numpy(), actions[decision.step])
            state = np.concatenate(
                [decision.observation["robot0_joint_pos"], decision.observation["robot0_gripper_qpos"]]
            ).astype(np.float32)
            np.testing.assert_array_equal(item["observation.state"].numpy(), state)
            row = decision.step // EVERY  # decisions fall on trace rows here: the same state
            trace_row = np.concatenate([episode.trace["robot_qpos"][row], episode.trace["gripper_qpos"][row]])
            np.testing.assert_allclose(item["observation.state"].numpy(), trace_row, atol=1e-6)
            image = (item["observation.images.front"].numpy().transpose(1, 2, 0) * 255).round()
            np.testing.assert_array_equal(image.astype(np.uint8), decision.observation["front_image"])
            assert int(item["decision.step"]) == decision.step and int(item["decision.num_steps"]) == EVERY
            last = i == len(kept) - 1
            assert bool(item["next.done"]) == last and bool(item["next.success"]) == (last and n == 0)
            np.testing.assert_allclose(
                float(item["next.reward"]), sum(episode.rewards[decision.step :][:EVERY])
            )
            assert item["task"] == task_string(episode)
    assert index == len(back)


@needs_lerobot
def test_episode_metadata_is_kept(exported, episode_folders):
    out, _ = exported
    back = _back(out)
    lines = [json.loads(line) for line in (out / "meta" / "scenegen_episodes.jsonl").read_text().splitlines()]
    assert [r["episode_index"] for r in lines] == [0, 1]
    assert [r["episode_id"] for r in lines] == ["scripted_0", "scripted_1"]
    assert [r["success"] for r in lines] == [True, False]
    assert lines[1]["info"] == {"note": "scripted 1"} and lines[1]["dropped_decisions"] == 1
    for record in lines:
        scene = record["scene"]
        assert scene["scene_id"] and scene["source"] and scene["target"]
        task = f"scene {scene['scene_id']} from {scene['source']}, target {scene['target']}"
        assert back.meta.episodes[record["episode_index"]]["tasks"] == [task]
        assert task in back.meta.tasks.index
    described = json.loads((out / "meta" / "scenegen_export.json").read_text())
    assert described["counts"] == {"episodes": 2, "frames": 6} and described["format_version"] == "v3.0"
    assert [s["arrays.npz"] for s in described["source"]] == [
        sha256_file(f / "arrays.npz") for f in episode_folders
    ]


@needs_lerobot
def test_an_existing_output_is_refused(exported, episode_folders):
    out, _ = exported
    with pytest.raises(FileExistsError, match="exists"):
        export_lerobot(episode_folders, out)


def test_without_lerobot_the_error_names_the_install_target(monkeypatch, tmp_path: Path):
    monkeypatch.setitem(sys.modules, "lerobot", None)  # `import lerobot` now fails, as when not installed
    with pytest.raises(ExporterMissing, match="make install-exporters"):
        export_lerobot([tmp_path / "no_episode"], tmp_path / "out")
    assert not (tmp_path / "out").exists() and isinstance(ExporterMissing("x"), RuntimeError)


@needs_lerobot
def test_the_cli_exports_a_folder_of_episodes(episode_folders, tmp_path: Path, capsys):
    from scenegen.cli import main

    out = tmp_path / "dataset"
    assert main(["export", str(episode_folders[0].parent), "--format", "lerobot", "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith("2 episodes, 6 frames")
    assert json.loads((out / "meta" / "info.json").read_text())["codebase_version"] == "v3.0"
    assert main(["export", str(tmp_path / "none"), "--format", "lerobot", "--out", str(out)]) == 2
    assert "no episode folders" in capsys.readouterr().err
