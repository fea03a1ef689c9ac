"""The structured-light sensor model (render/sensor.py): noise that grows with range as stated,
pixels missing only near depth edges and at the stated share, drawn from the decision point and the
camera alone; and, in closed loop, the head, the planner and the oracle all read the noisy depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenegen.render.sensor import StructuredLight

ROOT = Path(__file__).resolve().parents[2] / "assets"


def _step(z_near: float = 0.9, z_far: float = 1.2) -> np.ndarray:
    depth = np.full((240, 320), z_far, np.float32)
    depth[:, :160] = z_near  # one vertical depth edge between columns 159 and 160
    return depth


def test_noise_grows_with_range_as_stated():
    sensor = StructuredLight()
    depth = _step()
    noisy = sensor.corrupt(depth, "scene|decision", "front")
    for z, columns in ((0.9, slice(0, 150)), (1.2, slice(170, 320))):
        error = (noisy[:, columns] - depth[:, columns]).ravel()
        expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
        assert abs(error.mean()) < 0.1 * expected
        assert error.std() == pytest.approx(expected, rel=0.03)


def test_only_pixels_near_an_edge_go_missing_at_the_stated_share():
    sensor = StructuredLight()
    noisy = sensor.corrupt(_step(), "scene|decision", "front")
    near = np.zeros((240, 320), bool)
    near[:, 157:163] = True  # within 2 px of the jump's two pixels (159, 160)
    missing = noisy == 0
    assert not missing[~near].any()
    assert missing[near].mean() == pytest.approx(0.2, abs=0.05)
    flat = sensor.corrupt(np.full((240, 320), 1.0, np.float32), "scene|decision", "front")
    assert (flat > 0).all()  # no edge, nothing missing


def test_the_noise_is_drawn_from_the_point_and_the_camera_only():
    sensor, depth = StructuredLight(), _step()
    first = sensor.corrupt(depth[..., None], "s|a", "front")
    assert first.shape == (240, 320, 1) and first.dtype == np.float32
    assert np.array_equal(first, sensor.corrupt(depth[..., None], "s|a", "front"))
    assert not np.array_equal(first, sensor.corrupt(depth[..., None], "s|a", "side"))
    assert not np.array_equal(first, sensor.corrupt(depth[..., None], "s|b", "front"))
    assert np.array_equal(depth, _step())  # the input is not changed


def test_in_closed_loop_every_plan_is_made_from_the_noisy_depth(demo_batch: Path, tmp_path: Path):
    """Under the depth-noise variant the oracle's decision (rendered by ``observe``) and the attempt
    the simulation executed (its own observation inside the primitive) make the same plan, and it is
    not the exact depth's plan: both read the same noisy frames, seeded by the decision point."""
    from scenegen.env.physics import DEFAULT_PHYSICS, physics_mark, physics_named
    from scenegen.env.scenes import batch_scenes
    from scenegen.experiment.closed_loop import evaluate_policies
    from scenegen.experiment.sequences import NOMINAL, ObservationStore, PathStore, Variant
    from scenegen.policy.labels import scene_sha256
    from scenegen.policy.network import PrimitivePolicy

    policies = {"baseline": PrimitivePolicy.load(ROOT / "policy" / "baseline")}
    scenes = batch_scenes(demo_batch)[2:3]
    store, observations = PathStore(tmp_path / "paths.jsonl"), ObservationStore(tmp_path / "obs")
    noise = Variant("depth_noise", 1.0, "structured_light")
    exact = evaluate_policies(policies, scenes, store, observations, NOMINAL)
    noisy = evaluate_policies(policies, scenes, store, observations, noise)
    seen = "oracle" + physics_mark(physics_named(DEFAULT_PHYSICS))  # what the closed loop's key says
    key = ObservationStore.key(scene_sha256(scenes[0]), (), noise, "rgbd", seen)
    decided = observations.meta(key)["plans"][noisy[0]["choices"][0]]
    assert noisy[0]["plans"][0].split("+")[0] == decided
    assert noisy[0]["plans"][0] != exact[0]["plans"][0]
    assert key != ObservationStore.key(scene_sha256(scenes[0]), (), NOMINAL, "rgbd", seen)


def test_a_re_observation_under_noise_plans_as_the_simulation_did():
    """Inside push_from_edge the hand looks again: under depth noise the plan the closed loop makes
    there from the stored state (``regrasp_plan``, seeded by ``again_point``) is the one the
    simulation executed, so a stored attempt is served only to a policy that would act alike; the
    exact depth's plan there is another."""
    from scenes import place, proposal

    from scenegen.assets.catalog import load_catalog
    from scenegen.env.scenes import proposal_scene
    from scenegen.experiment.closed_loop import regrasp_plan, simulate
    from scenegen.experiment.sequences import NOMINAL, Variant, again_point
    from scenegen.policy.labels import scene_sha256
    from scenegen.schema.scene import Light, Lighting

    light = Lighting(lights=(Light(position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), intensity=0.8),))
    can = place(load_catalog(), "can", "soda_can", 0.1, 0.455)  # at the +y edge: pushed, then looked at
    scene = proposal_scene(proposal([can], lighting=light), "edge_can")
    noise = Variant("depth_noise", 1.0, "structured_light")
    row = simulate(scene, ("push_from_edge_then_grasp",), None, noise)[-1]
    assert row["regrasp"] is not None and row["regrasp"]["plan"] != "unseen"
    point = again_point(scene_sha256(scene), (), "push_from_edge_then_grasp", 0)
    state = row["regrasp"]["qpos"]
    assert regrasp_plan(scene, state, noise, None, point) == row["regrasp"]["plan"]
    assert regrasp_plan(scene, state, NOMINAL, None) != row["regrasp"]["plan"]
