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


def _floor_stack(row: dict) -> dict | None:
    """A held-out table-top stack (the target on a base resting on the table) lowered, both objects,
    onto the floor strip: a composition (stacked + on_floor) no reference layout holds."""
    objects = {o["name"]: o for o in row["objects"]}
    base = objects.get(objects[row["target"]]["support"])
    if base is None or base["support"] != "table":
        return None
    out = copy.deepcopy(row)
    moved = {o["name"]: o for o in out["objects"]}
    for name in (row["target"], base["name"]):
        x, y, z = moved[name]["position"]
        moved[name]["position"] = [0.1 + x - base["position"][0], 0.68 + y - base["position"][1], z - 0.8]
    moved[base["name"]]["support"] = "floor"
    return out


def _bright(row: dict) -> dict:
    out = copy.deepcopy(row)
    for light in out["lights"]:
        light["intensity"] *= 20
    return out


def test_a_composition_the_reference_lacks_is_judged_per_tag(rows, scorer):
    """Issue 64 point 3. Floor stacks built from held-out table-top stacks: the whole reference scores
    every one under the 0.01 floor (no layout holds stacked with on_floor), judged per tag most pass
    (measured 39 of 46); the same stacks under 20x the light, and table-top scenes of a composition the
    reference holds twice (near_edge + under_overhang) under 20x the light, fail per tag too. A
    composition the reference holds in k layouts or more is left to the whole reference."""
    reference = str(REFERENCE)
    _, heldout = rows
    composition = ("stacked", "on_floor")
    assert scene_score.composition_layouts(reference, composition) == 0
    stacks = [s for s in map(_floor_stack, (r for r in heldout if r["tag_stacked"])) if s]
    judged = [scene_score.composition_scores(reference, 5, composition, s) for s in stacks]
    assert len(stacks) >= 30
    assert all(j is not None and j.layouts == 0 for j in judged)
    assert np.all(scorer.scores(stacks) < 0.01)
    assert np.mean([j.score >= 0.01 for j in judged]) >= 0.75
    assert "0 reference layouts" in judged[0].detail() and "on_floor" in judged[0].detail()
    bright = [scene_score.composition_scores(reference, 5, composition, _bright(s)).score for s in stacks]
    assert max(bright) < 0.01  # at 8x, 8 of 46 passed, as 12 % of bright held-out rows pass the whole
    table_top = ("near_edge", "under_overhang")
    assert 0 < scene_score.composition_layouts(reference, table_top) < 5
    shelved = [r for r in heldout if r["tag_near_edge"] and any(f["kind"] == "shelf" for f in r["furniture"])]
    assert shelved and all(
        scene_score.composition_scores(reference, 5, table_top, _bright(r)).score < 0.01 for r in shelved
    )
    assert (
        scene_score.composition_scores(reference, 5, ("toppled", "stacked"), heldout[0]) is None
    )  # 6 layouts
    assert scene_score.composition_scores(reference, 5, ("on_floor",), stacks[0]) is None
