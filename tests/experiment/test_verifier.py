"""The learned verifier (issue 46, point 3): tries labelled from what the checks and predicates said,
collected from real batches of the generator on the tuning half (never the held-out one), a verifier
trained on them whose loss falls, and its gradient steering the generator's sampling: weight 0 is the
generator as it was, a positive weight moves the samples, a pinned sha256 that differs is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from scenegen.core.files import load_rows
from scenegen.diffusion.verifier import LABELS, load_verifier, try_labels
from scenegen.experiment import verifier_data
from scenegen.paths import PROJECT_ROOT
from scenegen.runner.config import ConfigError, load_pipeline
from scenegen.schema.condition import Condition
from scenegen.schema.scene import Rejection, TagValue

RECIPE = PROJECT_ROOT / "pipelines" / "generator_v3.yaml"


def test_a_try_is_labelled_by_what_was_measured():
    condition = Condition(
        task="retrieve",
        target="mug",
        tags={"near_edge": "required", "clutter": "required", "occluded": "forbidden"},
    )
    index = {label: i for i, label in enumerate(LABELS)}
    unmet = Rejection(
        proposal_index=0,
        stage="tag",
        label="condition_unmet",
        check="condition",
        detail="required near_edge = 0.2 m (threshold 0.03); "
        "forbidden occluded = 0.7 fraction (threshold 0.5)",
    )
    values, known = try_labels(condition, None, unmet)
    assert known[index["accepted"]] and values[index["accepted"]] == 0
    assert known[index["near_edge"]] and values[index["near_edge"]] == 0
    assert known[index["clutter"]] and values[index["clutter"]] == 1  # required and not named: held
    assert known[index["occluded"]] and values[index["occluded"]] == 1  # forbidden and named: held
    assert not known[index["toppled"]]  # neither asked nor measured in the row
    collision = Rejection(proposal_index=0, stage="check", label="collision", check="collision", detail="a~b")
    values, known = try_labels(condition, None, collision)
    assert known.sum() == 1 and values[0] == 0
    tags = {t: TagValue(holds=t == "clutter", value=0.0, threshold=0.0, unit="") for t in LABELS[1:]}
    values, known = try_labels(condition, tags, None)
    assert (
        known.all() and values[0] == 1 and values[index["clutter"]] == 1 and values[index["near_edge"]] == 0
    )


def test_the_held_out_half_is_never_collected():
    with pytest.raises(ValueError, match="tuning half only"):
        verifier_data.requests_for([], "heldout", 30)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("verifier")
    rows = load_rows(PROJECT_ROOT / "assets" / "reference" / "reference.parquet", "train")
    jobs = verifier_data.jobs(RECIPE, verifier_data.requests_for(rows, "tuning", 2), [])
    verifier_data.collect_all(out, jobs, tries=6, scenes=1, log=lambda _: None)
    summary = verifier_data.train(out, RECIPE, steps=80)
    return out, summary


def test_tries_are_collected_per_request_and_the_verifier_trains(trained):
    out, summary = trained
    data, cpu = verifier_data.load_tries(out)
    assert len(list((out / "tries").glob("*.npz"))) == 2 and cpu > 0
    assert 2 <= len(data["x0"]) <= 12 and data["known"][:, 0].all()
    assert summary["examples"] + summary["validation_examples"] == len(data["x0"])
    assert summary["losses"][-1] < summary["losses"][0]
    model = load_verifier(out / "verifier")
    assert model.config.width == data["x0"].shape[1]
    before = sorted((out / "tries").glob("*.npz"))
    stamps = [p.stat().st_mtime_ns for p in before]
    jobs = [(RECIPE, {})] * 2
    verifier_data.collect_all(out, jobs, tries=6, scenes=1, log=lambda _: None)  # resumed: nothing redone
    assert [p.stat().st_mtime_ns for p in before] == stamps


def recipe_with(tmp_path: Path, folder: Path, weight: float, sha: str | None = None) -> Path:
    raw = yaml.safe_load(RECIPE.read_text())
    raw["proposer"].update(verifier=str(folder), verifier_weight=weight, repairs=0, project=False)
    if sha:
        raw["proposer"]["verifier_sha256"] = sha
    path = tmp_path / f"recipe_{weight}.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_the_verifier_steers_sampling_only_with_a_weight(trained, tmp_path):
    from scenegen.propose.diffusion import DiffusionProposer

    out, summary = trained
    proposals = {}
    for name, path in [
        ("plain", RECIPE),
        ("zero", recipe_with(tmp_path, out / "verifier", 0.0)),
        ("guided", recipe_with(tmp_path, out / "verifier", 5.0, summary["sha256"])),
    ]:
        config = load_pipeline(path, {"n": 1})
        proposer = DiffusionProposer(config.proposer, config.catalog())
        proposals[name] = proposer.propose(config.condition, range(8), 0)
    assert [p.objects for p in proposals["zero"]] == [p.objects for p in proposals["plain"]]
    moved = [
        np.abs(np.subtract(a.position, b.position)).max()
        for p, q in zip(proposals["guided"], proposals["plain"], strict=True)
        for a, b in zip(p.objects, q.objects, strict=False)
    ]
    assert max(moved) > 1e-4  # the gradient moved the samples


def test_a_verifier_pinned_to_other_weights_is_refused(trained, tmp_path):
    out, _ = trained
    with pytest.raises(ConfigError, match="verifier_sha256"):
        load_pipeline(recipe_with(tmp_path, out / "verifier", 1.0, "0" * 64), {"n": 1})
    raw = yaml.safe_load(RECIPE.read_text())
    raw["proposer"]["verifier_weight"] = 1.0  # a weight without a verifier
    path = tmp_path / "no_verifier.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match="verifier_weight"):
        load_pipeline(path, {"n": 1})
    with pytest.raises(ConfigError, match="verifier"):
        load_pipeline(recipe_with(tmp_path, tmp_path / "missing", 1.0), {"n": 1})
