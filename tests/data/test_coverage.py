"""Coverage tables: exact counts and sparse marks from a Parquet table, a batch directory and a manifest;
the chart PNG; the CLI entry point; manifests naming data outside their folder are refused."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from scenegen.cli import main
from scenegen.data.coverage import CoverageError, coverage_table
from scenegen.data.project_manifest import DATASHEET, TRANSFER
from scenegen.manifest import Counts, Manifest, Source, write_manifest
from scenegen.manifest.schema import FileChecksum
from scenegen.schema.condition import TAGS

# (task, tags held, scenes): 48 retrieve scenes, 19 upright, no clear; one group holds two tags.
GROUPS = [
    ("retrieve", ["nominal"], 25),
    ("retrieve", ["near_edge", "clutter"], 20),
    ("retrieve", ["on_floor"], 3),
    ("upright", ["toppled"], 19),
]


def scenes_of(groups) -> list[tuple[str, list[str]]]:
    return [(task, tags) for task, tags, n in groups for _ in range(n)]


def write_parquet(path: Path, scenes: list[tuple[str, list[str]]]) -> Path:
    """A table with the columns coverage reads (and one it does not), one row per scene."""
    columns = {"origin": ["real"] * len(scenes), "task": [task for task, _ in scenes]}
    for tag in TAGS:
        columns[f"tag_{tag}"] = [tag in tags for _, tags in scenes]
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(columns), path)
    return path


def write_batch(root: Path, scenes: list[tuple[str, list[str]]]) -> Path:
    """A batch directory with what coverage reads: index.jsonl rows and each scene's condition.task."""
    root.mkdir(parents=True)
    rows = []
    for i, (task, tags) in enumerate(scenes):
        scene_id = f"scene_{i:06d}"
        (root / scene_id).mkdir()
        record = {"scene_id": scene_id, "condition": {"task": task, "target": "spoon", "tags": {}}}
        (root / scene_id / "scene.json").write_text(json.dumps(record))
        rows.append(json.dumps({"scene_id": scene_id, "proposal_index": i, "tags": sorted(tags)}))
    (root / "index.jsonl").write_text("".join(row + "\n" for row in rows))
    return root


def row_of(text: str, first: str) -> list[str]:
    return next(line.split() for line in text.splitlines() if line.split()[:1] == [first])


def test_parquet_counts_and_sparse_marks(tmp_path):
    table = coverage_table(write_parquet(tmp_path / "ref.parquet", scenes_of(GROUPS)))
    assert table.total == 67
    assert dict(table.scenes) == {"retrieve": 48, "upright": 19}
    assert table.tasks == ("retrieve", "upright", "clear")
    expected = {
        ("retrieve", "nominal"): 25,
        ("retrieve", "near_edge"): 20,
        ("retrieve", "clutter"): 20,
        ("retrieve", "on_floor"): 3,
        ("upright", "toppled"): 19,
    }
    for task in table.tasks:
        for tag in TAGS:
            assert table.count(task, tag) == expected.get((task, tag), 0), (task, tag)
    # 1 % of 67 scenes is under the count threshold, so the count decides: 20 is enough, 19 is not.
    not_sparse = {("retrieve", "nominal"), ("retrieve", "near_edge"), ("retrieve", "clutter")}
    assert set(table.sparse_cells()) == {(t, g) for t in table.tasks for g in TAGS} - not_sparse
    text = table.format_table()
    assert row_of(text, "task") == ["task", "scenes", *TAGS]
    assert row_of(text, "retrieve") == [
        "retrieve",
        "48",
        "20",
        "0*",
        "0*",
        "0*",
        "20",
        "0*",
        "0*",
        "3*",
        "25",
    ]
    assert row_of(text, "upright") == ["upright", "19", "0*", "0*", "19*", "0*", "0*", "0*", "0*", "0*", "0*"]
    assert row_of(text, "clear") == ["clear", "0", *["0*"] * len(TAGS)]
    assert row_of(text, "all") == ["all", "67", "20", "0", "19", "0", "20", "0", "0", "3", "25"]


