"""The proposal model's labels (issue 63, point 2): every candidate of a first decision executed
for real from the settled state and kept in the sequence store; the grasps after each push and pull
where no first grasp worked; a rerun simulates nothing, two workers give the same store."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from scenes import place, proposal

from scenegen.assets.catalog import load_catalog
from scenegen.core.layout import FURNITURE_HOME
from scenegen.env.scenes import proposal_scene, scene_sha256
from scenegen.experiment.proposal_labels import LabelConfig, candidate_labels, label_proposals, point_rng
from scenegen.experiment.sequences import ObservationStore, PathStore
from scenegen.manipulation.proposals import SamplerConfig
from scenegen.schema.scene import FurniturePlacement, Light, Lighting

LIGHT = Lighting(lights=(Light(position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), intensity=0.8),))
SHELF = FurniturePlacement(name="shelf", kind="shelf", position=(*FURNITURE_HOME["shelf"], 0.0))
# one top grasp, one push, one pull at the first decision; two grasps after a push or pull
CONFIG = LabelConfig(sampler=SamplerConfig(top=1, side=0, push=1, pull=1), follow=SamplerConfig(1, 1, 0, 0))


@functools.cache
def scenes():
    catalog = load_catalog()
    open_can = place(catalog, "can", "soda_can", 0.1, 0.0, pose=1)
    # under the near half of the shelf's board: a hand from above meets the board
    shelved = place(catalog, "can", "soda_can", 0.17, 0.27, pose=1, furniture=[SHELF])
    return (
        proposal_scene(proposal([open_can], lighting=LIGHT), "open_can"),
        proposal_scene(proposal([shelved], [SHELF], lighting=LIGHT), "shelved_can"),
    )


def _label(folder: Path, workers: int = 1):
    store, views = PathStore(folder / "paths.jsonl"), ObservationStore(folder / "views")
    cost = label_proposals(scenes(), store, views, CONFIG, workers=workers)
    return store, views, cost


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    return folder, *_label(folder)


def test_each_first_candidate_has_a_row_and_pushes_are_followed_only_where_no_grasp_worked(labelled):
    folder, store, views, cost = labelled
    records = candidate_labels(scenes(), store, views, CONFIG)
    by_scene = {}
    for r in records:
        by_scene.setdefault(r["scene_sha256"], []).append(r)
    open_can, shelved = (by_scene[scene_sha256(s)] for s in scenes())
    assert [r["candidate"]["action"] for r in open_can] == ["grasp", "push", "pull"]
    top = open_can[0]
    assert top["success"], "a top grasp from the can's visible top lifts a can in the open"
    assert all(r["after"] is None for r in open_can)  # a grasp alone worked: no follow-ups
    assert not shelved[0]["success"]  # the board stops the hand from above
    movers = [r for r in shelved if r["candidate"]["action"] != "grasp"]
    assert movers and all(r["after"] is not None and len(r["after"]) >= 1 for r in movers)
    assert cost.simulated == len(store.entries)  # one new row per job: a follow-up's push is known
    assert cost.per_candidate() > 0 and cost.stored == 0
    rows = [store.get(scene_sha256(scenes()[1]), row_tokens) for row_tokens in _follow_tokens(store)]
    assert rows and all(len(r["tokens"]) == 2 and r["prefix"][0] in ("push", "pull") for r in rows)


def _follow_tokens(store: PathStore) -> list[list[str]]:
    return [row["tokens"] for row in store.entries.values() if len(row["tokens"]) == 2]


def test_a_rerun_simulates_nothing_and_two_workers_write_the_same_rows(labelled, tmp_path: Path):
    folder, store, views, _ = labelled
    again = label_proposals(scenes(), PathStore(folder / "paths.jsonl"), views, CONFIG)
    assert again.simulated == 0 and again.stored == len(store.entries)
    parallel, _, _ = _label(tmp_path, workers=2)
    assert parallel.entries == store.entries and parallel.mismatches == 0


def test_a_killed_run_resumes_to_the_same_store(labelled, tmp_path: Path):
    """Killed after the first layout and in the middle of writing a row (a torn last line): the
    rerun keeps what was whole, simulates the rest and ends with the uninterrupted run's rows."""
    folder, store, _, _ = labelled
    lines = (folder / "paths.jsonl").read_text().splitlines(keepends=True)
    first = scene_sha256(scenes()[0])
    kept = [line for line in lines if f'"scene_sha256": "{first}"' in line]
    assert 0 < len(kept) < len(lines)
    torn = next(line for line in lines if line not in kept)
    (tmp_path / "paths.jsonl").write_text("".join(kept) + torn[: len(torn) // 2])
    views = ObservationStore(tmp_path / "views")
    resumed = label_proposals(scenes(), PathStore(tmp_path / "paths.jsonl"), views, CONFIG)
    assert resumed.stored == len(kept) and resumed.simulated == len(lines) - len(kept)
    assert PathStore(tmp_path / "paths.jsonl").entries == store.entries


def test_the_sampler_draws_the_same_candidates_at_a_point_in_any_process():
    a = point_rng(0, "abc", ["push@1s1:x"]).random(3)
    assert (a == point_rng(0, "abc", ["push@1s1:x"]).random(3)).all()
    assert not (a == point_rng(0, "abc", []).random(3)).all()
    assert not (a == point_rng(1, "abc", ["push@1s1:x"]).random(3)).all()


def test_examples_see_each_labelled_candidate_through_the_oracle_and_are_cached(labelled, tmp_path: Path):
    from scenegen.experiment.proposal_data import candidate_label, examples
    from scenegen.policy.proposal_model import CHANNELS, CROP, FEATURES

    folder, store, views, _ = labelled
    rendered = []
    first = examples(scenes(), store, views, tmp_path / "crops", CONFIG, progress=rendered.append)
    records = candidate_labels(scenes(), store, views, CONFIG)
    assert len(first) == len(records) and len(rendered) == 2  # one rendering per layout
    assert first.crops.shape == (len(records), CHANNELS, CROP, CROP) and first.features.shape[1] == FEATURES
    assert first.labels.tolist() == [float(candidate_label(r)) for r in records]
    assert first.labels[0] == 1.0  # the open can's top grasp
    centre = first.crops[0, 4, CROP // 2 - 2 : CROP // 2 + 3, CROP // 2 - 2 : CROP // 2 + 3]
    assert centre.mean() > 0.5  # the front camera's mask channel: the grasp point is on the can
    again = []
    second = examples(scenes(), store, views, tmp_path / "crops", CONFIG, progress=again.append)
    assert not again and np.array_equal(second.crops, first.crops)


def test_the_proposal_model_in_closed_loop_serves_labelled_first_attempts_and_reruns_free(labelled, tmp_path):
    from scenegen.experiment.closed_loop import Workers
    from scenegen.experiment.proposal_data import examples
    from scenegen.experiment.proposal_loop import evaluate_proposals
    from scenegen.experiment.sequences import Cost
    from scenegen.policy.proposal_model import train_model

    folder, store, views, _ = labelled
    data = examples(scenes(), store, views, tmp_path / "crops", CONFIG)
    train_model(data.crops, data.features, data.labels, steps=30, batch=8, width=4).save(tmp_path / "model")
    labelled_tokens = {tuple(row["tokens"]) for row in store.entries.values()}
    observations = ObservationStore(tmp_path / "decisions")
    cost = Cost()
    with Workers(1) as pool:
        records = evaluate_proposals(
            tmp_path / "model", scenes(), store, observations, pool, config=CONFIG, cost=cost
        )
        assert [r["scene_sha256"] for r in records] == [scene_sha256(s) for s in scenes()]
        for r in records:
            assert (
                1 <= len(r["plans"]) <= 3 and (r["plans"][0],) in labelled_tokens
            )  # the labels' first candidates
            assert r["success"] == store.get(r["scene_sha256"], r["plans"])["success"]
            assert r["first_attempt"] == (r["success"] and len(r["plans"]) == 1)
        assert cost.shared >= len(scenes()) and cost.attempts == sum(len(r["plans"]) for r in records)
        again = Cost()
        assert (
            evaluate_proposals(
                tmp_path / "model", scenes(), store, observations, pool, config=CONFIG, cost=again
            )
            == records
        )
        assert again.simulated == 0 and again.cpu["observe"] == 0.0  # every decision and attempt is stored


def test_no_label_set_holds_a_test_panel_layout():
    """Issue 63, acceptance 5: every layout the labels, the models and the curves read (the label
    sets) is off version 2's test side; validation is its validation side (which draws on version 1's
    spent panels, by version 2's design), and the training and curve sets are off version 1's too."""
    from scenegen.experiment.proposal_labels import LABEL_SETS, label_layouts
    from scenegen.policy.panels import panel_scene_ids
    from scenegen.policy.panels_v2 import load_panels_v2, panel_id

    v2 = load_panels_v2()
    test_v2 = {i for ids in v2["test"].values() for i in ids}
    validation = {i for ids in v2["validation"].values() for i in ids}
    sets = label_layouts(LABEL_SETS)
    for name, layouts in sets.items():
        ids = {panel_id(s) for s in layouts}
        assert not ids & test_v2, f"{name} holds a version 2 test layout"
        reference = {s.scene_id for s in layouts if panel_id(s).startswith("reference/")}
        assert name == "validation" or not reference & panel_scene_ids(), f"{name} holds a version 1 panel"
        assert (name == "validation") == (ids <= validation), name
