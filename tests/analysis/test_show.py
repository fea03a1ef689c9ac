"""``scenegen show``: the contact sheet of a batch, and its usage errors (exit 2, one line, nothing written).

The sheet is a grid of tiles in index order, ``--columns`` wide; a tile is one 320x240 thumbnail per
view (RGB, then depth and segmentation if asked) above a 34 px white label band; missing tiles of
the last row are white. Runs go through ``scenegen.cli.main`` with file-descriptor capture, so
anything a library prints to stderr counts too.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from scenegen.cli import main
from scenegen.propose.procedural import DEFAULT_CAMERAS

REPO_ROOT = Path(__file__).resolve().parents[2]
DEMO = REPO_ROOT / "pipelines" / "demo.yaml"
THUMB_W, THUMB_H = 320, 240
LABEL_H = 34
TILE_H = THUMB_H + LABEL_H
USAGE_ERROR = 2
PREFIX = "scenegen: error: "


# ---------------------------------------------------------------- helpers


def scene_ids(batch: Path) -> list[str]:
    return [json.loads(line)["scene_id"] for line in (batch / "index.jsonl").read_text().splitlines()]


def expected_shape(n_scenes: int, views: int, columns: int = 4, limit: int = 24) -> tuple[int, int, int]:
    tiles = min(n_scenes, limit)
    cols = max(1, min(columns, tiles))
    return math.ceil(tiles / cols) * TILE_H, cols * views * THUMB_W, 3


def tile(sheet: np.ndarray, i: int, views: int, columns: int) -> np.ndarray:
    """The i-th tile (thumbnails and label band) of a sheet."""
    row, col = divmod(i, columns)
    width = views * THUMB_W
    return sheet[row * TILE_H : (row + 1) * TILE_H, col * width : (col + 1) * width]


def thumbnail(image_path: Path) -> np.ndarray:
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    assert image is not None, image_path
    return cv2.resize(image, (THUMB_W, THUMB_H), interpolation=cv2.INTER_AREA)


def show(capfd: pytest.CaptureFixture, *args: str) -> tuple[int, str, str]:
    code = main(["show", *map(str, args)])
    captured = capfd.readouterr()
    return code, captured.out, captured.err


def assert_usage_error(code: int, out: str, err: str, needles: list[str]) -> str:
    assert code == USAGE_ERROR, (code, err)
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{err}"
    assert lines[0].startswith(PREFIX), lines[0]
    missing = [n for n in needles if n not in lines[0]]
    assert not missing, f"error line lacks {missing}: {lines[0]}"
    assert out == ""
    return lines[0]


def small_recipe(path: Path, n: int) -> Path:
    recipe = yaml.safe_load(DEMO.read_text())
    recipe["n"] = n
    recipe["proposer"]["cameras"] = [
        {"name": c.name, "position": list(c.position), "lookat": list(c.lookat), "width": 160, "height": 120}
        for c in DEFAULT_CAMERAS
    ]
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return path


# ---------------------------------------------------------------- fixtures


@pytest.fixture
def batch(demo_batch: Path, tmp_path: Path) -> Path:
    """A copy of the demo batch's scenes and index (the session's batch itself stays untouched)."""
    copy = tmp_path / "batch"
    copy.mkdir()
    for name in ("index.jsonl", "rejections.jsonl", "pipeline.yaml", "manifest.yaml"):
        shutil.copy(demo_batch / name, copy / name)
    for scene_id in scene_ids(demo_batch):
        shutil.copytree(demo_batch / scene_id, copy / scene_id)
    return copy


@pytest.fixture(scope="module")
def no_render_batch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("no_render_show")
    out = root / "batch"
    recipe = small_recipe(root / "small.yaml", n=1)
    assert main(["generate", str(recipe), "--out", str(out), "--no-render", "--quiet"]) == 0
    return out


# ---------------------------------------------------------------- sheets


def test_default_sheet_is_a_grid_of_front_thumbnails_in_index_order(batch: Path, capfd):
    code, out, err = show(capfd, batch)
    assert code == 0, err
    path = batch / "contact_sheet.png"
    assert out.strip() == str(path)
    sheet = cv2.imread(str(path), cv2.IMREAD_COLOR)
    ids = scene_ids(batch)
    assert len(ids) == 6
    assert sheet.shape == expected_shape(len(ids), views=1) == (2 * TILE_H, 4 * THUMB_W, 3)
    for i, scene_id in enumerate(ids):
        t = tile(sheet, i, views=1, columns=4)
        np.testing.assert_array_equal(
            t[:THUMB_H], thumbnail(batch / scene_id / "front_rgb.png"), err_msg=f"tile {i} is not {scene_id}"
        )
        band = t[THUMB_H:]
        assert (band < 128).any(), f"tile {i}: no label text"
        assert (band == 255).mean() > 0.6, f"tile {i}: label band is not white"
    for i in range(len(ids), 8):
        assert (tile(sheet, i, views=1, columns=4) == 255).all(), f"filler tile {i} is not blank"


def test_depth_and_seg_add_two_views_per_tile(batch: Path, capfd):
    code, _, err = show(capfd, batch, "--depth", "--seg")
    assert code == 0, err
    sheet = cv2.imread(str(batch / "contact_sheet.png"), cv2.IMREAD_COLOR)
    assert sheet.shape == expected_shape(6, views=3) == (2 * TILE_H, 4 * 3 * THUMB_W, 3)
    for i, scene_id in enumerate(scene_ids(batch)):
        t = tile(sheet, i, views=3, columns=4)
        rgb, depth, seg = (t[:THUMB_H, k * THUMB_W : (k + 1) * THUMB_W] for k in range(3))
        np.testing.assert_array_equal(rgb, thumbnail(batch / scene_id / "front_rgb.png"))
        ids = np.unique(cv2.imread(str(batch / scene_id / "front_seg.png"), cv2.IMREAD_UNCHANGED))
        colours = np.unique(seg.reshape(-1, 3), axis=0)
        assert 3 <= len(colours) <= len(ids), f"tile {i}: seg view has {len(colours)} colours, {len(ids)} ids"
        assert len(np.unique(depth.reshape(-1, 3), axis=0)) > 20, f"tile {i}: depth view is flat"
        assert not np.array_equal(depth, rgb) and not np.array_equal(depth, seg)


def test_out_elsewhere(batch: Path, tmp_path: Path, capfd):
    target = tmp_path / "sheets" / "nested" / "demo.png"
    code, out, err = show(capfd, batch, "--out", target)
    assert code == 0, err
    assert out.strip() == str(target)
    assert cv2.imread(str(target)).shape == expected_shape(6, views=1)
    assert not (batch / "contact_sheet.png").exists()


def test_side_camera(batch: Path, capfd):
    code, _, err = show(capfd, batch, "--camera", "side")
    assert code == 0, err
    sheet = cv2.imread(str(batch / "contact_sheet.png"), cv2.IMREAD_COLOR)
    for i, scene_id in enumerate(scene_ids(batch)):
        t = tile(sheet, i, views=1, columns=4)[:THUMB_H]
        np.testing.assert_array_equal(t, thumbnail(batch / scene_id / "side_rgb.png"), err_msg=scene_id)


def test_max_and_columns_shape_the_grid(batch: Path, capfd):
    code, _, err = show(capfd, batch, "--max", "3", "--columns", "2", "--seg")
    assert code == 0, err
    sheet = cv2.imread(str(batch / "contact_sheet.png"), cv2.IMREAD_COLOR)
    assert sheet.shape == expected_shape(6, views=2, columns=2, limit=3) == (2 * TILE_H, 2 * 2 * THUMB_W, 3)
    ids = scene_ids(batch)
    for i in range(3):
        t = tile(sheet, i, views=2, columns=2)[:THUMB_H, :THUMB_W]
        np.testing.assert_array_equal(t, thumbnail(batch / ids[i] / "front_rgb.png"))
    assert (tile(sheet, 3, views=2, columns=2) == 255).all()


# ---------------------------------------------------------------- usage errors


def test_unknown_camera_lists_the_valid_ones(batch: Path, capfd):
    code, out, err = show(capfd, batch, "--camera", "nope")
    line = assert_usage_error(code, out, err, ["--camera", "nope", "front", "side"])
    assert "valid" in line
    assert not (batch / "contact_sheet.png").exists()


@pytest.mark.parametrize("kind", ["empty_dir", "scenes_without_index", "missing_dir"])
def test_directory_without_index_is_a_usage_error(batch: Path, tmp_path: Path, capfd, kind: str):
    if kind == "empty_dir":
        target = tmp_path / "empty"
        target.mkdir()
    elif kind == "scenes_without_index":
        target = batch
        (batch / "index.jsonl").unlink()
    else:
        target = tmp_path / "nowhere"
    code, out, err = show(capfd, target)
    assert_usage_error(code, out, err, [str(target), "index.jsonl"])
    assert not (target / "contact_sheet.png").exists()


def test_no_render_batch_is_a_usage_error_naming_no_render(no_render_batch: Path, capfd):
    code, out, err = show(capfd, no_render_batch)
    assert_usage_error(code, out, err, ["--no-render"])
    assert not (no_render_batch / "contact_sheet.png").exists()
