"""Image statistics: exact values on synthetic images, the committed reference file, the check's
threshold on its own halves, a hand-built batch directory and its errors, and (slow) real renders of
reference layouts reproducing the committed rows and failing the check when darkened or tinted."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scenegen.analysis.image_stats import (
    IMAGE_STAT_NAMES,
    IMAGE_STATS_THRESHOLD,
    REFERENCE_IMAGE_STATS,
    REFERENCE_PARQUET,
    REFERENCE_RECIPE,
    batch_image_statistics,
    image_statistics,
    image_stats_check,
    load_reference_image_stats,
    read_rgb,
    sampled_smd,
)
from scenegen.data import reference_images

STAT = {name: i for i, name in enumerate(IMAGE_STAT_NAMES)}
REPO_ROOT = Path(__file__).resolve().parents[2]


def solid(rgb: tuple[int, int, int], shape: tuple[int, int] = (6, 8)) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, np.uint8), (*shape, 3)).copy()


# ---------------------------------------------------------------- one image


def test_black_white_grey_and_red_images_give_the_obvious_values():
    black, white = image_statistics(solid((0, 0, 0))), image_statistics(solid((255, 255, 255)))
    assert black.dtype == np.float64 and black.shape == (len(IMAGE_STAT_NAMES),)
    expected_black = dict.fromkeys(IMAGE_STAT_NAMES, 0.0) | {
        "underexposed": 1.0,
        "chroma_r": 1 / 3,
        "chroma_g": 1 / 3,
    }
    expected_white = {
        **dict.fromkeys(IMAGE_STAT_NAMES, 0.0),
        **dict.fromkeys(("luminance_mean", "luminance_p05", "luminance_p95", "overexposed"), 1.0),
        "chroma_r": 1 / 3,
        "chroma_g": 1 / 3,
    }
    assert dict(zip(IMAGE_STAT_NAMES, black, strict=True)) == pytest.approx(expected_black, abs=1e-12)
    assert dict(zip(IMAGE_STAT_NAMES, white, strict=True)) == pytest.approx(expected_white, abs=1e-12)

    red = dict(zip(IMAGE_STAT_NAMES, image_statistics(solid((255, 0, 0))), strict=True))
    assert (
        red["luminance_mean"] == pytest.approx(0.2126) and red["chroma_r"] == 1.0 and red["chroma_g"] == 0.0
    )
    assert red["saturation_mean"] == 1.0

    half = np.concatenate([solid((0, 0, 0)), solid((255, 255, 255))])  # half black, half white
    s = dict(zip(IMAGE_STAT_NAMES, image_statistics(half), strict=True))
    assert s["luminance_mean"] == pytest.approx(0.5) and s["luminance_std"] == pytest.approx(0.5)
    assert (
        s["underexposed"] == s["overexposed"] == 0.5
        and s["luminance_p05"] == 0.0
        and s["luminance_p95"] == 1.0
    )


def test_image_statistics_rejects_what_is_not_an_rgb_uint8_image():
    for bad in (np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8), np.zeros((4, 4, 3), np.float32)):
        with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
            image_statistics(bad)


def test_every_statistic_is_documented():
    docs = (REPO_ROOT / "docs" / "realism.md").read_text()
    for name in IMAGE_STAT_NAMES:
        assert f"``{name}``" in image_statistics.__doc__ and f"`{name}`" in docs, name
    assert f"**Threshold {IMAGE_STATS_THRESHOLD}**" in docs


# ---------------------------------------------------------------- the check


def test_check_reports_signed_standardized_differences():
    rng = np.random.default_rng(0)
    reference = rng.uniform(0.2, 0.8, (50, len(IMAGE_STAT_NAMES)))
    batch = reference.copy()
    std = reference[:, STAT["chroma_r"]].std(ddof=1)
    batch[:, STAT["chroma_r"]] -= 2.0 * std
    result = image_stats_check(batch, reference)
    assert result.per_stat["chroma_r"] == pytest.approx(-2.0)
    assert all(abs(v) < 1e-12 for k, v in result.per_stat.items() if k != "chroma_r")
    assert result.value == pytest.approx(2.0) and result.passed == (2.0 <= IMAGE_STATS_THRESHOLD)
    assert (result.n_batch, result.n_reference, result.threshold) == (50, 50, IMAGE_STATS_THRESHOLD)
    assert image_stats_check(batch, reference, threshold=2.5).passed


def test_check_guards_a_constant_reference_statistic():
    reference = np.full((10, len(IMAGE_STAT_NAMES)), 0.3)
    batch = reference[:2].copy()
    batch[:, STAT["overexposed"]] += 0.001  # one blown pixel in a thousand
    result = image_stats_check(batch, reference)
    assert np.isfinite(result.value) and result.value == pytest.approx(0.1) and result.passed


def test_check_needs_two_rows_of_the_right_width():
    reference = np.zeros((10, len(IMAGE_STAT_NAMES)))
    with pytest.raises(ValueError, match="batch has 1 image row"):
        image_stats_check(reference[:1], reference)
    with pytest.raises(ValueError, match="reference has 0 image row"):
        image_stats_check(reference, reference[:0])
    with pytest.raises(ValueError, match=r"\(N, 9\)"):
        image_stats_check(reference[:, :3], reference)
    nan = reference.copy()
    nan[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        image_stats_check(nan, reference)
    # a handful of scenes still gives a defined result
    assert np.isfinite(image_stats_check(reference[:2] + 0.001, reference).value)


def test_a_sampled_estimate_covers_the_whole_batch_value_at_its_stated_rate():
    """The audit judges a large batch's image check on a sample of its scenes (audit/scenes.py): the
    ratio estimator of the batch's per-statistic differences, with its standard error. On a synthetic
    batch of 400 scenes with one or two cameras each (images of a scene correlated), the whole sample
    gives the exact per-statistic values with no error; 300 samples of 40 scenes cover the exact value
    within 1.96 standard errors at close to their nominal 95 %."""
    rng = np.random.default_rng(3)
    width = len(IMAGE_STAT_NAMES)
    reference = rng.normal(0.4, 0.1, (120, width))
    scenes = []
    for _ in range(400):
        common = rng.normal(0.45, 0.08, width)
        scenes.append(common + rng.normal(0.0, 0.03, (int(rng.integers(1, 3)), width)))
    exact = image_stats_check(np.concatenate(scenes), reference).per_stat
    exact = np.array([exact[name] for name in IMAGE_STAT_NAMES])
    estimate, error = sampled_smd(scenes, len(scenes), reference)
    assert np.allclose(estimate, exact, atol=1e-12) and np.allclose(error, 0.0)
    covered = []
    for _ in range(300):
        chosen = rng.choice(len(scenes), size=40, replace=False)
        estimate, error = sampled_smd([scenes[i] for i in chosen], len(scenes), reference)
        covered.append(np.abs(estimate - exact) <= 1.96 * error)
    rate = np.mean(covered)
    assert 0.91 <= rate <= 0.98, rate
    with pytest.raises(ValueError, match="needs 2"):
        sampled_smd(scenes[:1], len(scenes), reference)


# ---------------------------------------------------------------- the committed reference file


def test_committed_reference_file_loads_and_matches_the_reference_set():
    import pyarrow.parquet as pq

    from scenegen.render.offscreen import RENDER_SETTINGS
    from scenegen.runner.config import load_pipeline
    from scenegen.store.batch import sha256_file

    rows, meta = load_reference_image_stats(REFERENCE_IMAGE_STATS)
    assert rows.shape == (2 * meta["n"], len(IMAGE_STAT_NAMES)) and meta["n"] == 60
    assert meta["stat_names"] == list(IMAGE_STAT_NAMES)
    assert meta["reference_sha256"] == sha256_file(REFERENCE_PARQUET), "reference.parquet changed: rebuild"
    assert meta["recipe"] == "pipelines/reference.yaml"
    assert meta["recipe_sha256"] == load_pipeline(REFERENCE_RECIPE).digest()
    assert meta["render_settings"] == json.loads(json.dumps(RENDER_SETTINGS))
    indices = pq.read_table(REFERENCE_PARQUET, columns=["index"]).column("index").to_pylist()[: meta["n"]]
    assert list(dict.fromkeys(meta["scene_index"])) == indices
    assert meta["camera"][:2] == ["front", "side"]
    assert "scenegen reference-images --n 60" in meta["command"]
    assert np.all((rows >= 0.0) & (rows <= 1.0))


def test_halves_of_the_committed_reference_pass_with_a_wide_margin():
    rows, _ = load_reference_image_stats(REFERENCE_IMAGE_STATS)
    half = len(rows) // 2  # 30 scenes each; rows come in (front, side) pairs
    for a, b in ((rows[:half], rows[half:]), (rows[half:], rows[:half])):
        result = image_stats_check(a, b)
        assert result.passed and result.value < IMAGE_STATS_THRESHOLD / 3, result  # measured 0.23, 0.25


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (None, "no such file"),
        ("{not json", "not valid JSON"),
        (json.dumps({"stat_names": ["a"], "rows": [[1.0]]}), "differ from IMAGE_STAT_NAMES"),
        (json.dumps({"stat_names": list(IMAGE_STAT_NAMES), "rows": [[0.1] * 3] * 2}), "has shape"),
        (
            json.dumps({"stat_names": list(IMAGE_STAT_NAMES), "rows": [[0.1] * 9] * 2, "camera": ["front"]}),
            "'scene_index' must have one entry per row",
        ),
    ],
)
def test_a_bad_reference_file_is_a_one_line_error_naming_it(tmp_path: Path, content, match):
    path = tmp_path / "image_stats.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ValueError, match=match) as info:
        load_reference_image_stats(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# ---------------------------------------------------------------- a stored batch


def write_batch(root: Path, scenes: dict[str, list[tuple[str, np.ndarray]]]) -> Path:
    """A batch directory in the store's layout: index.jsonl in the given scene order, each scene's
    scene.json naming its cameras' RGB PNGs."""
    root.mkdir()
    with open(root / "index.jsonl", "w") as index:
        for scene_id, cameras in scenes.items():
            (root / scene_id).mkdir()
            entries = []
            for name, rgb in cameras:
                cv2.imwrite(str(root / scene_id / f"{name}_rgb.png"), rgb[..., ::-1])
                entries.append(
                    {"name": name, "images": {k: f"{name}_{k}.png" for k in ("rgb", "depth", "seg")}}
                )
            (root / scene_id / "scene.json").write_text(
                json.dumps({"scene_id": scene_id, "cameras": entries})
            )
            index.write(json.dumps({"scene_id": scene_id}) + "\n")
    return root


