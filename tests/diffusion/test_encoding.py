"""Scene <-> tensor encoding: round trip on committed reference layouts, snapping of noisy tokens."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scenegen.analysis.realism import load_rows
from scenegen.assets.catalog import load_catalog
from scenegen.core import layout
from scenegen.core.layout import footprint_radius
from scenegen.diffusion.encoding import SLOTS, STACK_SNAP, XY_SCALE, SceneEncoding
from scenegen.propose.procedural import DEFAULT_CAMERAS
from scenegen.schema.condition import Condition

REFERENCE = Path(__file__).resolve().parents[2] / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def encoding():
    return SceneEncoding(load_catalog())


@pytest.fixture(scope="module")
def rows():
    return load_rows(REFERENCE, None)[:300]


def decode(encoding, tokens, scene, row):
    return encoding.decode(tokens, scene, Condition(target=row["target_category"]), DEFAULT_CAMERAS)


def angle(q1, q2) -> float:
    return 2 * math.acos(min(1.0, abs(float(np.dot(q1, q2)))))


def test_widths(encoding):
    tokens, scene = encoding.encode_row(load_rows(REFERENCE, None)[0])
    assert tokens.shape == (SLOTS, encoding.object_width) and scene.shape == (encoding.scene_width,)


def test_round_trip_of_reference_layouts(encoding, rows):
    for row in rows:
        tokens, scene = encoding.encode_row(row)
        assert np.all(np.abs(tokens) <= 2.0) and np.all(np.abs(scene) <= 3.0), row["index"]
        decoded = decode(encoding, tokens, scene, row)
        p = decoded.proposal
        assert p.target == row["target"]
        assert [o.name for o in p.objects] == [o["name"] for o in row["objects"]]
        for o, r in zip(p.objects, row["objects"], strict=True):
            assert (o.asset, o.support) == (r["asset"], r["support"])
            assert o.position[:2] == pytest.approx(r["position"][:2], abs=1e-6)
            # Settled poses sit within a few millimetres and degrees of the ideal resting pose.
            assert o.position[2] == pytest.approx(r["position"][2], abs=3e-3)
            assert angle(o.quat, r["quat"]) < 0.1
        assert max(decoded.projection) < 3e-3
        assert [f.kind for f in p.furniture] == [f["kind"] for f in row["furniture"]]
        for f, r in zip(p.furniture, row["furniture"], strict=True):
            assert f.position[:2] == pytest.approx((r["x"], r["y"]), abs=1e-6)
        assert p.lighting.ambient[0] == pytest.approx(row["ambient"], abs=1e-6)
        assert len(p.lighting.lights) == len(row["lights"])
        for light, r in zip(p.lighting.lights, row["lights"], strict=True):
            for key in ("position", "direction", "colour"):
                assert getattr(light, key) == pytest.approx(r[key], abs=2e-6), key
            assert light.intensity == pytest.approx(r["intensity"], abs=1e-6)
            assert light.cast_shadow == r["cast_shadow"]


def test_noisy_tokens_decode_onto_resting_poses_and_report_the_projection(encoding, rows):
    rng = np.random.default_rng(0)
    catalog = load_catalog()
    for row in rows[:50]:
        tokens, scene = encoding.encode_row(row)
        noisy = tokens + rng.normal(0, 0.05, tokens.shape)
        noisy[:, 0] = tokens[:, 0]  # same slots present
        decoded = decode(encoding, noisy, scene + rng.normal(0, 0.05, scene.shape), row)
        surfaces = layout.support_surfaces(decoded.proposal.furniture)
        for o, distance in zip(decoded.proposal.objects, decoded.projection, strict=True):
            pose = catalog.get(o.asset).resting_poses[o.resting_pose]
            if o.support in surfaces:  # stacked objects sit on their base's top instead
                assert o.position[2] == pytest.approx(surfaces[o.support].z + pose.height, abs=1e-6)
            assert distance >= 0.0
        assert max(decoded.projection) > 1e-3  # the height noise (0.05 x 0.5 m) was projected away


def test_the_object_count_decides_how_many_present_slots_are_decoded(encoding, rows):
    row = next(r for r in rows if len(r["objects"]) >= 4)
    tokens, scene = encoding.encode_row(row)
    n = len(row["objects"])
    assert np.argmax(scene[encoding.count_cols]) == n - 1
    target = encoding.catalog.get(row["objects"][2]["asset"]).category  # slot 2 is kept in every case

    def names(count: int, presence: np.ndarray) -> list[str]:
        t, c = tokens.copy(), scene.copy()
        t[:, 0] = presence
        c[encoding.count_cols] = -1.0
        c[encoding.count_cols.start + count - 1] = 1.0
        objects = encoding.decode(t, c, Condition(target=target), DEFAULT_CAMERAS).proposal.objects
        return [o.name for o in objects]

    expected = [o["name"] for o in row["objects"]]
    presence = np.full(SLOTS, 0.3)
    presence[[2, 0]] = (0.9, 0.6)  # every slot present, slots 2 and 0 the most
    assert names(2, presence) == [expected[0], expected[2]]  # the count keeps the two most present
    present_n = np.where(np.arange(SLOTS) < n, presence, -1.0)
    assert names(SLOTS, present_n) == expected  # never an empty slot, whatever the count
    none = np.full(SLOTS, -0.9)
    none[2] = -0.5
    assert names(2, none) == [expected[2]]  # none present: the most present one


def test_pose_column_zero_is_upright_for_every_asset_that_has_an_upright_pose(encoding):
    for asset in encoding.catalog.assets:
        order = encoding.pose_order[asset.name]
        assert sorted(order) == list(range(len(asset.resting_poses)))
        if any(p.upright for p in asset.resting_poses):
            assert asset.resting_poses[order[0]].upright, asset.name


def test_more_objects_than_slots_is_an_error(encoding, rows):
    row = dict(rows[0], objects=rows[0]["objects"] * (SLOTS + 1))
    with pytest.raises(ValueError, match="slots"):
        encoding.encode_row(row)


def test_the_target_is_an_object_of_the_requested_category(encoding, rows):
    row = next(r for r in rows if r["target_category"] == "mug")
    tokens, scene = encoding.encode_row(row)
    as_requested = encoding.decode(tokens, scene, Condition(target="mug"), DEFAULT_CAMERAS).proposal
    assert as_requested.target == row["target"]
    other = encoding.decode(tokens, scene, Condition(target="bottle"), DEFAULT_CAMERAS).proposal
    target = next(o for o in other.objects if o.name == other.target)
    assert target.category == "bottle"


def test_an_object_decoded_as_stacked_moves_onto_the_nearest_base(encoding, rows):
    """A stacked token a few centimetres off its base lands on the inner half of the base's top (the
    move counted in its projection distance); one farther than STACK_SNAP from any base stays on
    the table."""
    catalog = load_catalog()
    row, slot = next(
        (r, k)
        for r in rows
        for k, o in enumerate(r["objects"])
        if o["support"] in {p["name"] for p in r["objects"]}
    )
    tokens, scene = encoding.encode_row(row)
    objects = decode(encoding, tokens, scene, row).proposal.objects
    base = next(o for o in objects if o.name == objects[slot].support)
    top = layout.object_top_surface(catalog, base)
    away = np.asarray(objects[slot].position[:2]) - top.center
    away = away / np.hypot(*away) if np.hypot(*away) > 1e-9 else np.array([1.0, 0.0])

    def shifted(distance: float):
        moved = tokens.copy()
        moved[slot, encoding.xyz_cols.start : encoding.xyz_cols.start + 2] += away * distance / XY_SCALE
        return decode(encoding, moved, scene, row)

    near = shifted(max(top.half) + 0.05)
    snapped = near.proposal.objects[slot]
    assert snapped.support == base.name
    local = np.abs(top.local_xy(snapped.position[:2]))
    assert np.all(local <= np.asarray(top.half) / 2 + 1e-5)  # positions are stored to the micrometre
    assert near.projection[slot] >= 0.05

    far = shifted(max(top.half) + STACK_SNAP + 0.3).proposal.objects[slot]
    assert far.support != base.name


def test_an_object_inside_the_bins_walls_goes_into_the_bin_with_its_footprint_inside(encoding, rows):
    """A table object decoded inside the bin's walls rests on the bin's floor; one on the bin near a
    wall moves in until its footprint circle clears the walls (the procedural sampler's rule)."""
    row = next(r for r in rows if "bin" in {f["kind"] for f in r["furniture"]})
    tokens, scene = encoding.encode_row(row)
    bin_ = layout.support_surfaces(decode(encoding, tokens, scene, row).proposal.furniture)["bin"]
    slot, centre, support = 0, np.asarray(bin_.center), encoding.support_cols.start
    for xy, kind in [(centre + [0.0, bin_.half[1] - 0.01], "table"), (centre - [bin_.half[0], 0.0], "bin")]:
        moved = tokens.copy()
        moved[slot, encoding.xyz_cols.start : encoding.xyz_cols.start + 2] = np.asarray(xy) / XY_SCALE
        moved[slot, encoding.support_cols] = -1.0
        moved[slot, support + ("table", "floor", "shelf", "bin", "stacked").index(kind)] = 1.0
        decoded = decode(encoding, moved, scene, row)
        o = decoded.proposal.objects[slot]
        radius = footprint_radius(load_catalog().get(o.asset), o.resting_pose)
        height = load_catalog().get(o.asset).resting_poses[o.resting_pose].height
        assert o.support == "bin"
        assert o.position[2] - height == pytest.approx(bin_.z, abs=1e-6)  # on the bin's floor
        assert bin_.margin(o.position[:2]) >= min(radius, *bin_.half) - 1e-5
        assert decoded.projection[slot] >= np.hypot(*(np.asarray(o.position[:2]) - xy)) - 1e-5


def test_upright_off_table_decodes_floor_objects_upright_unless_the_target_must_be_toppled(encoding, rows):
    """``upright_off_table``: an object decoded lying on the floor takes its best upright pose (the
    reference sampler's rule); without the option, or for a target whose request requires toppled,
    the model's pose stands."""
    catalog = load_catalog()

    def both(name: str) -> bool:
        return len({p.upright for p in catalog.get(name).resting_poses}) == 2

    row = next(
        r
        for r in rows
        if sum(both(o["asset"]) for o in r["objects"]) >= 2
        and both(next(o["asset"] for o in r["objects"] if o["name"] == r["target"]))
    )
    tokens, scene = encoding.encode_row(row)
    plain = decode(encoding, tokens, scene, row).proposal
    target = next(k for k, o in enumerate(plain.objects) if o.name == plain.target)
    lying = tokens.copy()
    for slot in range(len(row["objects"])):
        asset = catalog.get(plain.objects[slot].asset)
        columns = encoding.pose_order[asset.name]
        flat = [k for k, c in enumerate(columns) if not asset.resting_poses[c].upright]
        if not flat or not any(asset.resting_poses[c].upright for c in columns):
            continue
        lying[slot, encoding.pose_cols] = -1.0
        lying[slot, encoding.pose_cols.start + flat[0]] = 1.0
        lying[slot, encoding.support_cols] = -1.0
        lying[slot, encoding.support_cols.start + 1] = 1.0  # "floor"
    changed = [s for s in range(len(row["objects"])) if not np.array_equal(lying[s], tokens[s])]
    assert target in changed and len(changed) >= 2, "pick a row whose objects can lie and stand"

    def poses(condition, **kw):
        p = encoding.decode(lying, scene, condition, DEFAULT_CAMERAS, **kw).proposal
        return [catalog.get(o.asset).resting_poses[o.resting_pose].upright for o in p.objects], p

    as_model, _ = poses(Condition(target=row["target_category"]))
    upright, p = poses(Condition(target=row["target_category"]), upright_off_table=True)
    assert all(p.objects[s].support == "floor" for s in changed)
    assert not any(as_model[s] for s in changed) and all(upright[s] for s in changed)
    toppled = Condition(target=row["target_category"], tags={"toppled": "required"})
    kept, _ = poses(toppled, upright_off_table=True)
    for s in changed:
        assert kept[s] == (s != target)


def test_upright_off_table_covers_a_table_object_that_the_bin_rule_puts_in_the_bin(encoding, rows):
    catalog = load_catalog()
    row = next(r for r in rows if "bin" in {f["kind"] for f in r["furniture"]})
    tokens, scene = encoding.encode_row(row)
    bin_ = layout.support_surfaces(decode(encoding, tokens, scene, row).proposal.furniture)["bin"]
    slot = next(
        k
        for k, o in enumerate(row["objects"])
        if o["name"] != row["target"] and len({p.upright for p in catalog.get(o["asset"]).resting_poses}) == 2
    )
    asset = catalog.get(row["objects"][slot]["asset"])
    columns = encoding.pose_order[asset.name]
    lying = tokens.copy()
    lying[slot, encoding.xyz_cols.start : encoding.xyz_cols.start + 2] = np.asarray(bin_.center) / XY_SCALE
    lying[slot, encoding.support_cols] = -1.0
    lying[slot, encoding.support_cols.start] = 1.0  # "table", inside the bin's walls
    lying[slot, encoding.pose_cols] = -1.0
    lying[
        slot,
        encoding.pose_cols.start
        + next(k for k, c in enumerate(columns) if not asset.resting_poses[c].upright),
    ] = 1.0
    condition = Condition(target=row["target_category"])
    for on in (False, True):
        o = encoding.decode(lying, scene, condition, DEFAULT_CAMERAS, upright_off_table=on).proposal.objects[
            slot
        ]
        assert o.support == "bin" and asset.resting_poses[o.resting_pose].upright == on
