"""Per-scene realism score (scene_score.SceneScorer) on the committed reference set: held-out layouts
score like the reference itself, distorted ones lower, far-moved ones near 0; and a stored record
scores as its Parquet row."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from scenegen.analysis import realism, scene_score

REPO_ROOT = Path(__file__).resolve().parents[2]
REFERENCE = REPO_ROOT / "assets" / "reference" / "reference.parquet"
RECIPE = REPO_ROOT / "pipelines" / "reference.yaml"


@pytest.fixture(scope="module")
def rows() -> tuple[list[dict], list[dict]]:
    """(train, heldout) rows of the committed reference set (~8,000 and ~2,000)."""
    rows = realism.load_rows(REFERENCE, None)
    return [r for r in rows if r["split"] == "train"], [r for r in rows if r["split"] == "heldout"]


@pytest.fixture(scope="module")
def scorer(rows) -> scene_score.SceneScorer:
    return scene_score.SceneScorer.from_rows(rows[0], k=5)  # ~3 s for 8,000 rows


def test_heldout_layouts_score_like_the_reference(rows, scorer):
    _, heldout = rows
    scores = scorer.scores(heldout[:200])
    assert np.all((scores >= 0.0) & (scores <= 1.0))
    # Measured 0.454 (first 200); over 1,000 random 200-row subsets of the held-out split the median
    # was never below 0.40. Under the null the score is about uniform on [0, 1].
    assert np.median(scores) > 0.3
    assert np.median(scorer.scores(heldout)) == pytest.approx(0.5, abs=0.05)  # measured 0.503


def test_distorted_layouts_score_lower(rows, scorer):
    _, heldout = rows
    sample = heldout[:200]
    base = scorer.scores(sample)
    # Every object moved 15 cm: median 0.317 against 0.454, lower in 70-79 % of layouts (seeds 0-3).
    moved = scorer.scores(realism.distort(sample, fraction=1.0, shift=0.15, seed=0))
    assert np.median(moved) < np.median(base) - 0.05
    assert np.mean(moved < base) > 0.6
    # One object moved 0.6 m in x and y (off the table): median 0.022, lower in 98.5 %.
    far = copy.deepcopy(sample)
    for row in far:
        position = row["objects"][0]["position"]
        row["objects"][0]["position"] = [position[0] + 0.6, position[1] + 0.6, position[2]]
    far_scores = scorer.scores(far)
    assert np.median(far_scores) < 0.1 and np.mean(far_scores < base) > 0.9


def test_reference_rows_score_in_range_and_scores_are_deterministic(rows, scorer):
    train, heldout = rows
    own = scorer.scores(train[:100])
    assert np.all((own >= 0.0) & (own <= 1.0))
    assert scorer.score(train[0]) == own[0]
    again = scene_score.SceneScorer.from_rows(train[:2000], k=5)
    assert np.array_equal(
        again.scores(heldout[:50]), scene_score.SceneScorer.from_rows(train[:2000]).scores(heldout[:50])
    )
    assert np.all(np.diff(scorer.reference_knn) >= 0)


def test_scorer_misuse_is_an_error(rows):
    train, _ = rows
    with pytest.raises(ValueError, match="k >= 1"):
        scene_score.SceneScorer.from_rows(train[:10], k=0)
    with pytest.raises(ValueError, match="needs at least 6"):
        scene_score.SceneScorer.from_rows(train[:5], k=5)


def test_a_stored_record_scores_as_its_parquet_row(rows, scorer):
    from scenegen.assets.catalog import load_catalog
    from scenegen.data.reference import request_for
    from scenegen.propose.base import PROPOSERS
    from scenegen.runner.config import load_pipeline
    from scenegen.runner.process import process_proposal

    _, heldout = rows
    config = load_pipeline(RECIPE)
    catalog = load_catalog()
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    index = heldout[0]["index"]  # held out, so not among the scorer's rows
    [proposal] = proposer.propose(request_for(config, index, catalog.categories), [index], config.seed)
    record = process_proposal(proposal, config, catalog, export=False).record
    assert record is not None
    assert scene_score.scene_score_for_record(record, scorer) == scorer.score(heldout[0])


def test_a_worker_uses_the_scorer_its_coordinator_built(scorer, monkeypatch: pytest.MonkeyPatch):
    """Pool workers get the coordinator's scorer (runner/process.py init_worker) instead of reading
    the reference set again: an installed scorer is the one returned, and nothing is read."""
    monkeypatch.setattr(scene_score, "_SCORERS", {})
    monkeypatch.setattr(scene_score, "load_rows", lambda *a, **k: pytest.fail("the reference set was read"))
    scene_score.install_scorer("elsewhere.parquet", 5, scorer)
    assert scene_score.reference_scorer("elsewhere.parquet", 5) is scorer


def test_the_scorer_is_cached_on_disk_and_rebuilt_when_the_cache_is_bad(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    reference = tmp_path / "reference.parquet"
    reference.write_bytes(REFERENCE.read_bytes())
    monkeypatch.setenv("SCENEGEN_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(scene_score, "_SCORERS", {})
    built = scene_score.reference_scorer(str(reference), 5)
    cache = scene_score.scorer_cache_path(reference, 5)
    assert cache.is_file() and cache.is_relative_to(tmp_path / "cache")

    scene_score._SCORERS.clear()
    real_load_rows = scene_score.load_rows
    monkeypatch.setattr(scene_score, "load_rows", lambda *a, **k: pytest.fail("the cache was not used"))
    cached = scene_score.reference_scorer(str(reference), 5)
    for name in ("mean", "scale", "reference", "reference_knn"):
        assert np.array_equal(getattr(cached, name), getattr(built, name)), name
    assert cached.categories == built.categories and cached.k == 5

    cache.write_bytes(b"not an npz")  # a torn or foreign file: rebuilt, not trusted
    scene_score._SCORERS.clear()
    monkeypatch.setattr(scene_score, "load_rows", real_load_rows)
    rebuilt = scene_score.reference_scorer(str(reference), 5)
    assert np.array_equal(rebuilt.reference_knn, built.reference_knn)
    with open(reference, "ab") as f:  # other reference bytes: another cache file
        f.write(b"\0")
    assert scene_score.scorer_cache_path(reference, 5) != cache