def test_batch_rows_follow_the_index_and_the_cameras(tmp_path: Path):
    red, grey, white = solid((200, 30, 30)), solid((128, 128, 128)), solid((255, 255, 255))
    batch = write_batch(
        tmp_path / "batch",
        {"scene_000007": [("front", red), ("side", grey)], "scene_000002": [("front", white)]},
    )
    rows, scene_ids, cameras = batch_image_statistics(batch)
    assert scene_ids == ["scene_000007", "scene_000007", "scene_000002"]
    assert cameras == ["front", "side", "front"]
    expected = np.stack([image_statistics(im) for im in (red, grey, white)])
    assert np.array_equal(rows, expected)  # PNG is lossless and BGR is turned back into RGB
    assert np.array_equal(read_rgb(batch / "scene_000007" / "front_rgb.png"), red)


def test_missing_or_unreadable_images_are_errors_naming_the_file(tmp_path: Path):
    batch = write_batch(
        tmp_path / "batch", {"scene_000000": [("front", solid((9, 9, 9))), ("side", solid((1, 2, 3)))]}
    )
    side = batch / "scene_000000" / "side_rgb.png"
    side.write_bytes(b"not a png")
    with pytest.raises(ValueError, match="not a readable image") as info:
        batch_image_statistics(batch)
    assert str(side) in str(info.value)
    side.unlink()
    with pytest.raises(ValueError, match="no such image file") as info:
        batch_image_statistics(batch)
    assert str(side) in str(info.value)

    scene_json = batch / "scene_000000" / "scene.json"
    scene_json.write_text(json.dumps({"cameras": [{"name": "front"}]}))  # a --no-render scene
    with pytest.raises(ValueError, match="no RGB image") as info:
        batch_image_statistics(batch)
    assert str(scene_json) in str(info.value)
    with pytest.raises(ValueError, match="no index.jsonl"):
        batch_image_statistics(tmp_path)


