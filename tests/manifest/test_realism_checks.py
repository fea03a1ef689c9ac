"""The batch realism checks can fail: the reference set's halves pass them, distorted batches fail them.

Layouts: 100 training-split reference layouts of the demo request (retrieve the spoon) against the
held-out ones, as they are, then spread 1.5x over the table and under lights at half strength.
The image-statistics check's halves and darkened / tinted renders: tests/analysis/test_image_stats.py.
"""

from __future__ import annotations

import copy

import pytest

from scenegen.analysis.realism import load_rows
from scenegen.manifest.realism_checks import (
    C2ST_THRESHOLD,
    MIN_SAMPLES,
    MMD_THRESHOLD,
    REFERENCE_TABLE,
    layout_checks,
    reference_layouts,
    reference_subset,
)
from scenegen.schema.condition import Condition

SHA = "0" * 64
SPOON = Condition(task="retrieve", target="spoon")


@pytest.fixture(scope="module")
def rows() -> list[dict]:
    return load_rows(REFERENCE_TABLE, None)


def spoon_train(rows: list[dict], n: int = 100) -> list[dict]:
    return [r for r in rows if r["split"] == "train" and r["target_category"] == "spoon"][:n]


def spread_and_dim(rows: list[dict], spread: float = 1.5, light: float = 0.5) -> list[dict]:
    out = copy.deepcopy(rows)
    for row in out:
        for o in row["objects"]:
            o["position"] = [o["position"][0] * spread, o["position"][1] * spread, o["position"][2]]
        row["ambient"] *= light
        for lamp in row["lights"]:
            lamp["intensity"] *= light
    return out


def by_metric(checks) -> dict:
    return {c.metric: c for c in checks}


def test_the_reference_subset_follows_the_request(rows):
    subset, description = reference_subset(rows, SPOON)
    assert description == "split=heldout target=spoon tags=any" and len(subset) >= 50
    assert all(r["target_category"] == "spoon" and r["split"] == "heldout" for r in subset)
    toppled = Condition(task="retrieve", target="mug", tags={"toppled": "required", "clutter": "forbidden"})
    subset, description = reference_subset(rows, toppled)
    assert all(r["tag_toppled"] and not r["tag_clutter"] for r in subset)
    assert "+toppled" in description and "-clutter" in description and len(subset) >= 50


@pytest.mark.parametrize(
    "condition, unconditional",
    [
        (SPOON, False),
        (
            Condition(task="retrieve", target="mug", tags={"toppled": "required", "clutter": "forbidden"}),
            False,
        ),
        (
            Condition(
                task="retrieve", target="can", tags={"under_overhang": "required", "low_light": "required"}
            ),
            False,
        ),
        (SPOON, True),
    ],
)
def test_the_subset_read_from_the_table_is_the_subset_of_every_row(rows, condition, unconditional):
    """A batch's manifest reads only the reference rows it compares with (reference_layouts): the
    same rows, in the same order, as the subset chosen from every row, widenings included."""
    assert reference_layouts(REFERENCE_TABLE, condition, unconditional) == reference_subset(
        rows, condition, unconditional
    )


def test_reference_layouts_pass_the_layout_checks(rows):
    checks = by_metric(layout_checks(spoon_train(rows), SHA, SPOON))
    assert checks["layout_c2st"].status == "passed" and checks["layout_c2st"].value <= C2ST_THRESHOLD
    assert checks["layout_mmd"].status == "passed" and checks["layout_mmd"].value <= MMD_THRESHOLD
    assert checks["layout_c2st"].samples == {
        "batch": 100,
        "reference": checks["layout_c2st"].samples["reference"],
    }


def test_distorted_layouts_fail_the_layout_checks(rows):
    checks = by_metric(layout_checks(spread_and_dim(spoon_train(rows)), SHA, SPOON))
    assert checks["layout_c2st"].status == "failed", checks["layout_c2st"]
    assert checks["layout_mmd"].status == "failed", checks["layout_mmd"]


def test_a_small_batch_is_recorded_as_insufficient(rows):
    checks = layout_checks(spread_and_dim(spoon_train(rows, MIN_SAMPLES - 1)), SHA, SPOON)
    assert {c.status for c in checks} == {"insufficient"}


def test_a_request_no_reference_layout_shows_is_recorded_as_insufficient(rows):
    """A combination of tags the reference set never holds (composing those is the generator's job)
    has no layouts to compare with: its checks say so instead of failing to read the table."""
    never = Condition(
        task="retrieve",
        target="can",
        tags={
            "near_edge": "required",
            "clutter": "required",
            "low_light": "required",
            "on_floor": "required",
        },
    )
    subset, _ = reference_layouts(REFERENCE_TABLE, never, False)
    assert subset == []
    checks = layout_checks(spoon_train(rows, MIN_SAMPLES), SHA, never)
    assert {c.status for c in checks} == {"insufficient"}
    assert {c.samples["reference"] for c in checks} == {0}
