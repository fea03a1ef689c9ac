"""Geometric checks on hand-built proposals: real fcl over the assets' convex parts, real robot geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenes import place, proposal

from scenegen.assets.catalog import load_catalog
from scenegen.check import geometry
from scenegen.check.geometry import CheckSettings
from scenegen.core import layout, solids
from scenegen.core.layout import FURNITURE_HOME
from scenegen.schema.condition import Condition
from scenegen.schema.scene import FurniturePlacement

CHECK_ORDER = ["workspace", "support", "collision", "robot_clearance", "reachability"]
SETTINGS = CheckSettings()
SHELF = FurniturePlacement(name="shelf", kind="shelf", position=(*FURNITURE_HOME["shelf"], 0.0))
BIN = FurniturePlacement(name="bin", kind="bin", position=(*FURNITURE_HOME["bin"], 0.0))
BOX = 0.06  # small_box footprint side (m)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


def collision(catalog, p):
    objects, furniture = geometry.scene_solids(p, catalog)
    return geometry.check_collision(objects, furniture, SETTINGS)


def robot_clearance(catalog, p):
    objects, furniture = geometry.scene_solids(p, catalog)
    robot, _ = geometry.robot_geometry(tuple(p.condition.robot_pose))
    return geometry.check_robot_clearance(objects, furniture, robot, SETTINGS)


def reachability(catalog, p):
    _, shoulder = geometry.robot_geometry(tuple(p.condition.robot_pose))
    return geometry.check_reachability(p, catalog, shoulder, SETTINGS)


def test_snapped_object_rests_on_the_table(catalog):
    box = place(catalog, "box", "small_box", 0.0, 0.0)
    assert box.position[2] == pytest.approx(layout.TABLE_TOP_Z + 0.025)
    # The lowest vertex of its convex part touches the table top.
    solid = solids.object_solid(catalog, box)
    assert solid.lo[2] == pytest.approx(layout.TABLE_TOP_Z, abs=1e-6)
    result = geometry.check_support(proposal([box]), catalog, SETTINGS)
    assert result.passed and result.value >= 0.0


def test_overlapping_boxes_collide(catalog):
    p = proposal(
        [place(catalog, "a", "small_box", 0.0, 0.0), place(catalog, "b", "small_box", BOX - 0.02, 0.0)]
    )
    result = collision(catalog, p)
    assert not result.passed
    assert result.label == "collision"
    assert result.value == pytest.approx(-0.02, abs=1e-4)
    assert result.threshold == -SETTINGS.penetration_tolerance
    assert result.detail == "a~b"


def test_object_penetrating_furniture_collides(catalog):
    # The shelf's side wall spans y in [0.06, 0.08]: a box 6 cm wide centred at y = 0.095 enters it 1.5 cm.
    box = place(catalog, "box", "small_box", SHELF.position[0], 0.095)
    result = collision(catalog, proposal([box], [SHELF]))
    assert not result.passed and result.label == "collision"
    assert result.value == pytest.approx(-0.015, abs=1e-4)
    assert result.detail == "box~shelf"


def test_resting_and_touching_contacts_are_not_collisions(catalog):
    # A box on the table touching a second box (gap 0), and a third box resting on the shelf board.
    objects = [
        place(catalog, "a", "small_box", 0.0, -0.2),
        place(catalog, "b", "small_box", BOX, -0.2),
        place(catalog, "c", "small_box", *SHELF.position[:2], support="shelf", furniture=[SHELF]),
    ]
    result = collision(catalog, proposal(objects, [SHELF]))
    assert result.passed
    assert result.label is None
    assert abs(result.value) < 1e-3


def test_single_resting_object_reports_large_clearance(catalog):
    result = collision(catalog, proposal([place(catalog, "a", "small_box", 0.0, 0.0)]))
    assert result.passed and result.value == 1.0


@pytest.mark.parametrize(
    ("gap", "passed"),
    [(0.001, True), (-0.0005, True), (-0.002, False)],
    ids=["gap_1mm", "overlap_0.5mm", "overlap_2mm"],
)
def test_penetration_tolerance(catalog, gap, passed):
    p = proposal(
        [place(catalog, "a", "small_box", 0.0, 0.0), place(catalog, "b", "small_box", BOX + gap, 0.0)]
    )
    result = collision(catalog, p)
    assert result.passed is passed
    assert result.value == pytest.approx(gap, abs=1e-4)


def test_rotated_box_penetration_is_measured(catalog):
    # A box turned 45 degrees: its corner reaches 3*sqrt(2) cm from its centre, into the neighbour's face.
    corner = BOX / 2 * math.sqrt(2)
    a = place(catalog, "a", "small_box", 0.0, 0.0)
    b = place(catalog, "b", "small_box", BOX / 2 + corner - 0.005, 0.0, yaw=math.pi / 4)
    result = collision(catalog, proposal([a, b]))
    assert not result.passed
    assert result.value == pytest.approx(-0.005, abs=5e-4)


def test_object_off_the_table_is_out_of_workspace(catalog):
    p = proposal(
        [place(catalog, "near", "small_box", 0.39, 0.0), place(catalog, "off", "small_box", 0.45, 0.2)]
    )
    result = geometry.check_workspace(p, catalog)
    assert not result.passed
    assert result.label == "out_of_workspace"
    assert result.value == pytest.approx(-0.05)
    assert result.detail == "off"


def test_object_near_the_edge_is_in_the_workspace(catalog):
    result = geometry.check_workspace(proposal([place(catalog, "near", "small_box", 0.39, -0.49)]), catalog)
    assert result.passed and result.value == pytest.approx(0.01)


def test_floating_object_is_unsupported(catalog):
    p = proposal(
        [place(catalog, "a", "small_box", 0.0, 0.0), place(catalog, "b", "mug", 0.2, 0.0, lift=0.01)]
    )
    result = geometry.check_support(p, catalog, SETTINGS)
    assert not result.passed
    assert result.label == "unsupported"
    assert result.value == pytest.approx(SETTINGS.support_height_tolerance - 0.01, abs=1e-6)
    assert result.detail == "b"


def test_object_sunk_into_the_table_is_unsupported(catalog):
    result = geometry.check_support(
        proposal([place(catalog, "a", "soup_can", 0.0, 0.0, lift=-0.005)]), catalog, SETTINGS
    )
    assert not result.passed and result.label == "unsupported"


def test_support_that_does_not_exist_is_unsupported(catalog):
    obj = place(catalog, "a", "small_box", *SHELF.position[:2], support="shelf", furniture=[SHELF])
    result = geometry.check_support(proposal([obj]), catalog, SETTINGS)  # the proposal has no shelf
    assert not result.passed and result.label == "unsupported"
    assert "no shelf" in result.detail


def test_tall_object_under_the_gripper_overlaps_the_robot(catalog):
    # At the home pose the gripper hangs at x ~ -0.10, y = 0 with its fingertips ~0.2 m above the table; an
    # upright bottle (0.235 m tall) there reaches into the hand.
    bottle = place(catalog, "bottle", "bottle", -0.10, 0.0)
    assert catalog.get("bottle").resting_poses[0].upright
    result = robot_clearance(catalog, proposal([bottle]))
    assert not result.passed
    assert result.label == "robot_overlap"
    assert result.value < SETTINGS.robot_clearance
    assert result.detail == "bottle"


def test_tall_object_into_a_finger_has_negative_clearance(catalog):
    result = robot_clearance(catalog, proposal([place(catalog, "bottle", "bottle", -0.10, 0.05)]))
    assert not result.passed and result.value < 0.0


def test_same_object_away_from_the_robot_is_clear(catalog):
    result = robot_clearance(catalog, proposal([place(catalog, "bottle", "bottle", 0.15, 0.0)]))
    assert result.passed
    assert result.value >= SETTINGS.robot_clearance


def test_far_corner_is_unreachable(catalog):
    box = place(catalog, "box", "small_box", 0.38, 0.45)
    result = reachability(catalog, proposal([box]))
    assert not result.passed
    assert result.label == "unreachable"
    assert result.value < 0.0
    # The margin is reach_max minus the distance from the shoulder to the best (top) grasp point.
    _, shoulder = geometry.robot_geometry(tuple(Condition().robot_pose))
    top = np.asarray(box.position) + [0.0, 0.0, 0.025]
    expected = SETTINGS.reach_max - np.linalg.norm(top - shoulder)
    assert result.value == pytest.approx(expected, abs=1e-5)


def test_robot_shoulder_is_where_the_panda_mounts(catalog):
    _, shoulder = geometry.robot_geometry(tuple(Condition().robot_pose))
    assert shoulder[0] < -layout.TABLE_SIZE[0] / 2  # behind the table
    assert shoulder[1] == pytest.approx(0.0, abs=1e-6)
    assert layout.TABLE_TOP_Z < shoulder[2] < layout.TABLE_TOP_Z + 0.6


def test_object_in_front_of_the_robot_is_reachable_from_the_top(catalog):
    result = reachability(catalog, proposal([place(catalog, "box", "small_box", 0.0, 0.0)]))
    assert result.passed and result.value > 0.0
    assert result.detail == "box by top"


def test_object_under_the_shelf_is_reachable_from_the_side_and_not_a_collision(catalog):
    # A soda can (12.2 cm) under the shelf board (underside 22 cm above the table): the board closes the top
    # approach, the side approach stays open.
    can = place(catalog, "can", "soda_can", *SHELF.position[:2], pose=1)
    assert catalog.get("soda_can").resting_poses[1].upright
    results, passed = geometry.run_checks(proposal([can], [SHELF, BIN]), catalog, SETTINGS)
    assert passed, results
    assert [r.check for r in results] == CHECK_ORDER
    assert results[2].value > 0.05  # clear of the shelf's walls and board
    assert results[-1].detail == "can by side"


def test_object_under_the_shelf_beyond_side_reach_is_unreachable(catalog):
    # At x = 0.27 only the (closed) top approach would be within reach_max; the side approach is not.
    can = place(catalog, "can", "soda_can", 0.27, SHELF.position[1], pose=1)
    p = proposal([can], [SHELF])
    result = reachability(catalog, p)
    assert not result.passed and result.label == "unreachable"
    assert result.detail == "can by side"
    # The same can with no shelf over it is reached from the top.
    assert reachability(catalog, proposal([can])).passed


@pytest.mark.parametrize(
    ("objects", "failed"),
    [
        ([("box", "small_box", 0.0, 0.0, 0.0), ("mug", "mug", 0.15, -0.15, 0.0)], None),
        ([("box", "small_box", 0.0, 0.0, 0.0), ("off", "small_box", 0.45, 0.0, 0.0)], "out_of_workspace"),
        ([("box", "small_box", 0.0, 0.0, 0.0), ("high", "small_box", 0.2, 0.0, 0.01)], "unsupported"),
        ([("box", "small_box", 0.0, 0.0, 0.0), ("hit", "small_box", 0.04, 0.0, 0.0)], "collision"),
        ([("box", "small_box", 0.0, 0.0, 0.0), ("tall", "bottle", -0.10, 0.0, 0.0)], "robot_overlap"),
        ([("box", "small_box", 0.38, 0.45, 0.0)], "unreachable"),
    ],
    ids=["pass", "workspace", "support", "collision", "robot", "reach"],
)
def test_run_checks_stops_at_the_first_failure_cheapest_first(catalog, objects, failed):
    placed = [place(catalog, name, asset, x, y, lift=lift) for name, asset, x, y, lift in objects]
    results, passed = geometry.run_checks(proposal(placed), catalog, SETTINGS)
    assert [r.check for r in results] == CHECK_ORDER[: len(results)]
    assert all(r.stage == "check" for r in results)
    assert all(r.passed for r in results[:-1])
    if failed is None:
        assert passed and len(results) == len(CHECK_ORDER)
    else:
        assert not passed
        assert not results[-1].passed and results[-1].label == failed


# ---------------------------------------------------------------- penetration depth


def test_deeply_interpenetrating_bowls_give_their_depth_instead_of_aborting(catalog):
    """Two bowls 4.5 cm apart (proposal 2807 of the reference recipe): fcl's EPA signed distance
    throws a C++ std::logic_error here that kills the process; the separating-axis depth does not."""
    bowl = place(catalog, "bowl_a", "bowl", 0.0, 0.0, pose=1)
    a = bowl.model_copy(
        update={"position": (-0.2486432, 0.0472862, 0.829667), "quat": (0.022939, 0, 0, -0.9997369)}
    )
    b = bowl.model_copy(
        update={
            "name": "bowl_b",
            "position": (-0.2106272, 0.0234887, 0.829667),
            "quat": (0.2645991, 0, 0, 0.9643585),
        }
    )
    result = collision(catalog, proposal([a, b]))
    assert not result.passed and result.label == "collision"
    assert result.value == pytest.approx(-0.0104, abs=5e-4)  # MPR says 3.7 cm: not the minimum


@pytest.mark.parametrize("seed", range(5))
def test_separating_axis_depth_matches_fcl_on_shallow_overlaps(catalog, seed: int):
    """Where fcl's EPA is safe (shallow overlaps between two convex parts), both depths agree."""
    import fcl

    rng = np.random.default_rng(seed)
    mug = solids.object_solid(catalog, place(catalog, "mug", "mug", 0.0, 0.0, pose=2))
    can = place(catalog, "can", "soup_can", 0.0, 0.0, pose=1, yaw=rng.uniform(-math.pi, math.pi))
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    for gap in (-0.004, -0.002, -0.0005):  # metres of overlap between footprint circles
        reach = 0.0535 + 0.038 + gap  # mug body radius + can radius, then overlapped
        moved = can.model_copy(update={"position": (*(direction * reach), can.position[2])})
        solid = solids.object_solid(catalog, moved)
        ours = solids.signed_distance(mug, solid)
        request = fcl.DistanceRequest(enable_signed_distance=True)
        theirs = min(
            fcl.distance(pa, pb, request, fcl.DistanceResult()) for pa in mug.pieces for pb in solid.pieces
        )
        assert ours == pytest.approx(theirs, abs=2e-5)


