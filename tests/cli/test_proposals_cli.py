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


def _episodes(path: Path, outcomes: list[tuple[bool, bool]], tags=(["toppled"], [], ["toppled"], [])) -> Path:
    rows = [
        {"scene_sha256": f"{k:064x}", "first_attempt": first, "success": whole, "tags": list(t)}
        for k, ((first, whole), t) in enumerate(zip(outcomes, tags, strict=True))
    ]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_compare_pairs_two_runs_by_layout_and_refuses_runs_on_other_layouts(tmp_path: Path, capsys):
    a = _episodes(tmp_path / "a.jsonl", [(True, True), (False, True), (True, True), (False, False)])
    b = _episodes(tmp_path / "b.jsonl", [(False, True), (False, False), (True, True), (False, False)])
    assert main(["proposals", "compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    table = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    first, whole = table["first_attempt"]["all"], table["success"]["all"]
    assert (first["first"], first["second"], first["difference"]["mean"]) == (0.5, 0.25, 0.25)
    assert (whole["first"], whole["second"], whole["difference"]["mean"]) == (0.75, 0.5, 0.25)
    assert whole["difference"]["low"] <= 0.25 <= whole["difference"]["high"]
    assert table["success"]["toppled"]["difference"]["scenes"] == 2
    assert table["success"]["nominal"]["difference"]["mean"] == 0.5
    assert "| success | all | 4 | 0.750 | 0.500 | +25.0 [" in (tmp_path / "cmp" / "compare.md").read_text()
    capsys.readouterr()
    short = tmp_path / "c.jsonl"
    short.write_text("".join(a.read_text().splitlines(keepends=True)[:3]))
    assert main(["proposals", "compare", str(short), str(b), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "different layouts (1 on one side only)" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad").exists()


def test_perception_gap_takes_candidates_only_with_a_proposal_model(tmp_path: Path, capsys):
    argv = ["experiment", "perception-gap", "--candidates", "4", "2", "1", "1"]
    argv += ["--out", str(tmp_path / "gap")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--candidates" in err and "with --proposals" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "gap").exists()


def test_policy_eval_acts_by_the_committed_proposal_model_and_reruns_free(tmp_path: Path, capsys):
    """`scenegen policy eval --proposals`: the committed model on one reference scene through the
    simulator's masks writes its episode and summary; a rerun decides and simulates nothing new
    (the stores beside them) and says the same; giving both or neither action side is refused."""
    from scenegen.paths import ASSETS_DIR

    model = ASSETS_DIR / "proposals" / "natural600"
    out = tmp_path / "eval"
    argv = ["policy", "eval", "--proposals", str(model), "--scenes", "assets/reference/reference.parquet"]
    argv += ["--n", "1", "--outside-panels", "--retrieval", "oracle", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    episode = json.loads((out / "episodes.jsonl").read_text())
    assert summary["episodes"] == 1 and summary["policy"] == "proposals" and summary["retrieval"] == "oracle"
    assert (
        episode["policy"] == "proposals" and episode["actions"] and summary["success"] == episode["success"]
    )
    rows = (out / "paths.jsonl").read_text()
    assert main(argv) == 0
    assert (out / "paths.jsonl").read_text() == rows and json.loads(
        (out / "summary.json").read_text()
    ) == summary
    capsys.readouterr()
    for extra in (["--checkpoint", "assets/policy/baseline"], []):
        both = [a for a in argv if a not in ("--proposals", str(model))] if not extra else [*argv, *extra]
        assert main([*both[:2], *both[2:]]) == 2
        err = capsys.readouterr().err
        assert "one of them" in err and len(err.strip().splitlines()) == 1
