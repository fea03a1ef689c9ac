"""The proposal model (issue 63, point 3): the oriented crop a candidate is seen through, and a real
training run at a small size that learns what lifts and what does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.core.files import CheckpointError
from scenegen.core.rotations import camera_rotation
from scenegen.manipulation.proposals import Candidate
from scenegen.perception.observation import TargetView
from scenegen.perception.points import estimate_target, masked_points
from scenegen.policy.proposal_model import (
    CHANNELS,
    CROP,
    FEATURES,
    MODEL_VERSION,
    ProposalModel,
    candidate_crop,
    candidate_features,
    project,
    train_model,
)
from scenegen.schema.scene import Camera

SIZE = (320, 240)
CAMS = {
    "front": Camera(name="front", position=(1.2, 0.0, 1.6), lookat=(0.0, 0.0, 0.8), width=320, height=240),
    "side": Camera(name="side", position=(0.0, 1.2, 1.6), lookat=(0.0, 0.0, 0.8), width=320, height=240),
}


def _table_frames(bar_yaw: float = 0.0):
    """Frames of a flat table (z 0.8) seen by both cameras, with a 16 x 3 cm bar of target mask (and
    red colour) lying at the origin along ``bar_yaw``: depth from the cameras' geometry."""
    frames = {}
    for name, cam in CAMS.items():
        rows, cols = np.mgrid[0:240, 0:320]
        k = cam.intrinsics()
        rays = np.stack(
            [(cols + 0.5 - k["cx"]) / k["fx"], -(rows + 0.5 - k["cy"]) / k["fy"], -np.ones_like(rows)], -1
        )
        world = rays @ camera_rotation(cam.position, cam.lookat).T
        t = (0.8 - cam.position[2]) / world[..., 2]
        hit = np.asarray(cam.position) + world * t[..., None]
        depth = t.astype(np.float32)  # along the optical axis: the ray's z in the camera frame is -1
        along = hit[..., 0] * np.cos(bar_yaw) + hit[..., 1] * np.sin(bar_yaw)
        across = -hit[..., 0] * np.sin(bar_yaw) + hit[..., 1] * np.cos(bar_yaw)
        mask = (np.abs(along) < 0.08) & (np.abs(across) < 0.015)
        image = np.full((240, 320, 3), 200, np.uint8)
        image[mask] = (200, 30, 30)
        frames[name] = (image, depth, mask)
    return frames


def _view(frames) -> TargetView:
    image, depth, mask = frames["front"]
    points = masked_points(depth, mask, CAMS["front"])
    return TargetView(estimate_target(points), np.zeros((0, 3)), target_points=points)


def test_the_features_say_whether_closing_fingers_meet_the_narrow_side():
    """For a 16 x 3 cm bar, whichever way it lies: fingers closing across it meet 3 cm of it and
    straddle 16 (twice the footprint angle: -1); along it, the reverse (+1); a heading and its
    reverse give the same numbers."""
    for yaw in (0.0, np.pi / 3):
        view = _view(_table_frames(bar_yaw=yaw))
        rows = {}
        for name, angle in (("along", yaw), ("across", yaw + np.pi / 2), ("back", yaw + 3 * np.pi / 2)):
            heading = [np.cos(angle), np.sin(angle)]
            c = Candidate("grasp", {"approach": "top", "position": [0.0, 0.0, 0.8], "heading": heading})
            rows[name] = candidate_features(c, view)[-11:-6]  # cos 2a, sin 2a, minor, span along, across
        assert np.all(np.abs(rows["across"][[0, 3, 4]] - [-1, 0.03, 0.16]) < [0.05, 0.01, 0.02]), rows
        assert np.all(np.abs(rows["along"][[0, 3, 4]] - [1, 0.16, 0.03]) < [0.05, 0.02, 0.01]), rows
        np.testing.assert_allclose(rows["back"], rows["across"], atol=1e-5)


def test_the_finger_line_features_measure_the_span_met_and_what_stands_in_the_way():
    """Version 3: on a 16 x 3 cm bar, fingers closing across it through its middle meet 3 cm of it,
    centred; along it, 16 cm; nothing else seen: both clearances at the cap; a neighbour's points on
    the fingers' line 4 cm away and a shelf 5 cm over the grip site are measured as such, a point
    beside the line or under the grip height is not."""
    from scenegen.policy.proposal_model import CLEAR_CAP

    yaw = np.pi / 5
    view = _view(_table_frames(bar_yaw=yaw))

    def line(angle: float, others=()):
        c = Candidate(
            "grasp",
            {"approach": "top", "position": [0.0, 0.0, 0.8], "heading": [np.cos(angle), np.sin(angle)]},
        )
        seen = TargetView(
            view.target, np.asarray(others, float).reshape(-1, 3), target_points=view.target_points
        )
        return candidate_features(c, seen)[-6:]  # span, offset, top - z, z - bottom, clear along, over

    across, along = line(yaw + np.pi / 2), line(yaw)
    assert abs(across[0] - 0.03) < 0.01 and abs(across[1]) < 0.005, across
    assert abs(along[0] - 0.16) < 0.02 and abs(along[1]) < 0.01, along
    np.testing.assert_allclose(across[4:], [CLEAR_CAP, CLEAR_CAP], atol=1e-6)
    heading = np.array([np.cos(yaw + np.pi / 2), np.sin(yaw + np.pi / 2)])
    beside = np.array([-heading[1], heading[0]]) * 0.05
    others = [
        [*(heading * 0.04), 0.81],  # on the fingers' line, 4 cm out
        [*(heading * 0.02 + beside), 0.81],  # 5 cm beside the line: not in the way
        [*(heading * 0.01), 0.70],  # under the grip height: not in the way
        [0.0, 0.0, 0.85],  # over the grip site
    ]
    crowded = line(yaw + np.pi / 2, others)
    np.testing.assert_allclose(crowded[4:], [0.04, 0.05], atol=1e-6)