def test_penetration_depth_of_two_cubes():
    cube = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * 0.05
    axes = np.eye(3)
    a = solids.Polytope(cube, axes, axes)
    b = solids.Polytope(cube + [0.07, 0.01, 0.0], axes, axes)
    assert solids.penetration_depth(a, b) == pytest.approx(0.03)


def test_unique_rows_is_numpys_unique():
    rng = np.random.default_rng(0)
    for _ in range(300):
        rows = np.round(rng.normal(size=(int(rng.integers(1, 40)), int(rng.integers(2, 4)))), 1)
        rows[rng.random(rows.shape) < 0.3] = 0.0  # ties in the first columns
        assert np.array_equal(solids.unique_rows(rows), np.unique(rows, axis=0))


@pytest.mark.parametrize("seed", range(3))
def test_a_translated_solid_is_the_rebuilt_one_and_its_overlap_depth_the_signed_distance(catalog, seed):
    """What the overlap projection uses (MovableSolid, overlap_depth) against what the check uses
    (object_solid, signed_distance): the same vertices bit for bit, the same depth of overlap."""
    rng = np.random.default_rng(seed)
    mug = solids.object_solid(catalog, place(catalog, "mug", "mug", 0.0, 0.0, pose=2))
    can = place(catalog, "can", "soup_can", 0.0, 0.0, pose=1, yaw=rng.uniform(-math.pi, math.pi))
    movable = solids.MovableSolid.of(catalog, can)
    seen = set()
    for _ in range(40):
        x, y = rng.uniform(-0.12, 0.12, size=2)
        position = (float(x), float(y), can.position[2])
        rebuilt = solids.object_solid(catalog, can.model_copy(update={"position": position}))
        moved = movable.at(position)
        for p, q in zip(rebuilt.polytopes, moved.polytopes, strict=True):
            assert np.array_equal(p.verts, q.verts)
            assert np.array_equal(p.normals, q.normals) and np.array_equal(p.edges, q.edges)
        distance, depth = solids.signed_distance(rebuilt, mug), solids.overlap_depth(moved, mug)
        if distance < 0:
            assert depth == -distance
        else:
            assert depth == 0.0
        seen.add(distance < -1e-4)
    assert seen == {True, False}  # both overlapping and separated placements were tried
