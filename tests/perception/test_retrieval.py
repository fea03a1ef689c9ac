"""The retrieval head at a tiny size: frames rendered once and cached by content, labels from the
segmentation, a real training run (deterministic, resumable), the metrics on hand-made masks, and
the commands end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenegen.env.scenes import batch_scenes, target_category
from scenegen.perception.retrieval.evaluate import Prediction, image_metrics
from scenegen.perception.retrieval.frames import FrameCache, frames_key, scene_frames
from scenegen.perception.retrieval.train import half, retrieval_data, train_head

CATEGORIES = ["bottle", "bowl", "box", "can", "fork", "knife", "mug", "plate", "spoon"]


@pytest.fixture(scope="module")
def scenes(demo_batch: Path):
    return batch_scenes(demo_batch)


@pytest.fixture(scope="module")
def cache(scenes, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    list(scene_frames(scenes, folder))
    return folder


def test_frames_are_rendered_once_and_read_back_from_the_cache(scenes, cache: Path):
    files = sorted(cache.rglob("*.npz"))
    assert len(files) == len(scenes)
    stamps = [f.stat().st_mtime_ns for f in files]
    frames = list(scene_frames(scenes, cache))
    assert [f.stat().st_mtime_ns for f in files] == stamps  # nothing rendered again
    first = frames[0]
    assert first.cameras == ("front", "side") and first.rgb.shape == (2, 240, 320, 3)
    assert first.depth.dtype == np.float32 and 0.3 < np.median(first.depth[first.depth > 0]) < 5.0
    assert FrameCache(cache).path(frames_key(scenes[0])).exists()


def test_labels_put_every_object_under_its_category(scenes, cache: Path):
    data = retrieval_data(scenes, scene_frames(scenes, cache), CATEGORIES)
    assert data.labels.shape == (len(scenes), 2, 120, 160)
    for scene, frames, labels in zip(scenes, scene_frames(scenes, cache), data.labels, strict=True):
        target = CATEGORIES.index(target_category(scene)) + 1
        seen = (frames.seg == scene.target_id).sum(axis=(1, 2))
        for camera in np.nonzero(seen >= 20)[0]:
            assert (labels[camera] == target).sum() > 0
        table = scene.segmentation["table"]
        assert (
            half(np.where(frames.seg == table, 1, 0)) * labels > 0
        ).sum() < labels.size  # table is not an object


def test_a_tiny_training_lowers_its_loss_is_deterministic_and_resumes(scenes, cache: Path, tmp_path: Path):
    data = retrieval_data(scenes, scene_frames(scenes, cache), CATEGORIES)
    summary = train_head(data, tmp_path / "a", steps=30, batch_size=2, seed=3)
    losses = summary["losses"]
    assert np.mean(losses[-5:]) < 0.85 * np.mean(losses[:5])
    assert summary["effective_shares"] == {"batch": 1.0}
    assert train_head(data, tmp_path / "b", steps=30, batch_size=2, seed=3)["losses"] == losses
    assert train_head(data, tmp_path / "c", steps=30, batch_size=2, seed=3, stop_after=12) is None
    assert (tmp_path / "c" / "_resume" / "state.json").exists() and not (
        tmp_path / "c" / "config.json"
    ).exists()
    resumed = train_head(data, tmp_path / "c", steps=30, batch_size=2, seed=3)
    assert resumed["losses"] == losses and not (tmp_path / "c" / "_resume").exists()
    same = (tmp_path / "a" / "model.safetensors").read_bytes() == (
        tmp_path / "c" / "model.safetensors"
    ).read_bytes()
    assert same


def test_the_metrics_on_hand_made_masks():
    seg = np.zeros((20, 30), np.int32)
    seg[5:10, 5:10] = 7  # the target
    seg[5:10, 20:25] = 8  # another object
    on_target = np.zeros_like(seg, bool)
    on_target[6:10, 5:9] = True
    m = image_metrics(Prediction(on_target, 1.0), seg, 7, [7, 8])
    assert m["hit"] and not m["wrong_object"] and m["iou"] == pytest.approx(16 / 25)
    on_other = np.zeros_like(seg, bool)
    on_other[5:10, 19:25] = True
    m = image_metrics(Prediction(on_other, 1.0), seg, 7, [7, 8])
    assert not m["hit"] and m["wrong_object"] and m["iou"] == 0.0
    m = image_metrics(Prediction(np.zeros_like(seg, bool), 0.0), seg, 7, [7, 8])
    assert m["miss"] and not m["predicted"]
    m = image_metrics(Prediction(on_other, 1.0), np.where(seg == 7, 0, seg), 7, [7, 8])
    assert m["false_alarm"] and not m["visible"]


@pytest.mark.parametrize(
    ("design", "kind"), [("candidates", "candidate_classifier"), ("segmenter", "retrieval_head")]
)
def test_train_and_eval_commands_end_to_end(demo_batch: Path, cache: Path, tmp_path: Path, design, kind):
    from scenegen.cli import main

    out = tmp_path / "head"
    common = ["--cache", str(cache), "--quiet"]
    assert main(["retrieval", "train", "--data", str(demo_batch), "--out", str(out), "--steps", "8",
                 "--batch-size", "2", "--split", "all", "--design", design, "--device", "cpu",
                 *common]) == 0  # fmt: skip
    config = json.loads((out / "config.json").read_text())
    assert config["kind"] == kind and config["training"]["steps"] == 8
    assert config["training"]["data"]["sources"][0]["path"] == str(demo_batch)
    report = tmp_path / "eval"
    assert main(["retrieval", "eval", "--checkpoint", str(out), "--scenes", str(demo_batch), "--split",
                 "all", "--out", str(report), *common]) == 0  # fmt: skip
    summary = json.loads((report / "summary.json").read_text())
    assert summary["all"]["scenes"] == 6 and summary["per_tag"]
    assert len((report / "images.jsonl").read_text().splitlines()) == 6


def test_a_folder_that_is_no_retrieval_checkpoint_is_a_one_line_error(
    demo_batch: Path, tmp_path: Path, capsys
):
    from scenegen.cli import main

    code = main(["retrieval", "eval", "--checkpoint", str(tmp_path), "--scenes", str(demo_batch), "--out",
                 str(tmp_path / "x")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "config.json" in err
    assert not (tmp_path / "x").exists()


def test_the_candidate_design_finds_objects_in_depth_and_names_them(scenes, cache: Path, tmp_path: Path):
    """Design (b), measured against the segmenter (benchmarks/retrieval_designs.py): depth regions
    above the table cover most of the visible objects' pixels (how well they split into instances is
    the benchmark's to measure); a tiny classifier trains and picks a region per camera."""
    from scenegen.perception.retrieval.candidates import (
        CandidatePicker,
        frame_candidates,
        robot_pixels,
        train_classifier,
    )

    frames = list(scene_frames(scenes, cache))
    covered = visible = 0
    for scene, f in zip(scenes, frames, strict=True):
        regions = frame_candidates(f, scene.cameras, robot_pixels(f, scene))
        for obj in scene.objects:
            for k in range(len(f.cameras)):
                mask = f.seg[k] == scene.segmentation[obj.name]
                if mask.sum() >= 50:
                    visible += 1
                    union = np.any([region for j, region, _ in regions if j == k] or [mask & False], axis=0)
                    covered += (union & mask).sum() > 0.5 * mask.sum()
    assert visible and covered >= 0.8 * visible
    summary = train_classifier(scenes, frames, CATEGORIES, tmp_path / "b", steps=40)
    assert summary["candidates"] > 0 and summary["losses"][-1] < summary["losses"][0]
    robot = robot_pixels(frames[0], scenes[0])
    predictions = CandidatePicker(tmp_path / "b").predict(
        frames[0], scenes[0].cameras, target_category(scenes[0]), robot
    )
    assert len(predictions) == 2 and all(p.mask.shape == (240, 320) for p in predictions)


def test_a_candidate_checkpoint_whose_weights_do_not_load_is_a_one_line_error(tmp_path: Path):
    from scenegen.core.files import CheckpointError
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    root = Path(__file__).resolve().parents[2] / "assets" / "retrieval" / "baseline"
    (tmp_path / "config.json").write_bytes((root / "config.json").read_bytes())
    (tmp_path / "model.safetensors").write_bytes(b"not weights")
    with pytest.raises(CheckpointError, match="model.safetensors: does not load"):
        RetrievalPerception.load(tmp_path)


def test_a_category_the_committed_head_does_not_know_is_a_one_line_error():
    from scenegen.paths import ASSETS_DIR
    from scenegen.perception.retrieval.candidates import CandidatePicker

    picker = CandidatePicker(ASSETS_DIR / "retrieval" / "baseline")
    with pytest.raises(ValueError, match="'grocery': this retrieval head knows .*scenegen retrieval train"):
        picker.predict(None, None, "grocery", None)  # refused before any frame is read