def test_projection_inverts_the_back_projection_of_depth():
    frames = _table_frames()
    _, depth, mask = frames["front"]
    rows, cols = np.nonzero(mask)
    points = masked_points(depth, mask, CAMS["front"])
    pixels, z = project(CAMS["front"], points, SIZE)
    np.testing.assert_allclose(pixels, np.stack([cols, rows], 1), atol=1e-6)
    np.testing.assert_allclose(z, depth[rows, cols], rtol=1e-5)


def test_the_crop_is_centred_on_the_candidate_and_turned_with_its_heading():
    grasp = {"approach": "top", "position": [0.0, 0.0, 0.8]}
    along = Candidate("grasp", {**grasp, "heading": [1.0, 0.0]})
    frames = _table_frames(bar_yaw=0.0)
    crop = candidate_crop(frames, CAMS, along)
    assert crop.shape == (CHANNELS, CROP, CROP)
    mask, depth = crop[4], crop[3]
    assert mask[CROP // 2, CROP // 2] == 1.0 and abs(depth[CROP // 2, CROP // 2]) < 0.05
    # the bar runs along the heading: along the crop's rows through the centre, not its columns
    assert mask[CROP // 2].sum() > 2 * mask[:, CROP // 2].sum()
    turned = candidate_crop(
        _table_frames(bar_yaw=np.pi / 2), CAMS, Candidate("grasp", {**grasp, "heading": [0.0, 1.0]})
    )
    np.testing.assert_allclose(turned[4].sum(), mask.sum(), rtol=0.35)
    assert turned[4][CROP // 2].sum() > 2 * turned[4][:, CROP // 2].sum()
    across = candidate_crop(frames, CAMS, Candidate("grasp", {**grasp, "heading": [0.0, 1.0]}))
    assert across[4][:, CROP // 2].sum() > 2 * across[4][CROP // 2].sum()
    beside = Candidate("grasp", {**grasp, "position": [0.0, 0.2, 0.8], "heading": [1.0, 0.0]})
    assert candidate_crop(frames, CAMS, beside)[4].sum() == 0  # 20 cm off the bar: no target in reach


def _examples(n: int, seed: int):
    """Candidates on and beside the bar (top grasps at random points and headings), labelled by
    whether the fingers close across it (heading within 30 degrees of across, the point on it)."""
    rng = np.random.default_rng(seed)
    frames = _table_frames()
    view = _view(frames)
    crops, features, labels = [], [], []
    for _ in range(n):
        x, y = rng.uniform(-0.1, 0.1), rng.uniform(-0.03, 0.03)
        angle = rng.uniform(0, np.pi)
        c = Candidate(
            "grasp", {"approach": "top", "position": [x, y, 0.8], "heading": [np.cos(angle), np.sin(angle)]}
        )
        on = abs(x) < 0.07 and abs(y) < 0.012 and abs(np.sin(angle)) > np.cos(np.radians(30))
        crops.append(candidate_crop(frames, CAMS, c))
        features.append(candidate_features(c, view))
        labels.append(float(on))
    return np.stack(crops), np.stack(features), np.asarray(labels, np.float32)


def test_a_small_model_learns_which_candidates_close_across_the_target(tmp_path: Path):
    crops, features, labels = _examples(600, seed=0)
    assert features.shape == (600, FEATURES) and 0.05 < labels.mean() < 0.5
    model = train_model(crops, features, labels, steps=1000, batch=64, width=8, seed=0)
    test_crops, test_features, test_labels = _examples(200, seed=1)
    scores = model.scores(test_crops, test_features)
    positive, negative = scores[test_labels == 1], scores[test_labels == 0]
    auc = (positive[:, None] > negative[None, :]).mean()
    assert auc > 0.9, auc
    best = np.argsort(-scores)[: int(test_labels.sum())]  # as many as there are positives
    assert test_labels[best].mean() > 0.5, test_labels[best].mean()  # the positives' rate by chance: 0.1
    model.save(tmp_path / "m")
    again = ProposalModel.load(tmp_path / "m")
    np.testing.assert_allclose(again.scores(test_crops, test_features), scores, rtol=1e-6)
    same = train_model(crops, features, labels, steps=1000, batch=64, width=8, seed=0)
    np.testing.assert_array_equal(same.scores(test_crops, test_features), scores)


def test_a_folder_that_is_not_a_proposal_model_is_refused_in_one_line(tmp_path: Path):
    with pytest.raises(CheckpointError, match="not a proposal model"):
        ProposalModel.load(tmp_path)
    (tmp_path / "config.json").write_text('{"kind": "policy"}')
    (tmp_path / "model.safetensors").write_bytes(b"junk")
    with pytest.raises(CheckpointError, match=f"not a proposal model of version {MODEL_VERSION}") as info:
        ProposalModel.load(tmp_path)
    assert "\n" not in str(info.value)
    (tmp_path / "config.json").write_text('{"kind": "proposals", "version": 1, "width": 8}')
    with pytest.raises(CheckpointError, match="version 1"):  # 13 numbers per candidate: not loaded
        ProposalModel.load(tmp_path)
