"""The reference dataset builder: deterministic rows, prefix regeneration, tags and metadata."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenegen.assets.catalog import load_catalog
from scenegen.data.reference import (
    HELDOUT_EVERY,
    build_reference,
    file_sha256,
    read_reference,
    reference_source,
    tag_rates,
)
from scenegen.manifest import read_manifest
from scenegen.runner.config import load_pipeline
from scenegen.schema.condition import RARE_TAGS, TAGS, TASKS
from scenegen.tags.predicates import PREDICATE_VERSION

REPO_ROOT = Path(__file__).resolve().parents[2]
RECIPE = REPO_ROOT / "pipelines" / "reference.yaml"


@pytest.fixture(scope="module")
def tables(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("reference")
    small = build_reference(load_pipeline(RECIPE, {"n": 3}), root / "small.parquet", progress=False)
    large = build_reference(load_pipeline(RECIPE, {"n": 6}), root / "large.parquet", progress=False)
    return (small, *read_reference(root / "small.parquet")), (large, *read_reference(root / "large.parquet"))


def test_rows_metadata_and_columns(tables):
    _, (stats, table, meta) = tables
    assert table.num_rows == stats["rows"] == 6
    assert meta["predicate_version"] == PREDICATE_VERSION
    assert "stands in for real data" in meta["scenegen.reference"]
    rows = table.to_pylist()
    assert [r["index"] for r in rows] == sorted(r["index"] for r in rows)
    for row in rows:
        assert row["task"] in TASKS
        assert row["split"] == ("heldout" if row["index"] % HELDOUT_EVERY == 0 else "train")
        target = [o for o in row["objects"] if o["name"] == row["target"]]
        assert len(target) == 1 and target[0]["category"] == row["target_category"]
        held = [t for t in TAGS if row[f"tag_{t}"]]
        assert row["tag_nominal"] == (held == ["nominal"])
    assert sum(c for c, _ in tag_rates(table).values()) >= table.num_rows  # every row holds some tag


def test_a_smaller_run_is_a_prefix_of_a_larger_one(tables):
    (_, small, _), (_, large, _) = tables
    assert small.to_pylist() == large.slice(0, small.num_rows).to_pylist()


# ---------------------------------------------------------------- the committed reference set

COMMITTED = REPO_ROOT / "assets" / "reference" / "reference.parquet"
PREFIX = 200


@pytest.fixture(scope="module")
def committed():
    return read_reference(COMMITTED)


def test_committed_reference_meets_the_rates_and_counts(committed):
    table, _ = committed
    rates = tag_rates(table)
    for tag in RARE_TAGS:
        count, rate = rates[tag]
        assert 0.01 <= rate <= 0.05, f"{tag}: natural rate {rate:.2%} outside 1-5 %"
        assert count >= 150, f"{tag}: {count} examples, fewer than 150"
    assert rates["nominal"][1] >= 0.60
    heldout = table.column("split").to_pylist().count("heldout")
    assert abs(heldout / table.num_rows - 1 / HELDOUT_EVERY) < 0.02


def test_committed_reference_matches_this_code(committed):
    """Stamped with today's predicates, catalog and recipe: otherwise regenerate it (README)."""
    _, meta = committed
    assert meta["predicate_version"] == PREDICATE_VERSION
    assert meta["catalog_sha256"] == load_catalog().sha256
    assert meta["pipeline_sha256"] == load_pipeline(RECIPE).digest()


def test_committed_reference_prefix_regenerates_bit_for_bit(committed, tmp_path: Path):
    table, _ = committed
    config = load_pipeline(RECIPE, {"n": PREFIX})
    build_reference(config, tmp_path / "prefix.parquet", workers=2, progress=False)
    prefix, _ = read_reference(tmp_path / "prefix.parquet")
    assert prefix.to_pylist() == table.slice(0, PREFIX).to_pylist()


@pytest.mark.full
def test_committed_reference_regenerates_bit_for_bit(tmp_path: Path):
    out = tmp_path / "reference.parquet"
    build_reference(load_pipeline(RECIPE), out, workers=2, progress=False)
    assert file_sha256(out) == file_sha256(COMMITTED)


def test_project_manifest_registers_the_committed_reference():
    """data_manifest.yaml's reference entry agrees with the file: checksum, counts, versions."""
    manifest = read_manifest(REPO_ROOT / "data_manifest.yaml")
    (source,) = [s for s in manifest.sources if s.origin == "reference"]
    assert source == reference_source(COMMITTED, REPO_ROOT)
    assert "stands in" in source.description
