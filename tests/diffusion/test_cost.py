"""Differentiable costs: zero where the scene satisfies them, positive where it does not, and their
gradient, applied during sampling, lowers the cost it targets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from scenegen.analysis.realism import load_rows
from scenegen.assets.catalog import load_catalog
from scenegen.diffusion.cost import SceneCost, disc_radius
from scenegen.diffusion.encoding import FURNITURE_KINDS, LIGHT_WIDTH, XY_SCALE, SceneEncoding
from scenegen.diffusion.model import ConditionBatch, Denoiser, DenoiserConfig
from scenegen.diffusion.sample import sample

REFERENCE = Path(__file__).resolve().parents[2] / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def encoding():
    return SceneEncoding(load_catalog())


@pytest.fixture(scope="module")
def tokens(encoding):
    rows = load_rows(REFERENCE, None)[:400]
    objects, scene = zip(*(encoding.encode_row(r) for r in rows), strict=True)
    return (
        rows,
        torch.tensor(np.stack(objects), dtype=torch.float32),
        torch.tensor(np.stack(scene), dtype=torch.float32),
    )


def test_moving_objects_onto_each_other_or_off_the_table_costs(encoding, tokens):
    rows, objects, scene = tokens
    cost = SceneCost(encoding)
    i = next(
        k
        for k, r in enumerate(rows)
        if len(r["objects"]) >= 2 and all(o["support"] == "table" for o in r["objects"])
    )
    base = cost.terms(objects[i : i + 1], scene[i : i + 1])
    stacked = objects[i : i + 1].clone()
    stacked[0, 1, encoding.xyz_cols] = stacked[0, 0, encoding.xyz_cols]  # second object onto the first
    assert cost.terms(stacked, scene[i : i + 1])["penetration"] > base["penetration"] + 0.02
    off = objects[i : i + 1].clone()
    off[0, 0, encoding.xyz_cols.start] = 0.7 / XY_SCALE  # x = 0.7 m: beyond the table's front edge
    assert cost.terms(off, scene[i : i + 1])["table_bounds"] > base["table_bounds"] + 0.2


@pytest.mark.parametrize(
    ("tag", "ratio"),
    [
        ("near_edge", 0.1),
        ("clutter", 0.2),
        ("on_floor", 0.1),
        ("stacked", 0.1),
        ("toppled", 0.1),
        ("under_overhang", 0.2),
        # an upper bound without the predicate's shadow rays: the reference's dim scenes are mostly
        # shadowed ones, so it separates them less sharply
        ("low_light", 0.6),
    ],
)
def test_soft_predicates_separate_the_reference_layouts_that_hold_them(encoding, tokens, tag, ratio):
    rows, objects, scene = tokens
    holds = torch.tensor([bool(r[f"tag_{tag}"]) for r in rows])
    term = SceneCost(encoding, required=(tag,)).terms(objects, scene)[tag]
    assert holds.sum() >= 3, tag
    assert term[holds].mean() < ratio * term[~holds].mean(), (
        float(term[holds].mean()),
        float(term[~holds].mean()),
    )
    assert (term >= 0).all()


def test_soft_low_light_is_the_predicates_formula_without_shadows(encoding, tokens):
    """Where nothing shadows the target the bound equals the measured irradiance (to the encoding's
    rounding); elsewhere it is above it."""
    rows, objects, scene = tokens
    e = encoding
    target = torch.softmax(8 * objects[..., e.target_col], -1)
    xyz = objects[..., e.xyz_cols] * XY_SCALE
    bound = SceneCost(encoding, ("low_light",))._light_bound(scene, xyz[..., :2], xyz[..., 2], target)
    measured = torch.tensor([r["value_low_light"] for r in rows], dtype=torch.float32)
    assert (bound >= measured - 0.05).float().mean() > 0.97
    assert ((bound - measured).abs() < 0.02).float().mean() > 0.5


def test_aimed_soft_low_light_moves_where_lights_point_not_how_bright_they_are(encoding, tokens):
    """``aim_lights`` (``proposer.light_projection: aim``): the same bound, but its gradient reaches
    no ambient or intensity number, only where the lights point and stand; without it, both."""
    rows, objects, scene = tokens
    lit = [i for i, r in enumerate(rows) if not r["tag_low_light"]][:32]
    base = 3 * len(FURNITURE_KINDS)  # the scene token: furniture, then ambient, then each light's slot
    brightness = [base] + [base + 1 + LIGHT_WIDTH * i + 7 for i in range(encoding.light_slots)]
    aim = [base + 1 + LIGHT_WIDTH * i + k for i in range(encoding.light_slots) for k in (4, 5)]
    grads = {}
    for aimed in (False, True):
        s = scene[lit].clone().requires_grad_(True)
        cost = SceneCost(encoding, ("low_light",), aim_lights=aimed)
        cost(objects[lit], s).sum().backward()
        grads[aimed] = s.grad
    assert grads[False][:, brightness].abs().sum() > 0 and grads[True][:, brightness].abs().sum() == 0
    assert grads[True][:, aim].abs().sum() > 0
    plain = SceneCost(encoding, ("low_light",))(objects[lit], scene[lit])
    assert torch.equal(SceneCost(encoding, ("low_light",), aim_lights=True)(objects[lit], scene[lit]), plain)


def test_cost_guidance_lowers_the_cost(encoding):
    torch.manual_seed(0)
    config = DenoiserConfig(
        object_width=encoding.object_width,
        scene_width=encoding.scene_width,
        slots=encoding.slots,
        n_tasks=3,
        n_targets=len(encoding.catalog.categories),
        n_tags=8,
        d_model=32,
        layers=2,
    )
    model = Denoiser(config)
    for head in (model.object_out, model.scene_out):
        torch.nn.init.normal_(head.weight, std=0.05)
    model.eval()
    n = 16
    g = torch.Generator().manual_seed(1)
    noise = (
        torch.randn(n, config.slots, config.object_width, generator=g),
        torch.randn(n, config.scene_width, generator=g),
    )
    c = ConditionBatch(
        torch.zeros(n, dtype=torch.long),
        torch.zeros(n, dtype=torch.long),
        torch.zeros(n, 8, dtype=torch.long),
        torch.zeros(n, 7),
        torch.ones(n, dtype=torch.bool),
    ).null_like(config)
    cost = SceneCost(encoding, required=("near_edge",))
    train = {"train_timesteps": 1000, "beta_schedule": "squaredcos_cap_v2"}
    free = cost(*sample(model, train, c, *noise, steps=10)).mean()
    guided = cost(*sample(model, train, c, *noise, steps=10, cost=cost, cost_weight=2.0)).mean()
    assert guided < 0.5 * free, (float(free), float(guided))


def test_reach_term_is_near_zero_on_reachable_layouts_and_grows_outside_the_envelope(encoding, tokens):
    from scenegen.check.geometry import robot_geometry
    from scenegen.schema.condition import ROBOT_POSES

    rows, objects, scene = tokens
    shoulder = tuple(float(v) for v in robot_geometry(tuple(ROBOT_POSES["home"]))[1])
    cost = SceneCost(encoding, shoulder=shoulder)
    reach = cost.terms(objects, scene)["reach"]
    # every reference target passed the reachability check (0.25-0.95 m); the term aims 3 cm inside it
    assert float((reach < 0.03).float().mean()) > 0.97, float(reach.max())
    far = objects.clone()
    far[:, :, encoding.xyz_cols.start] = 0.9 / XY_SCALE  # every object 0.9 m in front of the table centre
    assert (cost.terms(far, scene)["reach"] > 0.3).float().mean() > 0.9


def test_a_stacked_object_does_not_count_as_penetrating_its_base(encoding, tokens):
    rows, objects, scene = tokens
    cost = SceneCost(encoding)
    stacked = [
        k
        for k, r in enumerate(rows)
        if any(o["support"] in {p["name"] for p in r["objects"]} for o in r["objects"])
    ]
    assert stacked
    table_only = [k for k, r in enumerate(rows) if all(o["support"] == "table" for o in r["objects"])]
    term = cost.terms(objects, scene)["penetration"]
    assert term[stacked].mean() < 0.01 and term[table_only].mean() < 0.01  # reference layouts do not overlap


def test_penetration_uses_the_disc_of_the_sampled_resting_pose(encoding, tokens):
    """Two upright mugs overlap exactly when their centres are closer than twice the upright pose's
    disc radius (not the circle of the asset's widest pose); columns the mug lacks weigh nothing."""
    rows, objects, scene = tokens
    mug = encoding.catalog.get("mug")
    upright = encoding.pose_order["mug"][0]
    radius = disc_radius(mug, upright)
    assert radius < max(disc_radius(mug, p) for p in range(len(mug.resting_poses)))
    pair = -torch.ones(1, encoding.slots, encoding.object_width)
    for slot in (0, 1):
        pair[0, slot, 0] = 1.0
        pair[0, slot, encoding.asset_cols.start + encoding.assets.index("mug")] = 1.0
        pair[0, slot, encoding.pose_cols.start] = 1.0  # column 0: an upright pose
        pair[0, slot, encoding.support_cols.start] = 1.0  # on the table
        pair[0, slot, encoding.xyz_cols] = torch.tensor([0.0, 0.0, 0.05 / XY_SCALE])
        pair[0, slot, encoding.yaw_cols.start] = 1.0
    cost = SceneCost(encoding)

    def penetration(gap: float) -> float:
        moved = pair.clone()
        moved[0, 1, encoding.xyz_cols.start] = (2 * radius + gap) / XY_SCALE
        return float(cost.terms(moved, scene[:1])["penetration"])

    assert penetration(0.005) < 1e-4
    assert penetration(-0.02) == pytest.approx(0.02, abs=2e-3)


def test_soft_occluded_separates_the_reference_layouts_where_the_target_is_hidden(encoding):
    from scenegen.propose.procedural import DEFAULT_CAMERAS

    rows = load_rows(REFERENCE, None)[:2000]  # occluded: 4 % of layouts
    encoded = [encoding.encode_row(r) for r in rows]
    objects = torch.tensor(np.stack([o for o, _ in encoded]), dtype=torch.float32)
    scene = torch.tensor(np.stack([s for _, s in encoded]), dtype=torch.float32)
    holds = torch.tensor([bool(r["tag_occluded"]) for r in rows])
    cost = SceneCost(encoding, required=("occluded",), camera=DEFAULT_CAMERAS[0].position)
    term = cost.terms(objects, scene)["occluded"]
    assert holds.sum() >= 10 and (term >= 0).all()
    assert term[holds].mean() < 0.4 * term[~holds].mean()
    assert (term[~holds] > 0.05).float().mean() > 0.95  # a visible target is (nearly) always charged


def test_arm_clearance_is_zero_on_the_reference_and_charges_an_object_under_the_gripper(encoding, tokens):
    from scenegen.check.geometry import arm_discs
    from scenegen.schema.condition import Condition

    rows, objects, scene = tokens
    pose = Condition(task="retrieve", target="mug", robot_pose="home").robot_pose
    cost = SceneCost(encoding, arm=arm_discs(tuple(pose)))
    term = cost.terms(objects, scene)["arm_clearance"]
    assert (term < 1e-3).float().mean() > 0.9  # layouts that passed the robot_clearance check
    i = next(k for k, r in enumerate(rows) if r["objects"][0]["asset"] == "cereal_box")
    under = objects[i : i + 1].clone()
    gripper = arm_discs(tuple(pose))[-3]  # the hand, 0.2 m above the table
    under[0, 0, encoding.xyz_cols.start : encoding.xyz_cols.start + 2] = torch.tensor(gripper[:2] / XY_SCALE)
    assert cost.terms(under, scene[i : i + 1])["arm_clearance"] > 0.01
    front = under.clone()
    front[0, 0, encoding.xyz_cols.start] = 0.3 / XY_SCALE  # the table's front, far from the arm
    assert cost.terms(front, scene[i : i + 1])["arm_clearance"] < 1e-3
