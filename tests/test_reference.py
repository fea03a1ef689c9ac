"""The reference dataset builder: deterministic rows, prefix regeneration, tags and metadata."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenegen.config import load_pipeline
from scenegen.reference import HELDOUT_EVERY, build_reference, read_reference, tag_rates
from scenegen.schema.condition import TAGS, TASKS
from scenegen.tags import PREDICATE_VERSION

REPO_ROOT = Path(__file__).resolve().parents[1]
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
