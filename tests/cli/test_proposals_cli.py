"""`scenegen proposals label | train | eval` on one validation layout: the label folder records its
settings and refuses others, training reads them, eval writes the first-ranked figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scenegen.cli import main


@pytest.fixture(scope="module")
def labels(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("proposals") / "labels"
    argv = ["proposals", "label", "--layouts", "validation", "--limit", "1", "--sampler", "3", "1", "0", "0"]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    return out


def test_a_label_folder_keeps_its_settings(labels: Path, capsys):
    settings = json.loads((labels / "labels.json").read_text())
    assert settings["sampler"] == {"top": 3, "side": 1, "push": 0, "pull": 0} and settings["physics"] == "dt5"
    rows = (labels / "paths.jsonl").read_text().splitlines()
    assert 1 <= len(rows) <= 4 and all(json.loads(r)["candidate"]["action"] == "grasp" for r in rows)
    argv = ["proposals", "label", "--layouts", "validation", "--limit", "1", "--sampler", "2", "1", "0", "0"]
    assert main([*argv, "--out", str(labels), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "labelled with sampler 3 1 0 0 seed 0" in err and len(err.strip().splitlines()) == 1


def test_train_then_eval_looks_up_the_first_ranked_candidate(labels: Path, tmp_path: Path, capsys):
    model, out = tmp_path / "model", tmp_path / "eval"
    shared = ["--layouts", "validation", "--limit", "1", "--labels", str(labels), "--quiet"]
    rows = [json.loads(r) for r in (labels / "paths.jsonl").read_text().splitlines()]
    assert any(r["success"] for r in rows), "the first validation layout: a grasp of the four lifts it"
    code = main(["proposals", "train", *shared, "--out", str(model), "--steps", "20", "--width", "4"])
    assert code == 0 and (model / "model.safetensors").is_file()
    assert main(["proposals", "eval", *shared, "--model", str(model), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["by_tag"]["all"]["layouts"] == 1
    assert summary["by_tag"]["all"]["ceiling"] == 1.0
    assert summary["by_tag"]["all"]["success"] in (0.0, 1.0)


def test_training_without_labels_says_what_to_run(tmp_path: Path, capsys):
    argv = ["proposals", "train", "--labels", str(tmp_path), "--out", str(tmp_path / "m"), "--quiet"]
    assert main(argv) == 2
    assert "run `scenegen proposals label" in capsys.readouterr().err


def test_perception_gap_with_a_folder_that_is_not_a_proposal_model_says_so(tmp_path: Path, capsys):
    argv = ["experiment", "perception-gap", "--proposals", str(tmp_path), "--out", str(tmp_path / "gap")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "not a proposal model" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "gap").exists()
