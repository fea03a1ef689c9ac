"""Acceptance of user assets end to end: robosuite's six object meshes (which no test of this project
authored) imported with one command each, as docs/assets.md and `make robosuite-objects` do, then a
rendered batch of 20 rare-case scenes with them, re-simulated from its files and audited."""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from pathlib import Path

import pytest
from scenes import resimulated

from scenegen.cli import main
from scenegen.paths import PROJECT_ROOT

# (file, asset name, mass kg, texture): the Makefile's robosuite-objects target, line for line
OBJECTS = (
    ("bottle", "rs_bottle", "0.3", "glass"),
    ("bread", "rs_bread", "0.1", "bread"),
    ("can", "rs_can", "0.35", "soda"),
    ("cereal", "rs_cereal", "0.4", "cereal"),
    ("lemon", "rs_lemon", "0.1", "lemon"),
    ("milk", "rs_milk", "0.5", "ceramic"),
)
MAX_PENETRATION = 1e-3  # m, deepest contact at the settled keyframe
MAX_OBJECT_MOVE = 5e-3  # m, in 2 s of passive simulation


@pytest.fixture(scope="module")
def robosuite_batch(tmp_path_factory):
    """(working dir, batch) after importing the six meshes and generating pipelines/robosuite_objects.yaml."""
    import robosuite

    source = Path(robosuite.__file__).parent / "models" / "assets"
    work = tmp_path_factory.mktemp("user_assets")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(work)
        mp.setenv("SCENEGEN_CACHE", os.environ.get("SCENEGEN_CACHE", str(work / "cache")))
        for mesh, name, mass, texture in OBJECTS:
            argv = [
                "assets",
                "add",
                str(source / "objects" / "meshes" / f"{mesh}.obj"),
                "--category",
                "grocery",
            ]
            argv += ["--name", name, "--mass", mass, "--texture", str(source / "textures" / f"{texture}.png")]
            assert main([*argv, "--catalog", "runs/robosuite_objects/catalog.yaml"]) == 0, name
        recipe = work / "robosuite_objects.yaml"
        shutil.copy(PROJECT_ROOT / "pipelines" / "robosuite_objects.yaml", recipe)
        argv = ["generate", str(recipe), "--out", "runs/robosuite_batch", "--workers", "2", "--quiet"]
        assert main(argv) == 0
        yield work, work / "runs" / "robosuite_batch"


def test_every_imported_asset_appears_three_or_more_as_targets_and_the_rare_tag_holds(robosuite_batch):
    _, batch = robosuite_batch
    records = [json.loads(p.read_text()) for p in sorted(batch.glob("scene_*/scene.json"))]
    assert len(records) == 20
    seen = {o["asset"] for r in records for o in r["objects"]}
    assert seen == {name for _, name, _, _ in OBJECTS}
    targets = Counter(next(o["asset"] for o in r["objects"] if o["name"] == r["target"]) for r in records)
    assert len(targets) >= 3, targets
    assert all(r["tags"]["toppled"]["holds"] for r in records)
    assert all(
        r["provenance"]["catalogs"][1]["path"] == "runs/robosuite_objects/catalog.yaml" for r in records
    )


def test_each_scene_loads_standalone_rests_and_does_not_penetrate(robosuite_batch, tmp_path, monkeypatch):
    _, batch = robosuite_batch
    monkeypatch.chdir(tmp_path)  # scene.xml references only the batch's _assets/
    for scene in sorted(batch.glob("scene_*")):
        deepest, moved = resimulated((scene / "scene.xml").resolve())
        assert deepest <= MAX_PENETRATION, f"{scene.name}: {deepest * 1e3:.2f} mm"
        assert moved <= MAX_OBJECT_MOVE, f"{scene.name}: an object moved {moved * 1e3:.2f} mm"


def test_the_batch_and_the_user_catalog_pass_the_audit(robosuite_batch, monkeypatch, capsys):
    work, batch = robosuite_batch
    monkeypatch.chdir(work)
    assert main(["audit", str(batch / "manifest.yaml")]) == 0, capsys.readouterr().out
    stray = work / "runs" / "robosuite_objects" / "rs_bread" / "notes.txt"
    stray.write_text("a file no catalog entry lists")
    assert main(["audit", str(batch / "manifest.yaml")]) != 0
    assert "rs_bread/notes.txt" in capsys.readouterr().out
    stray.unlink()


def test_the_batch_exports_and_labels_like_a_bundled_one(robosuite_batch, monkeypatch):
    import pyarrow.parquet as pq

    work, batch = robosuite_batch
    monkeypatch.chdir(work)  # the scenes name their user catalog relative to where they were made
    assert main(["export", str(batch), "--format", "webdataset", "--out", str(work / "wds")]) == 0
    assert any((work / "wds").glob("*.tar"))
    labels = work / "labels.parquet"
    argv = ["label", str(batch), "--out", str(labels), "--limit", "1", "--primitives", "top_grasp", "--quiet"]
    assert main(argv) == 0
    rows = pq.read_table(labels).to_pylist()
    assert len(rows) == 1 and rows[0]["target_category"] == "grocery"
