"""Physics settling and the passive stability test, on small real MuJoCo scenes."""

from __future__ import annotations

import functools

import mujoco
import numpy as np
import pytest
import scenes

from scenegen.assets.catalog import load_catalog
from scenegen.core import layout
from scenegen.settle.physics import SettleSettings, contact_configuration, passive_test, settle
from scenegen.sim import world

SETTINGS = SettleSettings()
SETTLE_CHECKS = ["sim_diverged", "fell_off", "displacement", "penetration", "passive_motion", "ee_motion"]


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


# These scenes never required the snap to keep the requested resting pose.
place = functools.partial(scenes.place, check_pose=False)


def run_settle(catalog, objects, settings=SETTINGS):
    """Build, compile and settle a table scene; returns (model, proposal, outcome)."""
    p = scenes.proposal(objects)
    model = world.build_world(catalog, p.objects).compile()
    qpos, ctrl = world.initial_state(model, p.condition.robot_pose, p.objects)
    return model, p, settle(model, p, qpos, ctrl, settings, catalog)


@pytest.fixture(scope="module")
def stable(catalog):
    objects = [
        place(catalog, "box", "small_box", 0.0, 0.0),
        place(catalog, "can", "soup_can", 0.15, 0.1, pose=1),
    ]
    assert catalog.get("soup_can").resting_poses[1].upright
    return run_settle(catalog, objects)


def test_stable_scene_passes_every_settle_check(stable):
    _, _, outcome = stable
    assert outcome.passed
    assert [c.check for c in outcome.checks] == SETTLE_CHECKS
    for check in outcome.checks:
        assert check.passed, check
        assert check.stage == "settle" and check.label is None
    assert outcome.stats["still"]
    assert outcome.stats["sim_time"] <= SETTINGS.max_time


def test_stable_scene_passive_values_are_within_thresholds(stable):
    _, _, outcome = stable
    by_name = {c.check: c for c in outcome.checks}
    assert by_name["penetration"].value <= SETTINGS.max_penetration
    assert by_name["passive_motion"].value <= SETTINGS.passive_move
    assert by_name["ee_motion"].value <= SETTINGS.passive_ee_move
    assert by_name["displacement"].value <= SETTINGS.max_move
    # Snapped exactly onto resting poses, the objects barely move at all while settling.
    assert by_name["displacement"].value < 1e-3


def test_settled_objects_stay_where_they_were_proposed(stable):
    model, proposal, outcome = stable
    data = mujoco.MjData(model)
    data.qpos[:] = outcome.qpos
    mujoco.mj_forward(model, data)
    for obj in proposal.objects:
        assert data.body(obj.name).xpos == pytest.approx(obj.position, abs=1e-3)


def test_passive_test_reproduces_the_settle_stage(stable):
    # The acceptance test calls passive_test on a stored state: from the settled qpos it must agree.
    model, _, outcome = stable
    again = passive_test(model, outcome.qpos, outcome.ctrl, SETTINGS)
    assert [(c.check, c.passed, c.value) for c in again] == [
        (c.check, c.passed, c.value) for c in outcome.checks[3:]
    ]


def test_contact_configuration_reports_objects_resting_on_the_table(stable):
    model, proposal, outcome = stable
    contacts = contact_configuration(model, outcome.qpos, [o.name for o in proposal.objects])
    rests = {(c.a, c.b) for c in contacts if c.kind == "rests_on"}
    assert rests == {("box", "table"), ("can", "table")}
    for c in contacts:
        assert abs(c.distance) < SETTINGS.max_penetration


def test_object_dropped_from_above_is_unstable(catalog):
    model, proposal, outcome = run_settle(catalog, [place(catalog, "box", "small_box", 0.0, 0.0, lift=0.05)])
    assert not outcome.passed
    failed = outcome.checks[-1]
    assert failed.check == "displacement"
    assert failed.label == "unstable"
    assert failed.value == pytest.approx(0.05, abs=0.005)  # it fell onto the table and stayed there
    assert failed.value > SETTINGS.max_move
    assert all(c.passed for c in outcome.checks[:-1])
    contacts = contact_configuration(model, outcome.qpos, ["box"])
    assert [(c.b, c.kind) for c in contacts] == [("table", "rests_on")]


def test_object_hanging_over_the_edge_falls_off(catalog):
    # A 6 cm box with its centre 6 mm past the table edge (60% of it overhangs): its centre of mass is
    # unsupported, so it tips over the edge and lands on the floor well within max_time (~0.9 s measured),
    # where it comes to rest. Settling therefore sees it still and ~0.77 m below the table top: fell_off,
    # not the "still" check's unstable (that would need it to be still moving at max_time).
    edge = layout.TABLE_SIZE[0] / 2
    model, _, outcome = run_settle(catalog, [place(catalog, "box", "small_box", edge + 0.006, 0.0)])
    assert not outcome.passed
    assert [c.label for c in outcome.checks if not c.passed] == ["fell_off"]
    failed = outcome.checks[-1]
    assert failed.check == "fell_off"
    assert failed.value > 0.5 > SETTINGS.support_drop
    assert failed.detail == "box"
    # It lies on the floor (the world body), no longer on the table.
    contacts = contact_configuration(model, outcome.qpos, ["box"])
    assert ("box", "world", "rests_on") in {(c.a, c.b, c.kind) for c in contacts}
    assert all(c.b != "table" for c in contacts)


def test_object_mostly_on_the_table_stays(catalog):
    # The counterpart of the overhang case: 40% over the edge, the centre of mass still over the table.
    edge = layout.TABLE_SIZE[0] / 2
    _, _, outcome = run_settle(catalog, [place(catalog, "box", "small_box", edge - 0.006, 0.0)])
    assert outcome.passed, outcome.checks


def test_settle_stops_early_once_still(stable):
    _, _, outcome = stable
    steps_min = int(round(SETTINGS.min_time / world.TIMESTEP))
    assert steps_min <= outcome.stats["steps"] < int(round(SETTINGS.max_time / world.TIMESTEP))


def test_stillness_not_reached_within_max_time_is_unstable(catalog):
    # A resting box, but a stillness window (1000 steps) longer than max_time (25 steps): never still.
    strict = SETTINGS.model_copy(update={"max_time": 0.05, "min_time": 0.0, "still_steps": 1000})
    _, _, outcome = run_settle(catalog, [place(catalog, "box", "small_box", 0.0, 0.0)], strict)
    assert not outcome.passed
    assert [c.check for c in outcome.checks] == ["sim_diverged", "still"]
    assert outcome.checks[-1].label == "unstable"
    assert not outcome.stats["still"] and outcome.stats["steps"] == 25
    assert np.isfinite(outcome.qpos).all()
