"""The instances design (issue 43): boundary labels from instance ids and heights, regions grown from
predicted interiors, a real tiny training of both networks, its checkpoint read safely; the overlap
rule of scoring and its version in the closed loop's keys."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenegen.env.scenes import batch_scenes, target_category
from scenegen.perception.retrieval.evaluate import Prediction, image_metrics, perception_missed
from scenegen.perception.retrieval.frames import scene_frames
from scenegen.perception.retrieval.separation import grow_regions, interior_labels

CATEGORIES = ["bottle", "bowl", "box", "can", "fork", "knife", "mug", "plate", "spoon"]


def _knife_on_plate():
    """A 40 x 60 frame: a plate (instance 1, 1 cm high) with a knife 3 px wide lying on it (instance
    2, 1.3 cm), and a mug standing apart (instance 3), on the table (not foreground)."""
    seg = np.zeros((40, 60), np.int32)
    height = np.zeros((40, 60))
    seg[5:35, 5:35], height[5:35, 5:35] = 1, 0.010
    seg[10:30, 18:21], height[10:30, 18:21] = 2, 0.013
    seg[10:20, 45:55], height[10:20, 45:55] = 3, 0.05
    return seg, seg > 0, height


def test_the_boundary_band_lies_on_the_lower_object_so_a_thin_object_keeps_its_interior():
    seg, keep, height = _knife_on_plate()
    labels = interior_labels(seg, keep, height, band=2)
    assert (labels[~keep] == -1).all()
    assert (labels[seg == 2] == 1).all()  # the knife, three pixels wide, is all interior
    assert (labels[seg == 3] == 1).all()  # nothing touches the mug: no band
    plate_band = (seg == 1) & (labels == 0)
    rows, cols = np.nonzero(plate_band)
    assert plate_band.sum() == (24 * 7 - 20 * 3) and cols.min() == 16 and cols.max() == 22
    assert rows.min() == 8 and rows.max() == 31


def test_the_contact_channels_say_how_high_the_step_and_which_side_stands_proud():
    from scenegen.perception.retrieval.separation import CHANNELS, STEP, separator_input

    seg, keep, height = _knife_on_plate()
    rgb = np.full((*seg.shape, 3), 128, np.uint8)
    depth = 1.0 - height
    x = separator_input(rgb, depth, keep, height)
    assert x.shape == (CHANNELS, 40, 60) == (9, 40, 60)
    assert np.array_equal(separator_input(rgb, depth, keep, height, 7), x[:7])  # the saved heads' input
    with pytest.raises(ValueError, match="separator channels 8: 7 or 9"):
        separator_input(rgb, depth, keep, height, 8)
    step, proud = x[7], x[8]
    knife, band = seg == 2, (seg == 1) & (interior_labels(seg, keep, height) == 0)
    beside = band & ((np.roll(knife, 1, 1)) | np.roll(knife, -1, 1))  # plate pixels touching the knife
    assert np.allclose(step[knife & np.roll(beside, 1, 1)], 0.003 / STEP)  # the knife's edge: 3 mm
    assert np.allclose(step[beside], 0.003 / STEP)  # and the plate's pixel beside it
    assert np.allclose(proud[knife], 0.003 / STEP)  # three pixels wide, all of it stands proud
    assert np.allclose(proud[seg == 1], 0.0, atol=1e-5)  # the plate under it nowhere does
    assert proud[~keep].max() == 0


def test_a_separator_saved_before_the_contact_channels_loads_with_its_seven(tmp_path: Path):
    from scenegen.core.files import CheckpointError
    from scenegen.paths import ASSETS_DIR
    from scenegen.perception.retrieval.candidates import CandidatePicker

    old = ASSETS_DIR / "retrieval" / "instances_v1"  # issue 43's first head: no "channels" key
    assert "channels" not in json.loads((old / "config.json").read_text())["separator"]
    assert CandidatePicker(old).split.model.channels == 7
    for name in ("model.safetensors", "separator.safetensors"):
        (tmp_path / name).write_bytes((old / name).read_bytes())
    config = json.loads((old / "config.json").read_text())
    for wrong in (8, 9.0, True):
        config["separator"]["channels"] = wrong
        (tmp_path / "config.json").write_text(json.dumps(config))
        with pytest.raises(CheckpointError, match=f"separator channels {wrong!r}: 7 or 9") as caught:
            CandidatePicker(tmp_path)
        assert len(str(caught.value).splitlines()) == 1


def test_regions_grown_from_the_true_interiors_are_the_instances():
    seg, keep, height = _knife_on_plate()
    interior = interior_labels(seg, keep, height) == 1
    regions = grow_regions(interior, keep, height)
    found = sorted((int(seg[r][0]), int(r.sum())) for r in regions)
    assert found == [(1, int((seg == 1).sum())), (2, 60), (3, 100)]  # the band went back to the plate
    for region in regions:
        assert len(np.unique(seg[region])) == 1


def test_the_overlap_rule_counts_a_mask_that_holds_the_base_as_missed():
    seg, _, _ = _knife_on_plate()
    ids = [1, 2, 3]
    knife_and_plate = Prediction((seg == 1) | (seg == 2), 1.0)
    merged = image_metrics(knife_and_plate, seg, 2, ids)
    assert merged["hit"] and not merged["iou_hit"]  # its centre lies on the knife, IoU 60 / 900
    own = image_metrics(Prediction(seg == 2, 1.0), seg, 2, ids)
    assert own["iou_hit"] and own["iou"] == 1.0
    unseen = np.zeros_like(seg)
    assert image_metrics(Prediction(unseen > 0, 0.0), unseen, 2, ids)["iou_hit"]  # nothing where nothing is
    assert not image_metrics(Prediction(seg == 3, 1.0), unseen, 2, ids)["iou_hit"]  # a false alarm
    scored = {"hit": True, "hit_iou": False, "wrong_object": False}
    assert not perception_missed(scored, 1) and perception_missed(scored, 2)
    with pytest.raises(ValueError, match="perception rules 3"):
        perception_missed(scored, 3)


@pytest.fixture(scope="module")
def tiny_head(demo_batch: Path, tmp_path_factory):
    from scenegen.perception.retrieval.candidates import train_instances

    scenes = batch_scenes(demo_batch)
    frames = list(scene_frames(scenes, tmp_path_factory.mktemp("frames")))
    out = tmp_path_factory.mktemp("heads") / "instances"
    summary = train_instances(scenes, frames, CATEGORIES, out, steps=30, seed=0, separator_steps=40)
    return scenes, frames, out, summary


def test_a_tiny_instances_head_trains_both_networks_and_predicts(tiny_head, tmp_path: Path):
    from scenegen.perception.retrieval.candidates import robot_pixels, train_instances
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    scenes, frames, out, summary = tiny_head
    losses = summary["separator"]["losses"]
    assert len(losses) == 40 and np.mean(losses[-10:]) < np.mean(losses[:10])
    assert summary["candidates"] > 0 and summary["losses"][-1] < summary["losses"][0]
    config = json.loads((out / "config.json").read_text())
    assert config["kind"] == "instances" and config["separator"]["width"] == 8
    assert config["separator"]["channels"] == 9
    assert {p.name for p in out.iterdir()} == {"config.json", "model.safetensors", "separator.safetensors"}
    perception = RetrievalPerception.load(out)
    scene, f = scenes[0], frames[0]
    predictions = perception.predict(f, scene.cameras, target_category(scene), robot_pixels(f, scene))
    assert len(predictions) == 2 and all(p.mask.shape == (240, 320) for p in predictions)
    again = train_instances(
        scenes, frames, CATEGORIES, tmp_path / "again", steps=30, seed=0, separator_steps=40
    )
    assert again["losses"] == summary["losses"]  # a function of its seed
    for name in ("separator.safetensors", "model.safetensors"):
        assert (tmp_path / "again" / name).read_bytes() == (out / name).read_bytes()


def test_a_head_trained_through_a_sensor_keeps_its_depth_rule_and_mends_what_it_is_shown(
    demo_batch: Path, tmp_path: Path
):
    from scenegen.core.files import CheckpointError
    from scenegen.perception.retrieval.candidates import CandidatePicker, robot_pixels, train_instances
    from scenegen.perception.retrieval.regions import DEPTH_RULES, foreground

    scenes = batch_scenes(demo_batch)[:3]
    frames = list(scene_frames(scenes, tmp_path / "frames", sensor="active_stereo"))
    assert all((f.depth == 0).any() for f in frames)  # the sensor leaves pixels without depth
    rule, out = DEPTH_RULES["mended_5mm"], tmp_path / "head"
    train_instances(scenes, frames, CATEGORIES, out, steps=20, seed=0, separator_steps=20, rule=rule)
    assert json.loads((out / "config.json").read_text())["depth_rule"] == rule.config()
    picker = CandidatePicker(out)
    assert picker.rule == rule and picker.split.rule == rule
    shown = []
    split = picker.split
    picker.split = lambda rgb, depth, robot, camera: shown.append(depth) or split(rgb, depth, robot, camera)
    scene, f = scenes[0], frames[0]
    robot = robot_pixels(f, scene)
    picker.predict(f, scene.cameras, target_category(scene), robot)
    assert len(shown) == 2
    assert all(np.array_equal(d, rule.mend(raw)) for d, raw in zip(shown, f.depth, strict=True))
    cameras = {c.name: c for c in scene.cameras}
    for k, name in enumerate(f.cameras):  # what the rule is for: the table's noise is no object
        table = f.seg[k] == scene.segmentation["table"]
        raw, _ = foreground(f.depth[k], robot[k], cameras[name])
        mended, _ = rule.foreground(shown[k], robot[k], cameras[name])
        assert (raw & table).sum() > 1000 and (mended & table).sum() < 0.25 * (raw & table).sum()
    config = json.loads((out / "config.json").read_text())
    assert "outputs" not in config["separator"]  # a threshold rule: the separator's one map
    (out / "config.json").write_text(json.dumps(config | {"depth_rule": {"median": 4}}))
    with pytest.raises(
        CheckpointError, match=r"config.json: depth_rule median 4: .*retrieval train"
    ) as caught:
        CandidatePicker(out)
    assert len(str(caught.value).splitlines()) == 1


def test_a_learned_foreground_labels_objects_against_the_table_and_maps_them(
    demo_batch: Path, tmp_path: Path
):
    from scenegen.core.files import CheckpointError
    from scenegen.perception.observation import BACKGROUND
    from scenegen.perception.retrieval.candidates import CandidatePicker, robot_pixels, train_instances
    from scenegen.perception.retrieval.regions import DEPTH_RULES
    from scenegen.perception.retrieval.separation import separator_frames

    scenes = batch_scenes(demo_batch)[:2]
    rule = DEPTH_RULES["learned"]
    frames = [rule.mend_frames(f) for f in scene_frames(scenes, tmp_path / "frames", sensor="active_stereo")]
    inputs, labels, _, _, objects = separator_frames(scenes, frames, rule=rule)
    assert len(objects) == len(labels) == 4
    for k, (scene, f) in enumerate((s, f) for s, f in zip(scenes, frames, strict=True) for _ in range(2)):
        seg = f.seg[k % 2]
        background = np.isin(seg, [scene.segmentation[n] for n in BACKGROUND])
        table = seg == scene.segmentation["table"]
        assert (objects[k][table] <= 0).all() and (objects[k][table] == 0).mean() > 0.9  # the table: 0
        assert (objects[k][~background] >= 0).mean() > 0.9  # objects on the table: scored ...
        assert ((objects[k] == 1) == ((objects[k] >= 0) & ~background)).all()  # ... as objects
        assert ((labels[k] >= 0) == (objects[k] == 1)).all()  # interiors and boundaries: objects only
        assert inputs[k][7].any()  # the height channels see the whole table
    out = tmp_path / "learned"
    with pytest.raises(ValueError, match="no candidate region in the 2 training scenes' frames"):
        train_instances(scenes, frames, CATEGORIES, out, steps=10, seed=0, separator_steps=1, rule=rule)
    train_instances(scenes, frames, CATEGORIES, out, steps=10, seed=0, separator_steps=100, rule=rule)
    config = json.loads((out / "config.json").read_text())
    assert config["separator"]["outputs"] == 2 and config["depth_rule"]["learned"] is True
    picker = CandidatePicker(out)
    assert picker.split.model.outputs == 2
    scene, f = scenes[0], frames[0]
    robot = robot_pixels(f, scene)
    camera = {c.name: c for c in scene.cameras}[f.cameras[0]]
    field, height = rule.foreground(f.depth[0], robot[0], camera)
    interior, keep = picker.split.interior(f.rgb[0], f.depth[0], field, height)
    assert not (keep & ~field).any() and not (interior & ~keep).any()  # the object map lies on the table
    config["separator"]["outputs"] = 3
    (out / "config.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="separator outputs 3: 1 or 2") as caught:
        CandidatePicker(out)
    assert len(str(caught.value).splitlines()) == 1


def test_an_instances_checkpoint_without_its_separator_is_a_one_line_error(tiny_head, tmp_path: Path):
    from scenegen.core.files import CheckpointError
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    _, _, out, _ = tiny_head
    for name in ("config.json", "model.safetensors"):
        (tmp_path / name).write_bytes((out / name).read_bytes())
    with pytest.raises(CheckpointError, match="separator.safetensors: does not load") as caught:
        RetrievalPerception.load(tmp_path)
    assert len(str(caught.value).splitlines()) == 1


def test_a_head_is_its_whole_folder_and_the_rules_version_keys_its_observations(tiny_head, tmp_path: Path):
    from scenegen.experiment.sequences import NOMINAL, sight

    _, _, out, _ = tiny_head
    copy = tmp_path / "head"
    copy.mkdir()
    for item in out.iterdir():
        (copy / item.name).write_bytes(item.read_bytes())
    before = {rules: sight(copy, NOMINAL, rules) for rules in (1, 2)}
    assert before[2].endswith("|perception2") and before[1] != before[2]
    assert sight(copy, NOMINAL) == before[2] and sight(None, NOMINAL) == "oracle"
    weights = bytearray((copy / "separator.safetensors").read_bytes())
    weights[-1] ^= 1  # another separator, the same classifier
    (copy / "separator.safetensors").write_bytes(bytes(weights))
    assert sight(copy, NOMINAL, 2) != before[2] and sight(copy, NOMINAL, 1) != before[1]
    from scenegen.core.files import sha256_file
    from scenegen.paths import ASSETS_DIR

    old = ASSETS_DIR / "retrieval" / "baseline"  # issue 33's head keeps its version 1 key of then
    assert sight(old, NOMINAL, 1) == f"retrieval:{sha256_file(old / 'model.safetensors')[:16]}@nominal:1.0"


def test_the_separators_default_steps_follow_the_depth_rule():
    """3,000 on exact depth (the committed heads' bytes); 12,000 under the learned rule, whose
    separator also learns the object map (the pilot that chose it: docs/sensor.md)."""
    from scenegen.cli import main
    from scenegen.perception.retrieval.candidates import default_separator_steps
    from scenegen.perception.retrieval.regions import DEPTH_RULES, SENSOR_RULE
    from scenegen.perception.retrieval.separation import LEARNED_RULE_STEPS, SEPARATOR_STEPS

    assert default_separator_steps(DEPTH_RULES["exact"]) == SEPARATOR_STEPS == 3000
    assert default_separator_steps(DEPTH_RULES["mended_5mm"]) == SEPARATOR_STEPS
    assert default_separator_steps(DEPTH_RULES[SENSOR_RULE]) == LEARNED_RULE_STEPS == 12000
    assert main(["retrieval", "train", "--data", "x", "--out", "y", "--separator-steps", "0"]) == 2
