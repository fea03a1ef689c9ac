"""A run killed while it starts a batch leaves a folder the next run starts or resumes.

pipeline.yaml marks a batch and is written first; a run killed before its write completed leaves
nothing or the write's temp file, one killed just after it leaves pipeline.yaml without the logs.
(CI once saw `generate` killed in that window, and every later run refused the folder as "not a
scenegen batch".)
"""

from __future__ import annotations

from pathlib import Path

import pytest

from scenegen.store.batch import BatchStore, ResumeState, StoreError

RECIPE = "name: t\nn: 2\n"
SKELETON = {"_assets", "index.jsonl", "rejections.jsonl", "pipeline.yaml"}


def names(root: Path) -> set[str]:
    return {p.name for p in root.iterdir()}


def test_a_new_batch_holds_its_skeleton(tmp_path: Path):
    root = tmp_path / "b"
    assert BatchStore(root).open(RECIPE) == ResumeState()
    assert names(root) == SKELETON and (root / "pipeline.yaml").read_text() == RECIPE


def test_a_start_killed_inside_the_recipe_write_starts_anew(tmp_path: Path):
    root = tmp_path / "b"
    root.mkdir()
    (root / ".pipeline.yaml.tmp4242").write_text("name: t\nn:")  # torn
    assert BatchStore(root).open(RECIPE) == ResumeState()
    assert names(root) == SKELETON


def test_a_start_killed_after_the_recipe_resumes_and_makes_the_rest(tmp_path: Path):
    root = tmp_path / "b"
    root.mkdir()
    (root / "pipeline.yaml").write_text(RECIPE)
    assert BatchStore(root).open(RECIPE) == ResumeState()
    assert names(root) == SKELETON


def test_a_folder_of_other_files_is_still_refused(tmp_path: Path):
    root = tmp_path / "b"
    root.mkdir()
    (root / "notes.txt").write_text("mine")
    with pytest.raises(StoreError, match="not a scenegen batch"):
        BatchStore(root).open(RECIPE)
    assert names(root) == {"notes.txt"}
