"""The success table over hand-made label rows: Wilson intervals, best primitives, and the test of
whether a rare tag's best primitive beats nominal's best within a category."""

from __future__ import annotations

import pytest

from scenegen.policy.success_table import (
    best_primitives,
    differs_from_nominal,
    markdown_table,
    success_cells,
    wilson,
)


def rows(tag: str | None, category: str, primitive: str, successes: int, n: int) -> list[dict]:
    return [
        {
            "tags": [tag] if tag else [],
            "target_category": category,
            "primitive": primitive,
            "success": i < successes,
            "duration": 10.0,
        }
        for i in range(n)
    ]


LABELS = (
    rows(None, "mug", "top_grasp", 27, 30)
    + rows(None, "mug", "side_grasp", 15, 30)
    + rows("under_overhang", "mug", "top_grasp", 3, 30)
    + rows("under_overhang", "mug", "side_grasp", 20, 30)
    + rows("toppled", "mug", "top_grasp", 10, 30)
    + rows("toppled", "mug", "side_grasp", 14, 30)  # better, but by less than 15 points
)


def test_wilson_intervals_match_the_textbook_values():
    assert wilson(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson(0, 0) == (0.0, 1.0)


def test_cells_and_the_best_primitive_per_tag():
    cells = success_cells(LABELS)
    assert cells[("nominal", "top_grasp")].n == 30 and cells[("nominal", "top_grasp")].rate == 0.9
    best = best_primitives(cells)
    assert best[("nominal",)][0] == "top_grasp" and best[("under_overhang",)][0] == "side_grasp"


def test_only_a_tag_whose_best_beats_nominals_best_by_15_points_counts():
    found = differs_from_nominal(LABELS)
    assert [(f["tag"], f["best"]) for f in found] == [("under_overhang", "side_grasp")]
    assert (
        found[0]["best_rate"] == pytest.approx(0.667, abs=1e-3) and found[0]["nominal_best_rate_here"] == 0.1
    )
    assert differs_from_nominal(LABELS, min_cell=31) == []  # too few scenes per cell


def test_the_markdown_table_marks_the_best_and_shows_big_cells_only():
    text = markdown_table(LABELS)
    assert "| under_overhang | 0.67 [" not in text and "**0.67**" in text
    assert "| toppled | mug (n=30) |" in text and "**0.47** [0.30, 0.64]" in text  # the cell's best
    assert "| toppled | mug" not in markdown_table(LABELS, min_cell=31)


def test_tables_combine_once_per_scene_and_primitive_leaving_stale_rows_out(tmp_path, capsys):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from scenegen.cli import main
    from scenegen.env.physics import DEFAULT_PHYSICS, PHYSICS
    from scenegen.manipulation.primitives import PRIMITIVES
    from scenegen.policy.labels import current_rows

    version = PRIMITIVES["top_grasp"].version
    made = {"primitive_version": version, "observation": "rgbd", "physics": PHYSICS[DEFAULT_PHYSICS].key()}
    labelled = [
        row | {"scene_sha256": f"s{i}", **made}
        for i, row in enumerate(rows(None, "mug", "top_grasp", 27, 30))
    ]
    stale = [row | {"primitive_version": version - 1} for row in labelled[:5]]
    state = [row | {"observation": "state", "success": False} for row in labelled[:5]]
    other = [row | {"physics": "other"} for row in labelled[:5]]  # simulated under another physics
    combined, left_out = current_rows([labelled, labelled[:10], stale, state, other])
    assert len(combined) == 30 and left_out == 15
    assert current_rows([state], "state")[0] == state
    for name, table in (("a", labelled[:10]), ("b", labelled + stale + state)):
        pq.write_table(pa.Table.from_pylist(table), tmp_path / f"{name}.parquet")
    assert main(["success-table", str(tmp_path / "a.parquet"), str(tmp_path / "b.parquet")]) == 0
    out, err = capsys.readouterr()
    assert "| nominal | **0.90** [0.74, 0.97] n=30 |" in out and "left out 10 rows" in err
    assert main(["success-table", str(tmp_path / "a.parquet"), "--observation", "state"]) == 2
    assert "no rows of the current primitives (state observation, dt5 physics)" in capsys.readouterr().err