# ---------------------------------------------------------------- real renders (slow)


@pytest.fixture(scope="module")
def rendered_reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """The first 2 reference layouts rendered through build_reference_image_stats (~10 s): the
    written file's content and the directory of their RGB PNGs."""
    out = tmp_path_factory.mktemp("image_stats")
    reference_images.build_reference_image_stats(2, out / "image_stats.json", images=out / "images")
    return json.loads((out / "image_stats.json").read_text()), out / "images"


@pytest.mark.slow
def test_rendering_reference_layouts_reproduces_the_committed_rows(rendered_reference):
    built, _ = rendered_reference
    committed, meta = load_reference_image_stats(REFERENCE_IMAGE_STATS)
    rows = np.asarray(built["rows"])
    assert built["scene_index"] == meta["scene_index"][: len(rows)]
    assert built["camera"] == meta["camera"][: len(rows)]
    assert np.abs(rows - committed[: len(rows)]).max() < 1e-3
    assert built["reference_sha256"] == meta["reference_sha256"]
    assert built["recipe_sha256"] == meta["recipe_sha256"]


@pytest.mark.slow
def test_darkened_or_tinted_reference_images_fail_the_check(rendered_reference):
    built, images = rendered_reference
    reference, _ = load_reference_image_stats(REFERENCE_IMAGE_STATS)
    pictures = [
        read_rgb(images / f"{i:06d}_{camera}_rgb.png").astype(np.float64)
        for i, camera in zip(built["scene_index"], built["camera"], strict=True)
    ]

    def statistics(change) -> np.ndarray:
        return np.stack(
            [image_statistics(np.clip(np.round(change(p)), 0, 255).astype(np.uint8)) for p in pictures]
        )

    # Measured: as rendered 0.91, darkened x0.5 4.38, tinted 10.5 (2 scenes, 4 images).
    as_rendered = image_stats_check(statistics(lambda p: p), reference)
    darkened = image_stats_check(statistics(lambda p: 0.5 * p), reference)
    tinted = image_stats_check(statistics(lambda p: p * np.array([1.15, 1.0, 0.85])), reference)
    assert as_rendered.passed, as_rendered
    assert not darkened.passed and darkened.value > 2 * IMAGE_STATS_THRESHOLD, darkened
    assert darkened.per_stat["luminance_mean"] < 0 and darkened.per_stat["underexposed"] > 0
    assert not tinted.passed and tinted.value > 4 * IMAGE_STATS_THRESHOLD, tinted
    assert tinted.per_stat["chroma_r"] > 0 and tinted.per_stat["saturation_mean"] > 0


def test_command_line_misuse_is_an_error_exit(tmp_path: Path, capsys):
    from scenegen.cli import main

    assert main(["reference-images", "--n", "0", "--out", str(tmp_path / "x.json")]) == 2
    assert "n=0" in capsys.readouterr().err and not (tmp_path / "x.json").exists()


@pytest.mark.slow
def test_layouts_that_are_not_the_reference_rows_are_refused(tmp_path: Path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    other = tmp_path / "other.parquet"  # a reference set whose first layout is proposal 1
    pq.write_table(pa.table({"index": [1, 2]}), other)
    with pytest.raises(ValueError, match="changed since the Parquet file was built"):
        reference_images.build_reference_image_stats(1, tmp_path / "image_stats.json", reference=other)
    assert not (tmp_path / "image_stats.json").exists()