def test_sparse_threshold_and_share(tmp_path):
    scenes = scenes_of(GROUPS)
    lenient = coverage_table(write_parquet(tmp_path / "ref.parquet", scenes), sparse=3)
    assert not lenient.is_sparse("retrieve", "on_floor") and not lenient.is_sparse("upright", "toppled")
    assert lenient.is_sparse("clear", "nominal")
    # Under 1 % of all scenes is sparse whatever the count: 25 of 2500 is exactly 1 %, 24 of 2499 is not.
    for rare, sparse in ((25, False), (24, True)):
        big = scenes_of([("clear", ["nominal"], 2475), ("clear", ["stacked"], rare)])
        table = coverage_table(write_parquet(tmp_path / f"big{rare}.parquet", big))
        assert table.count("clear", "stacked") == rare > 20
        assert table.is_sparse("clear", "stacked") is sparse
        assert table.sparse_below() == 25


def test_batch_directory_counts_like_the_same_scenes_in_parquet(tmp_path):
    scenes = scenes_of(GROUPS)
    batch = coverage_table(write_batch(tmp_path / "batch", scenes))
    parquet = coverage_table(write_parquet(tmp_path / "ref.parquet", scenes))
    assert batch.counts == parquet.counts and batch.scenes == parquet.scenes and batch.total == 67
    assert batch.sparse_cells() == parquet.sparse_cells()


def test_batch_with_a_missing_scene_json_is_an_error(tmp_path):
    root = write_batch(tmp_path / "batch", scenes_of(GROUPS[:1]))
    (root / "scene_000003" / "scene.json").unlink()
    with pytest.raises(CoverageError, match=r"scene_000003/scene\.json: missing, but index\.jsonl line 4"):
        coverage_table(root)


def _source(name: str, location: str) -> Source:
    return Source(
        name=name,
        origin="real",
        location=location,
        counts=Counts(scenes=0),
        checksums=FileChecksum(sha256="0" * 64),
        collection="hand-written test scenes",
    )


def _project(sources: list[Source]) -> Manifest:
    return Manifest(kind="project", sources=sources, datasheet=DATASHEET, transfer=TRANSFER)


def test_manifest_sums_its_sources(tmp_path):
    write_batch(tmp_path / "batch", scenes_of(GROUPS))
    write_parquet(tmp_path / "data" / "real.parquet", scenes_of([("clear", ["occluded", "low_light"], 30)]))
    sources = [
        _source("batch", "batch"),
        _source("real", "data/real.parquet"),
        _source("later", "not_yet_here"),
    ]
    write_manifest(tmp_path / "data_manifest.yaml", _project(sources))
    table = coverage_table(tmp_path / "data_manifest.yaml")
    assert table.total == 97
    assert dict(table.scenes) == {"retrieve": 48, "upright": 19, "clear": 30}
    assert table.count("clear", "occluded") == table.count("clear", "low_light") == 30
    assert table.count("retrieve", "near_edge") == 20
    assert table.skipped == ("later (not_yet_here: missing)",)
    assert "not counted: later (not_yet_here: missing)" in table.format_table()


def test_batch_manifest_counts_its_own_batch(tmp_path):
    root = write_batch(tmp_path / "batch", scenes_of(GROUPS))
    write_manifest(root / "manifest.yaml", Manifest(kind="batch", sources=[_source("batch", ".")]))
    assert coverage_table(root / "manifest.yaml").counts == coverage_table(root).counts


