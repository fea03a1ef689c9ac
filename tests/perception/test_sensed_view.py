"""A sensor's depth read by the robust rule (perception/points.py, issue 62): a stereo pair's errors
(edges that mix an object with what is behind it, pixels metres along their rays) do not become the
target's size or place; exact depth keeps the plain rule's numbers."""

from __future__ import annotations

import numpy as np
import pytest
from scenes import place, proposal

from scenegen.perception.points import SENSOR_REACH, estimate_target, inliers


def _box(rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """Points of a 7 x 5 cm footprint, 10 cm high, centred at (0.1, 0.2) on a table at 0.8 m."""
    return np.column_stack(
        [rng.uniform(0.065, 0.135, n), rng.uniform(0.175, 0.225, n), rng.uniform(0.8, 0.9, n)]
    )


def test_far_points_move_the_plain_estimate_and_not_the_robust_one():
    rng = np.random.default_rng(0)
    clean = _box(rng)
    errors = np.array([[2.1, 0.3, 0.85], [0.1, -1.5, 0.82], [0.4, 0.25, 0.81]])  # along their rays
    noisy = np.vstack([clean, errors])
    plain, robust = estimate_target(noisy), estimate_target(noisy, robust=True)
    assert plain.extent[0] > 1.0  # the plain rule takes the extremes: the errors are its size
    assert robust.extent == pytest.approx((0.07, 0.05), abs=0.005)
    assert robust.centre[:2] == pytest.approx((0.1, 0.2), abs=0.005)
    assert len(inliers(noisy)) == len(clean)  # all three errors lie beyond SENSOR_REACH
    assert np.all(np.linalg.norm(errors[:, :2] - np.median(noisy[:, :2], axis=0), axis=1) > SENSOR_REACH)
    exact = estimate_target(clean)  # the plain rule on clean points: its numbers as they were
    xy = clean[:, :2]
    assert exact.centre[:2] == pytest.approx(0.5 * (xy.min(0) + xy.max(0)))


def test_through_the_stereo_sensor_the_view_of_a_can_is_the_exact_depths_within_centimetres():
    from scenegen.assets.catalog import load_catalog
    from scenegen.env.physics import physics_named
    from scenegen.env.scenes import proposal_scene
    from scenegen.experiment.closed_loop import episode_env
    from scenegen.perception.observation import observe
    from scenegen.perception.points import masked_points
    from scenegen.render.sensor import SENSORS

    can = place(load_catalog(), "can", "soda_can", 0.1, 0.05, pose=1)
    scene = proposal_scene(proposal([can]), "can")
    env = episode_env(scene, physics_named("dt5"))
    env.reset_to(scene)
    _, exact = observe(env, image=False)
    env.depth_sensor = (SENSORS["active_stereo"], "can|0")
    obs, sensed = observe(env, image=False)
    assert sensed.target.extent == pytest.approx(exact.target.extent, abs=0.02)
    assert sensed.target.centre[:2] == pytest.approx(exact.target.centre[:2], abs=0.015)
    assert abs(sensed.target.top_z - exact.target.top_z) < 0.01
    # the plain rule on the same sensed frames is further off than the robust one
    cameras = {c.name: c for c in scene.cameras}
    raw = np.concatenate([
        masked_points(obs[f"{n}_depth"], np.squeeze(obs[f"{n}_segmentation"]) == scene.target_id, cameras[n])
        for n in env.cameras
    ])  # fmt: skip
    plain = estimate_target(raw)
    off = lambda view: abs(view.extent[0] - exact.target.extent[0])  # noqa: E731
    assert off(plain) > off(sensed.target)
