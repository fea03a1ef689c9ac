"""The failure labeller on hand-made episode records: each rule names its case."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen.env.episodes import TRACE_KEYS, Decision, Episode
from scenegen.policy.failures import failure_label

TARGET = 5


def episode(
    lift=(0.0, 0.0, 0.0),
    contacts=(0, 0, 0),
    eef_to_target=0.2,
    mask=200,
    seconds=5.0,
    chosen="top_grasp",
    tags=("under_overhang",),
    success=False,
) -> Episode:
    n = len(lift)
    target = np.array([[0.1, 0.0, 0.85 + dz] for dz in lift])
    trace = {k: [] for k in TRACE_KEYS}
    trace["time"] = list(np.linspace(0, seconds, n))
    trace["target_pos"] = list(target)
    trace["eef_pos"] = list(target + np.array([0.0, 0.0, eef_to_target]))
    trace["robot_target_contacts"] = list(contacts)
    seg = np.zeros((24, 32, 1), np.int32)
    seg.flat[:mask] = TARGET
    return Episode(
        episode_id="e",
        scene={"scene_id": "s", "tags": list(tags), "target_category": "mug", "target": "mug0"},
        observation_kind="rgbd",
        controller="BASIC",
        control_freq=20.0,
        trace_every=5,
        decisions=[Decision(0, {"front_segmentation": seg}, {"primitive": chosen})],
        trace=trace,
        success=success,
    )


EXPERT_TOP_ONLY = [{"primitive": "top_grasp", "success": True}, {"primitive": "side_grasp", "success": False}]
COVERED = {("under_overhang", "mug"): 40}


@pytest.mark.parametrize(
    ("case", "expected", "expert", "coverage"),
    [
        (dict(success=True), "", [], COVERED),
        (dict(mask=3), "perception", [], COVERED),
        (dict(chosen="side_grasp"), "grasp_choice", EXPERT_TOP_ONLY, COVERED),
        (dict(eef_to_target=0.2), "control", [], COVERED),
        (dict(lift=(0.0, 0.03, 0.0), contacts=(0, 2, 0), eef_to_target=0.0), "dynamics", [], COVERED),
        (dict(lift=(0.0, -0.01, -0.05), contacts=(0, 1, 0), eef_to_target=0.0), "dynamics", [], COVERED),
        (dict(contacts=(0, 1, 1), eef_to_target=0.0), "data_coverage", [], {("under_overhang", "mug"): 2}),
        (dict(contacts=(0, 1, 1), eef_to_target=0.0, seconds=30.0), "timing", [], COVERED),
        (dict(contacts=(0, 1, 1), eef_to_target=0.0), "unknown", [], COVERED),
    ],
)
def test_each_rule_names_its_case(case, expected, expert, coverage):
    assert failure_label(episode(**case), TARGET, expert, coverage) == expected
