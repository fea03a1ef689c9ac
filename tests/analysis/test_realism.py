"""Layout realism metrics: features on hand-built layouts, the two-sample tests on Gaussians of known
difference, and (slow) both on a real reference sample of 120 settled layouts."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

from scenegen.analysis import realism
from scenegen.assets.catalog import load_catalog
from scenegen.core.layout import TABLE_TOP_Z

REPO_ROOT = Path(__file__).resolve().parents[2]
RECIPE = REPO_ROOT / "pipelines" / "reference.yaml"
N_REFERENCE = 120  # ~60 s of check + settle + tag on one worker
CATEGORIES = load_catalog().categories


def random_row(rng: np.random.Generator, n_objects: int) -> dict:
    """A layout in the reference row shape: objects on the table, one on the shelf, one stacked."""
    objects = []
    for i in range(n_objects):
        support = "shelf" if i == 1 else f"obj{i - 1}" if i == 2 else "table"
        quat = rng.normal(size=4)
        objects.append(
            {
                "name": f"obj{i}",
                "asset": "x",
                "category": CATEGORIES[int(rng.integers(len(CATEGORIES)))],
                "support": support,
                "resting_pose": 0,
                "position": [*rng.uniform(-0.35, 0.35, 2), TABLE_TOP_Z + rng.uniform(0.0, 0.3)],
                "quat": list(quat / np.linalg.norm(quat)),
            }
        )
    lights = [
        {"colour": list(rng.uniform(0.8, 1.0, 3)), "intensity": float(rng.uniform(0.3, 1.0))}
        for _ in range(int(rng.integers(1, 4)))
    ]
    return {
        "target": f"obj{int(rng.integers(n_objects))}",
        "objects": objects,
        "furniture": [{"kind": "shelf", "x": 0.0, "y": 0.3, "yaw": 0.0}],
        "ambient": float(rng.uniform(0.08, 0.3)),
        "lights": lights,
    }


def moved_distances(before: list[dict], after: list[dict]) -> list[np.ndarray]:
    """Per layout, how far (m) each object moved in 3-D."""
    return [
        np.array(
            [
                np.linalg.norm(np.subtract(o2["position"], o1["position"]))
                for o1, o2 in zip(r1["objects"], r2["objects"], strict=True)
            ]
        )
        for r1, r2 in zip(before, after, strict=True)
    ]


# ---------------------------------------------------------------- features


def test_features_of_a_hand_built_layout():
    row = {
        "target": "b",
        "objects": [
            {
                "name": "a",
                "category": "mug",
                "support": "table",
                "position": [0.0, 0.0, 0.85],
                "quat": [1, 0, 0, 0],
            },
            # lying on its side: body +z is horizontal
            {
                "name": "b",
                "category": "can",
                "support": "a",
                "position": [0.3, -0.4, 0.9],
                "quat": [math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
            },
            {
                "name": "c",
                "category": "mug",
                "support": "floor",
                "position": [0.0, 0.1, 0.05],
                "quat": [0, 0, 0, 1],
            },
        ],
        "furniture": [{"kind": "bin", "x": 0.2, "y": -0.3, "yaw": 0.0}],
        "ambient": 0.2,
        "lights": [
            {"colour": [1.0, 1.0, 1.0], "intensity": 0.5},
            {"colour": [0.7, 1.0, 1.0], "intensity": 1.0},
        ],
    }
    f = dict(zip(realism.FEATURE_NAMES, realism.layout_features(row), strict=True))
    assert f["n_objects"] == 3
    assert (f["target_x"], f["target_y"]) == (0.3, -0.4)
    assert f["target_height"] == pytest.approx(0.1)
    assert f["target_tilt"] == pytest.approx(math.pi / 2)
    # pairs: a-b 0.5, a-c 0.1, b-c hypot(0.3, 0.5)
    assert f["pair_distance_min"] == pytest.approx(0.1)
    assert f["pair_distance_mean"] == pytest.approx((0.5 + 0.1 + math.hypot(0.3, 0.5)) / 3)
    assert f["target_nn_distance"] == pytest.approx(0.5)
    assert (f["count_mug"], f["count_can"], f["count_spoon"]) == (2, 1, 0)
    shares = [f[f"support_{k}"] for k in realism.SUPPORT_KINDS]
    assert shares == pytest.approx([1 / 3, 0, 0, 1 / 3, 1 / 3])  # table, shelf, bin, floor, stacked
    assert f["mean_abs_x"] == pytest.approx(0.1) and f["mean_abs_y"] == pytest.approx(0.5 / 3)
    assert f["ambient"] == 0.2 and f["light_total"] == pytest.approx(0.5 + 0.9)
    assert (f["has_bin"], f["has_shelf"]) == (1.0, 0.0)


def test_features_fixed_length_and_permutation_invariant():
    rng = np.random.default_rng(0)
    length = len(realism.FEATURE_NAMES)
    assert length == len(set(realism.FEATURE_NAMES))
    for n_objects in (1, 2, 3, 7, 12):
        row = random_row(rng, n_objects)
        features = realism.layout_features(row)
        assert features.shape == (length,) and np.isfinite(features).all()
        for _ in range(3):
            shuffled = {**row, "objects": [row["objects"][i] for i in rng.permutation(n_objects)]}
            assert np.array_equal(realism.layout_features(shuffled), features)


def test_single_object_has_zero_distances():
    row = random_row(np.random.default_rng(1), 1)
    f = dict(zip(realism.FEATURE_NAMES, realism.layout_features(row), strict=True))
    assert f["pair_distance_min"] == f["pair_distance_mean"] == f["target_nn_distance"] == 0.0
    assert f["n_objects"] == 1


def test_unknown_support_or_category_is_an_error_that_says_so():
    row = random_row(np.random.default_rng(2), 3)
    row["objects"][0]["support"] = "windowsill"
    with pytest.raises(ValueError, match="windowsill"):
        realism.layout_features(row)
    row = random_row(np.random.default_rng(2), 3)
    row["objects"][0]["category"] = "teapot"
    with pytest.raises(ValueError, match="teapot"):
        realism.layout_features(row)


def test_every_feature_is_documented_in_order():
    text = (REPO_ROOT / "docs" / "realism.md").read_text()
    documented = re.findall(r"^\| \d+ \| `([a-z_]+)` \|", text, flags=re.MULTILINE)
    assert tuple(documented) == realism.FEATURE_NAMES
    assert f"{len(realism.FEATURE_NAMES)} features" in text
    for name in realism.FEATURE_NAMES:
        assert f"``{name}``" in realism.layout_features.__doc__ or name.startswith(
            ("count_", "support_", "has_")
        )


def test_distort_moves_the_stated_share_by_the_stated_distance():
    rng = np.random.default_rng(3)
    rows = [random_row(rng, n) for n in (1, 2, 3, 4, 5, 6, 7, 10)]
    snapshot = [realism.layout_features(r) for r in rows]
    moved = realism.distort(rows, fraction=0.3, shift=0.02, seed=4)
    for row, before, after in zip(rows, snapshot, moved_distances(rows, moved), strict=True):
        expected = math.floor(0.3 * len(row["objects"]) + 0.5)
        assert int(np.sum(after > 1e-12)) == expected
        assert after[after > 1e-12] == pytest.approx(0.02, abs=1e-12)
        assert np.array_equal(realism.layout_features(row), before)  # the input is left alone
    again = realism.distort(rows, fraction=0.3, shift=0.02, seed=4)
    assert again == moved


# ---------------------------------------------------------------- two-sample tests


def test_wilson_interval_matches_scipy():
    for k, n in ((60, 120), (97, 120), (3, 40)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert realism.wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_c2st_same_distribution_covers_chance():
    rng = np.random.default_rng(10)
    a, b = rng.normal(size=(150, 8)), rng.normal(size=(150, 8))
    result = realism.c2st(a, b, seed=0)
    assert result.n == 300
    assert result.ci[0] <= 0.5 <= result.ci[1], result
    assert not result.distinguishes


def test_c2st_detects_a_one_sd_shift_and_is_deterministic():
    rng = np.random.default_rng(11)
    a, b = rng.normal(size=(150, 8)), rng.normal(size=(200, 8))
    b[:, :3] += 1.0  # one standard deviation in three of eight features
    result = realism.c2st(a, b, seed=0)
    assert result.n == 300  # the larger sample is subsampled to the smaller
    assert result.accuracy > 0.7 and result.ci[0] > 0.5 and result.distinguishes, result
    assert realism.c2st(a, b, seed=0) == result
    assert realism.c2st(a, b, seed=0, folds=3).n == 300


def test_c2st_rejects_misuse():
    with pytest.raises(ValueError, match="same D"):
        realism.c2st(np.zeros((10, 3)), np.zeros((10, 4)), seed=0)
    with pytest.raises(ValueError, match="at least 5 rows"):
        realism.c2st(np.zeros((4, 3)), np.zeros((10, 3)), seed=0)
    with pytest.raises(ValueError, match="NaN"):
        realism.c2st(np.full((10, 3), np.nan), np.zeros((10, 3)), seed=0)


def test_mmd_same_versus_shifted():
    rng = np.random.default_rng(12)
    a, b = rng.normal(size=(150, 8)), rng.normal(size=(150, 8))
    same = realism.mmd(a, b, seed=0)
    assert same.p_value > 0.05 and abs(same.mmd2) < 0.01, same
    assert realism.mmd(a, b, seed=0) == same
    shifted = realism.mmd(a, b + np.r_[1.0, 1.0, 1.0, np.zeros(5)], seed=0)
    assert shifted.p_value < 0.01 and shifted.mmd2 > 10 * max(abs(same.mmd2), 1e-3), shifted
    assert shifted.p_value == pytest.approx(1 / 201)  # no permutation reaches the observed MMD^2


def test_power_is_a_fraction():
    rng = np.random.default_rng(13)
    rows = [random_row(rng, int(rng.integers(2, 8))) for _ in range(40)]
    rate = realism.power(rows, n_trials=2, seed=0)
    assert 0.0 <= rate <= 1.0
    assert rate * 2 == int(rate * 2)


# ---------------------------------------------------------------- on real reference layouts


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from scenegen.data.reference import build_reference
    from scenegen.runner.config import load_pipeline

    path = tmp_path_factory.mktemp("realism") / "reference.parquet"
    build_reference(load_pipeline(RECIPE, {"n": N_REFERENCE}), path, workers=1, progress=False)
    return path


@pytest.mark.slow
def test_reference_splits_and_features(reference):
    train, heldout = realism.load_rows(reference, "train"), realism.load_rows(reference, "heldout")
    assert len(train) + len(heldout) == N_REFERENCE and all(r["index"] % 5 == 0 for r in heldout)
    features = realism.reference_features(reference, "heldout")
    assert features.shape == (len(heldout), len(realism.FEATURE_NAMES)) and np.isfinite(features).all()
    f = dict(zip(realism.FEATURE_NAMES, realism.reference_features(reference, None).T, strict=True))
    assert np.all((f["n_objects"] >= 2) & (f["n_objects"] <= 7))  # the recipe's n_objects
    counts = sum(f[f"count_{c}"] for c in CATEGORIES)
    assert np.array_equal(counts, f["n_objects"])
    assert np.allclose(sum(f[f"support_{k}"] for k in realism.SUPPORT_KINDS), 1.0)
    with pytest.raises(ValueError, match="split"):
        realism.load_rows(reference, "test")


@pytest.mark.slow
def test_two_halves_of_the_reference_are_indistinguishable(reference):
    rows = realism.load_rows(reference, None)
    order = np.random.default_rng(0).permutation(len(rows))
    half = len(rows) // 2
    a = realism.feature_matrix([rows[i] for i in order[:half]])
    b = realism.feature_matrix([rows[i] for i in order[half:]])
    result = realism.c2st(a, b, seed=0)
    assert result.ci[0] <= 0.5 <= result.ci[1], result
    assert realism.mmd(a, b, seed=0).p_value > 0.05


@pytest.mark.slow
def test_distort_on_reference_rows(reference):
    rows = realism.load_rows(reference, None)
    moved = realism.distort(rows, seed=0)
    distances = moved_distances(rows, moved)
    total = sum(len(r["objects"]) for r in rows)
    expected = sum(math.floor(0.3 * len(r["objects"]) + 0.5) for r in rows)
    hits = np.concatenate(distances)
    assert int(np.sum(hits > 1e-12)) == expected and abs(expected / total - 0.3) < 0.1
    assert hits[hits > 1e-12] == pytest.approx(0.02, abs=1e-9)


@pytest.mark.slow
def test_a_stored_record_has_the_features_of_its_parquet_row(reference):
    from scenegen.data.reference import request_for
    from scenegen.propose.base import PROPOSERS
    from scenegen.runner.config import load_pipeline
    from scenegen.runner.process import process_proposal

    config = load_pipeline(RECIPE, {"n": N_REFERENCE})
    catalog = load_catalog()
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    by_index = {r["index"]: r for r in realism.load_rows(reference, None)}
    checked = 0
    for index in range(6):
        [proposal] = proposer.propose(request_for(config, index, catalog.categories), [index], config.seed)
        record = process_proposal(proposal, config, catalog, export=False).record
        assert (record is None) == (index not in by_index)
        if record is not None:
            row = realism.record_row(record)
            assert np.array_equal(realism.layout_features(row), realism.layout_features(by_index[index]))
            untagged = realism.record_row(record.model_copy(update={"tags": {}}))
            assert np.array_equal(realism.layout_features(untagged), realism.layout_features(row))
            checked += 1
    assert checked >= 2
