"""The resolution a plan is executed at (``PlanGrid``): positions on a grid of metres, directions on
one of degrees, so that two heads whose plans differ below it execute one attempt."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen.manipulation.primitives import PlanGrid

GRID = PlanGrid(metres=0.005, degrees=5.0)
PLAN = {
    "position": [0.1234, -0.0571, 0.8129],
    "closing": [float(np.cos(0.3)), float(np.sin(0.3))],
    "approach_z": 0.9312,
}


def test_positions_land_on_the_metre_grid_and_directions_on_the_degree_grid():
    snapped = GRID.snap(PLAN)
    assert snapped["position"] == pytest.approx([0.125, -0.055, 0.815])
    assert snapped["approach_z"] == pytest.approx(0.930)
    closing = np.asarray(snapped["closing"])
    assert np.linalg.norm(closing) == pytest.approx(1.0)
    heading = np.degrees(np.arctan2(closing[1], closing[0]))
    assert heading == pytest.approx(5.0 * round(np.degrees(0.3) / 5.0))  # 17.2 deg -> 15
    assert GRID.snap(snapped) == snapped  # on the grid already: unchanged
    assert GRID.snap(None) is None  # the target not seen


def test_plans_within_one_cell_snap_alike_and_a_cell_apart_do_not():
    near = {
        **PLAN,
        "position": [0.1236, -0.0569, 0.8131],
        "closing": [float(np.cos(0.295)), float(np.sin(0.295))],
    }
    far = {**PLAN, "position": [0.1334, -0.0571, 0.8129]}
    assert GRID.snap(near) == GRID.snap(PLAN)
    assert GRID.snap(far) != GRID.snap(PLAN)


def test_a_grid_needs_a_positive_resolution():
    with pytest.raises(ValueError, match="above 0"):
        PlanGrid(metres=0.0, degrees=5.0)


def test_headings_either_side_of_180_degrees_are_one_plan():
    left, right = (np.radians(a) for a in (179.6, -179.6))
    plans = [{**PLAN, "closing": [float(np.cos(h)), float(np.sin(h))]} for h in (left, right)]
    assert GRID.snap(plans[0]) == GRID.snap(plans[1])
    assert str(GRID.snap(plans[0])) == str(GRID.snap(plans[1]))  # no -0.0 against 0.0 in its digest