@pytest.mark.parametrize("location", ["../outside", "/tmp", "inside/../../outside", "link"])
def test_manifest_location_outside_its_folder_is_refused(tmp_path, location):
    folder = tmp_path / "project"
    folder.mkdir()
    write_batch(tmp_path / "outside", scenes_of(GROUPS))
    (folder / "link").symlink_to(tmp_path / "outside")  # a link out of the folder is outside too
    write_manifest(folder / "data_manifest.yaml", _project([_source("x", location)]))
    with pytest.raises(CoverageError, match="outside the manifest's folder") as info:
        coverage_table(folder / "data_manifest.yaml")
    assert "\n" not in str(info.value) and "source 'x'" in str(info.value)


def test_bad_sources_are_one_line_errors(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "empty").mkdir()
    pq.write_table(pa.table({"task": ["retrieve"]}), tmp_path / "other.parquet")
    (tmp_path / "broken.yaml").write_text("kind: [")
    (tmp_path / "wrong.yaml").write_text("kind: nonsense\n")
    cases = {
        "missing": "no such file or directory",
        "notes.txt": "not a Parquet table, batch directory or manifest YAML",
        "empty": "a directory without index.jsonl",
        "other.parquet": "no column 'tag_near_edge'",
        "broken.yaml": "not valid YAML",
        "wrong.yaml": "not a data manifest: kind",
    }
    for name, message in cases.items():
        with pytest.raises(CoverageError, match=message) as info:
            coverage_table(tmp_path / name)
        assert "\n" not in str(info.value)


def test_bar_chart_png(tmp_path):
    table = coverage_table(write_parquet(tmp_path / "ref.parquet", scenes_of(GROUPS)))
    path = table.bar_chart(tmp_path / "charts" / "coverage.png")
    image = cv2.imread(str(path))
    # 9 tag groups of 3 task bars (46 px) and a 26 px gap, between 120 px of margins; 640 px tall.
    assert image.shape == (640, 120 + len(TAGS) * (3 * 46 + 26), 3)
    assert (image < 250).any(axis=2).mean() > 0.02  # not blank
    # The retrieve bars are drawn in the first task colour: near_edge, clutter, on_floor, nominal.
    retrieve = np.all(image == (178, 114, 0), axis=2)
    assert retrieve.sum() > 4 * 30 * 10
    clear = np.all(image == (115, 158, 0), axis=2)
    assert 0 < clear.sum() < 20 * 20  # no clear scenes: its colour is only in the legend


def test_main_prints_the_table_and_writes_the_chart(tmp_path, capsys):
    source = write_batch(tmp_path / "batch", scenes_of(GROUPS))
    assert main(["coverage", str(source), "--sparse", "3"]) == 0
    out = capsys.readouterr().out
    assert row_of(out, "upright") == ["upright", "19", "0*", "0*", "19", *["0*"] * 6]
    assert f"chart: {source / 'coverage.png'}" in out
    assert (source / "coverage.png").is_file()  # default: next to the source (inside a batch)
    chart = tmp_path / "c.png"
    assert main(["coverage", str(source), "--out", str(chart)]) == 0 and chart.is_file()


def test_main_on_a_bad_source_returns_2_with_one_line(tmp_path, capsys):
    assert main(["coverage", str(tmp_path / "nope.parquet")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scenegen: error: ") and err.count("\n") == 1
    assert not (tmp_path / "coverage.png").exists()


@pytest.mark.slow
def test_reference_table_from_the_builder(tmp_path):
    """The real reference builder's output reads as it is written (tag_rates agrees), ~10 s."""
    from scenegen.data.reference import build_reference, read_reference, tag_rates
    from scenegen.runner.config import load_pipeline

    recipe = Path(__file__).resolve().parents[2] / "pipelines" / "reference.yaml"
    out = tmp_path / "reference.parquet"
    build_reference(load_pipeline(recipe, {"n": 8}), out, workers=1, progress=False)
    table = coverage_table(out)
    reference, _ = read_reference(out)
    assert table.total == reference.num_rows == 8
    for tag, (count, _) in tag_rates(reference).items():
        assert sum(table.count(task, tag) for task in table.tasks) == count
