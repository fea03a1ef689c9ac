"""Overlap projection (propose/separate.py): interpenetrating objects pushed apart until the real
collision check (fcl over convex parts) passes, by as little as needed, with the distance recorded."""

from __future__ import annotations

import math

import pytest
from scenes import place, proposal

from scenegen.assets.catalog import load_catalog
from scenegen.check.geometry import CheckSettings, check_collision, scene_solids
from scenegen.propose.separate import separate
from scenegen.schema.scene import FurniturePlacement


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


def collision(p, catalog):
    objects, furniture = scene_solids(p, catalog)
    return check_collision(objects, furniture, CheckSettings())


def test_overlapping_cans_are_pushed_apart_until_the_check_passes(catalog):
    a = place(catalog, "a", "soda_can", 0.0, 0.0)
    b = place(catalog, "b", "soda_can", 0.04, 0.0)  # centres 4 cm apart: ~2.6 cm of overlap
    before = proposal([a, b])
    assert not collision(before, catalog).passed
    after = separate(before, catalog)
    assert collision(after, catalog).passed
    moved = [math.dist(o.position, p.position) for o, p in zip(before.objects, after.objects, strict=True)]
    assert all(0.005 < m < 0.03 for m in moved), moved  # about half the overlap each, not more
    assert after.objects[0].position[0] < 0.0 < 0.04 < after.objects[1].position[0]  # along the line
    for o, p, m in zip(before.objects, after.objects, moved, strict=True):
        assert p.position[2] == o.position[2]  # horizontal only: heights stay snapped
        assert p.projection_distance == pytest.approx(math.hypot(o.projection_distance, m), abs=1e-5)


def test_a_feasible_proposal_is_returned_unchanged(catalog):
    p = proposal([place(catalog, "a", "soda_can", 0.0, 0.0), place(catalog, "b", "mug", 0.2, 0.1)])
    assert collision(p, catalog).passed
    assert separate(p, catalog) == p


def test_max_shift_bounds_the_push_and_leaves_the_rest_to_the_check(catalog):
    a = place(catalog, "a", "soda_can", 0.0, 0.0)
    b = place(catalog, "b", "soda_can", 0.005, 0.0)
    after = separate(proposal([a, b]), catalog, max_shift=0.004)
    for o, p in zip((a, b), after.objects, strict=True):
        assert math.dist(o.position, p.position) <= 0.004 + 2e-6  # positions are rounded to 1 um
    assert not collision(after, catalog).passed


def test_an_object_stacked_on_a_moved_one_moves_with_it(catalog):
    plate = place(catalog, "plate", "plate", 0.0, 0.0)
    can = place(catalog, "can", "soda_can", 0.1, 0.0)  # overlaps the plate's rim
    cup = place(catalog, "cup", "mug", 0.0, 0.0, support="plate", below=[plate])
    after = separate(proposal([plate, can, cup]), catalog)
    by_name = {o.name: o for o in after.objects}
    shift = [by_name["plate"].position[i] - plate.position[i] for i in (0, 1)]
    assert math.hypot(*shift) > 0.005
    assert by_name["cup"].position[0] - cup.position[0] == pytest.approx(shift[0], abs=1e-6)
    assert by_name["cup"].position[1] - cup.position[1] == pytest.approx(shift[1], abs=1e-6)
    assert collision(after, catalog).passed


def test_an_object_in_a_bin_wall_is_pushed_into_the_bin(catalog):
    bin_ = FurniturePlacement(name="bin", kind="bin", position=(0.2, -0.3, 0.0))
    # the bin's inner half length along x is 0.11 m: a can centred at 0.1 m from its centre cuts the wall
    can = place(catalog, "can", "soda_can", 0.3, -0.3, support="bin", furniture=[bin_])
    before = proposal([can], [bin_])
    assert not collision(before, catalog).passed
    after = separate(before, catalog)
    assert collision(after, catalog).passed
    assert after.objects[0].position[0] < 0.3  # inward, toward the bin's centre


def test_spacing_moves_same_support_objects_to_their_footprint_circles(catalog):
    """``spacing``: two cans that touch without overlapping are left alone by plain separation and
    pushed to the procedural sampler's spacing (centres at least the sum of footprint radii apart)."""
    from scenegen.core.layout import footprint_radius

    r = footprint_radius(catalog.get("soda_can"), 0)
    a = place(catalog, "a", "soda_can", 0.0, 0.0)
    b = place(catalog, "b", "soda_can", 1.6 * r, 0.0)  # circles overlap by 0.4 r, solids apart
    p = proposal([a, b])
    assert collision(p, catalog).passed
    assert separate(p, catalog) == p
    spaced = separate(p, catalog, spacing=True)
    (xa, ya, _), (xb, yb, _) = (o.position for o in spaced.objects)
    assert math.hypot(xb - xa, yb - ya) >= 2 * r - 1.5e-3
    assert xa < 0.0 and xb > 1.6 * r and ya == yb == 0.0  # along the line, each half
    far = proposal([a, place(catalog, "b", "soda_can", 2.5 * r, 0.0)])
    assert separate(far, catalog, spacing=True) == far
