"""The baseline policy: a tiny training run on real rendered observations lowers its loss, the
checkpoint round-trips through safetensors, and closed-loop evaluation writes episode records with
failure labels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from scenegen.env.scenes import batch_scenes
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.policy.network import PrimitivePolicy


@pytest.fixture(scope="module")
def examples(demo_batch: Path):
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.policy.train import CAMERA, CAMERA_SIZE, Examples, render_observation

    scenes = batch_scenes(demo_batch)
    env = SceneEnv(scenes[0], cameras=[CAMERA], camera_size=CAMERA_SIZE, render_each_step=False)
    try:
        x = np.stack([render_observation(env, s) for s in scenes])
    finally:
        env.close()
    primitives = list(PRIMITIVES)
    # hand-made labels that depend on what the camera sees: top_grasp succeeds on the scenes whose
    # target covers the most pixels, side_grasp on the others
    pixels = x[:, 4].sum(axis=(1, 2))
    big = pixels > np.median(pixels)
    y = np.zeros((len(scenes), len(primitives)), np.float32)
    y[:, primitives.index("top_grasp")] = big
    y[:, primitives.index("side_grasp")] = ~big
    return Examples(x, y, np.ones_like(y, dtype=bool), scenes, primitives)


def test_observations_hold_rgb_depth_and_the_target_mask(examples):
    assert examples.x.shape[1:] == (5, 72, 96) and examples.x.dtype == np.float32
    assert examples.x[:, :3].max() <= 1.0
    seen = examples.x[:, 4].sum(axis=(1, 2)) > 0
    assert seen.sum() >= len(seen) - 2  # the target is in view (it may be hidden: occluded scenes)


def test_a_tiny_training_lowers_its_loss_and_the_checkpoint_round_trips(examples, tmp_path: Path):
    from scenegen.policy.train import train_policy

    summary = train_policy(examples, tmp_path / "ckpt", steps=150, batch_size=6, seed=0)
    losses = summary["losses"]
    assert np.mean(losses[-20:]) < 0.5 * np.mean(losses[:20])
    assert summary["effective_shares"] == {"batch": 1.0}
    model = PrimitivePolicy.load(tmp_path / "ckpt")
    config = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    assert config["primitives"] == list(PRIMITIVES) and config["training"]["steps"] == 150
    with torch.no_grad():
        logits = model(torch.from_numpy(examples.x))
    assert torch.isfinite(logits).all() and model.choose(torch.from_numpy(examples.x[0])) in PRIMITIVES
    again = train_policy(examples, tmp_path / "again", steps=150, batch_size=6, seed=0)
    assert again["losses"] == losses  # same seed, same run


def test_a_closed_loop_evaluation_writes_episodes_with_failure_labels(examples, demo_batch, tmp_path: Path):
    from scenegen.env.episodes import read_episode
    from scenegen.policy.evaluate import evaluate

    PrimitivePolicy(list(PRIMITIVES)).eval().save(tmp_path / "untrained")
    summary = evaluate(tmp_path / "untrained", batch_scenes(demo_batch)[:1], tmp_path / "episodes")
    assert summary["episodes"] == 1 and 0.0 <= summary["success_rate"] <= 1.0
    (folder,) = [p for p in (tmp_path / "episodes").iterdir() if p.is_dir()]
    episode = read_episode(folder)
    assert episode.decisions and episode.decisions[0].choice["primitive"] in PRIMITIVES
    assert len(episode.trace["time"]) > 2
    assert episode.info["failure"] == ("" if episode.success else episode.info["failure"])
    assert episode.success or episode.info["failure"] in summary["failures"]


def test_a_missing_checkpoint_is_named(tmp_path: Path):
    with pytest.raises(ValueError, match="not a policy checkpoint"):
        PrimitivePolicy.load(tmp_path)


def test_only_labels_of_the_current_primitives_seen_through_the_cameras_train_it(demo_batch, tmp_path: Path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from scenegen.policy.labels import scene_sha256
    from scenegen.policy.train import current, labelled_examples

    sha = scene_sha256(batch_scenes(demo_batch)[0])
    from scenegen.env.physics import DEFAULT_PHYSICS, PHYSICS

    row = {
        "scene_sha256": sha,
        "primitive": "top_grasp",
        "success": True,
        "observation": "rgbd",
        "duration": 9.0,
        "physics": PHYSICS[DEFAULT_PHYSICS].key(),
    }
    version = PRIMITIVES["top_grasp"].version
    rows = [
        row | {"primitive_version": version - 1},
        row | {"primitive_version": version, "observation": "state"},
        row | {"primitive_version": version, "duration": 50.0},  # a success the time limit cannot judge
        row | {"primitive_version": version, "physics": PHYSICS["exact"].key()},  # another physics
    ]
    assert not any(map(current, rows)) and current(row | {"primitive_version": version})
    pq.write_table(pa.Table.from_pylist(rows), tmp_path / "stale.parquet")
    with pytest.raises(
        ValueError, match="4 rows of older primitive versions, another observation or physics, or an unjudged"
    ):
        labelled_examples([(demo_batch, tmp_path / "stale.parquet")], split=None)


def test_the_checkpoint_records_its_coverage_for_the_failure_labeller(examples, tmp_path: Path):
    from scenegen.policy.evaluate import evaluate
    from scenegen.policy.train import coverage, train_policy

    counts = coverage(examples)
    assert sum(counts.values()) >= len(examples.scenes)  # a scene counts once per tag it holds
    train_policy(examples, tmp_path / "ckpt", steps=2, batch_size=2)
    loaded = PrimitivePolicy.load(tmp_path / "ckpt").trained_on["coverage"]
    assert {(tag, category): n for tag, category, n in loaded} == counts
    PrimitivePolicy(["top_grasp", "teleport"]).save(tmp_path / "other")
    with pytest.raises(ValueError, match="chooses primitives this code lacks \\(teleport\\)"):
        evaluate(tmp_path / "other", examples.scenes[:1], tmp_path / "episodes")


def test_label_train_and_eval_run_end_to_end_from_the_command_line(demo_batch, tmp_path: Path, capsys):
    from scenegen.cli import main
    from scenegen.env.episodes import read_episode

    labels, ckpt, episodes = tmp_path / "labels.parquet", tmp_path / "ckpt", tmp_path / "episodes"
    argv = ["label", str(demo_batch), "--out", str(labels), "--limit", "2", "--quiet"]
    assert main([*argv, "--primitives", "top_grasp", "toppled_grasp"]) == 0
    argv = ["policy", "train", "--data", str(demo_batch), str(labels), "--out", str(ckpt)]
    assert main([*argv, "--steps", "5", "--batch-size", "2"]) == 0
    assert "2 examples, 5 steps" in capsys.readouterr().out
    argv = ["policy", "eval", "--checkpoint", str(ckpt), "--scenes", str(demo_batch), "--split", "all"]
    assert main([*argv, "--n", "1", "--labels", str(labels), "--out", str(episodes), "--quiet"]) == 0
    summary = json.loads((episodes / "summary.json").read_text())
    (folder,) = [p for p in episodes.iterdir() if p.is_dir()]
    episode = read_episode(folder)
    assert summary["episodes"] == 1 and summary["success_rate"] == float(episode.success)
    assert 1 <= episode.info["attempts"] <= 3 and (episode.success or episode.info["failure"])
    argv = [
        "policy",
        "eval",
        "--checkpoint",
        str(tmp_path),
        "--scenes",
        str(demo_batch),
        "--out",
        str(episodes),
    ]
    assert main(argv) == 2 and "not a policy checkpoint" in capsys.readouterr().err


def test_the_committed_baseline_loads_and_names_the_labels_it_learnt_from():
    from scenegen.core.files import sha256_file

    policy = PrimitivePolicy.load(Path("assets/policy/baseline"))
    assert set(policy.primitives) <= set(PRIMITIVES)
    (source,) = policy.trained_on["data"]["sources"]
    assert sha256_file(Path(source["labels"])) == source["labels_sha256"]
    assert policy.trained_on["examples"] == 282 and policy.trained_on["stale_label_rows"] == 0
