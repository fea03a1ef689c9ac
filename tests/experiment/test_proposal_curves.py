"""The proposal model's learning curves (issue 63, point 5) on two labelled validation layouts: a
job trains once and scores through the oracle and the default head; a rerun reads its scores; two
sets trained on the same layouts lead each other by nothing; a layout without labels is refused."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from scenegen.env.scenes import scene_sha256
from scenegen.experiment.proposal_curves import SIGHTS, ProposalJob, chooser_results, chooser_rows, run_job
from scenegen.experiment.proposal_labels import LabelConfig, label_layouts, label_proposals, open_labels
from scenegen.experiment.retrieval_curves import curve_results, curve_table, leads
from scenegen.experiment.sequences import NOMINAL, ObservationStore
from scenegen.manipulation.proposals import SamplerConfig
from scenegen.perception.retrieval import DEFAULT_HEAD

CONFIG = LabelConfig(sampler=SamplerConfig(top=3, side=1, push=0, pull=0))


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    folder = tmp_path_factory.mktemp("curves") / "labels"
    scenes = label_layouts(["validation"], limit=3)["validation"]
    config, store, views = open_labels(folder, CONFIG)
    label_proposals(scenes[:2], store, views, config)
    return folder, scenes


def test_a_job_trains_once_scores_through_each_sight_and_identical_sets_lead_by_nothing(labelled, tmp_path):
    labels, scenes = labelled
    layouts = scenes[:2]
    kwargs = {"scored": layouts, "train": layouts, "steps": 30}
    records = []
    for set_name in ("natural", "rare_rich"):
        records += run_job(ProposalJob(set_name, 2, 0), tmp_path, labels, DEFAULT_HEAD, **kwargs)
    assert [r["job"] for r in records] == [f"{s}/{n}_2_0" for n in ("natural", "rare_rich") for s in SIGHTS]
    for r in records:
        assert [row["layout"] for row in r["rows"]] == [scene_sha256(s) for s in layouts]
        assert all(row["set"] == "curve" and isinstance(row["success"], bool) for row in r["rows"])
        assert all(row["any"] or not row["success"] for row in r["rows"])  # a pick cannot beat the best
    model = tmp_path / "natural_2_0" / "model" / "model.safetensors"
    stamp = model.stat().st_mtime_ns
    again = run_job(ProposalJob("natural", 2, 0), tmp_path, labels, DEFAULT_HEAD, **kwargs)
    assert again == records[:2] and model.stat().st_mtime_ns == stamp  # read, not trained again
    results = curve_results(records, replicates=50, scored_sets=("curve",), designs=SIGHTS, value="success")
    for sight in SIGHTS:
        cell = results["scored"]["curve"][sight]["all"][2]
        assert cell["lead"]["mean"] == 0.0 and cell["natural"]["mean"] == cell["rare_rich"]["mean"]
    assert leads(results, "curve")["oracle"]["flat"] is True
    assert "| oracle | all | 2 | 2 |" in curve_table(results, "curve")


def test_a_set_with_a_layout_not_yet_labelled_is_refused(labelled, tmp_path: Path):
    labels, scenes = labelled
    with pytest.raises(
        ValueError, match="1 of the 3 layouts .* have no labels: run `scenegen proposals label"
    ):
        run_job(
            ProposalJob("natural", 3, 0), tmp_path, labels, None, scored=scenes[:2], train=scenes, steps=5
        )
    assert not (tmp_path / "natural_3_0" / "scores.json").exists()


def test_a_layout_whose_target_is_not_seen_is_no_gap_and_scores_a_failure(labelled, tmp_path: Path):
    """A first decision that sees no target proposes nothing ([] in the view store): nothing to label,
    so the set is complete without it, and a scored layout of that kind is the policy's failure (every
    policy is scored over the same layouts)."""
    labels, scenes = labelled
    labels = shutil.copytree(labels, tmp_path / "labels")  # the shared folder stays as labelled
    config, _, views = open_labels(labels)
    unseen = scenes[2]
    views.put(ObservationStore.key(scene_sha256(unseen), (), NOMINAL, config.inputs(config.sampler)), None,
              {"candidates": []})  # fmt: skip
    job = ProposalJob("natural", 3, 0)
    records = run_job(job, tmp_path / "models", labels, None, scored=scenes, train=scenes, steps=5)
    for record in records:
        last = record["rows"][-1]
        assert last["layout"] == scene_sha256(unseen) and not last["success"] and not last["any"]


def test_the_choosers_first_attempt_beside_the_curves_is_simulated_once(labelled, tmp_path: Path):
    _, scenes = labelled
    layouts = scenes[:2]
    rows = chooser_rows(tmp_path / "chooser", DEFAULT_HEAD, scored=layouts)
    assert list(rows) == list(SIGHTS)
    for sight_rows in rows.values():
        assert [r["layout"] for r in sight_rows] == [scene_sha256(s) for s in layouts]
        assert all(r["success"] == r["any"] for r in sight_rows)
    stored = (tmp_path / "chooser" / "paths.jsonl").read_text()
    assert 1 <= len(stored.splitlines()) <= 4  # one first attempt per layout and sight, shared where alike
    assert chooser_rows(tmp_path / "chooser", DEFAULT_HEAD, scored=layouts) == rows
    assert (tmp_path / "chooser" / "paths.jsonl").read_text() == stored  # a rerun simulates nothing
    table = chooser_results(rows, replicates=50)
    oracle = table["oracle"]["all"]
    assert oracle["scenes"] == 2 and oracle["mean"] == np.mean([r["success"] for r in rows["oracle"]])
