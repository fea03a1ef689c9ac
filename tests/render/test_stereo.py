"""The simulated active stereo sensor (render/stereo.py) measured as a real one is: the plane RMS
of a bare table against a D415's published subpixel error at three ranges (a sensor with much more or
no image noise fails the same bound), the bare table's fill rate, the depth-less bands beside an
occluding edge against the arrangement's prediction; frames drawn from the point and camera alone,
whatever OpenCV's thread count; its imagers rendered exactly as a camera of the model would be; and
in the environment, the depth a planner reads is the sensor's."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from scenegen.render import stereo_quality as quality
from scenegen.render.stereo import ActiveStereo

RANGES = (0.8, 1.2, 1.6)  # m: the cameras here look from about 1.4 m


@pytest.fixture(scope="module")
def renderer():
    from scenegen.render.offscreen import SceneRenderer

    r = SceneRenderer()
    yield r
    r.close()


def _ratios(renderer, sensor: ActiveStereo) -> list[float]:
    return [
        quality.plane_rms(quality.bare_table(renderer, z, sensor)) / quality.predicted_rms(z, sensor)
        for z in RANGES
    ]


def test_plane_rms_follows_a_d415s_subpixel_error_at_each_range(renderer):
    sensor = ActiveStereo()
    ratios = _ratios(renderer, sensor)
    assert all(1 / 1.5 <= r <= 1.5 for r in ratios), ratios
    # the bound has teeth: four times the image noise, or none, leaves it at some range
    noisy = dataclasses.replace(sensor, read_noise=4 * sensor.read_noise, shot_noise=4 * sensor.shot_noise)
    assert max(_ratios(renderer, noisy)) > 1.5
    clean = dataclasses.replace(sensor, read_noise=0.0, shot_noise=0.0)
    assert min(_ratios(renderer, clean)) < 1 / 1.5


def test_the_bare_table_is_filled(renderer):
    sensor = ActiveStereo()
    for z in RANGES:
        assert quality.fill_rate(quality.bare_table(renderer, z, sensor), sensor) >= 0.97, z


def test_the_bands_beside_an_occluding_edge_are_as_wide_as_the_arrangement_predicts(renderer):
    sensor = ActiveStereo()
    for height in (0.8, 1.0):
        frame = quality.box_edge(renderer, height, sensor)
        measured, predicted = quality.edge_bands(frame, sensor), quality.predicted_bands(frame, sensor)
        for m, p in zip(measured, predicted, strict=True):
            assert abs(m - p) <= max(0.3 * p, 2.0), (height, measured, predicted)
        assert predicted[0] > 2 * predicted[1]  # the right imager's shadow is the wide one


def test_frames_come_from_the_point_and_camera_alone_on_any_thread_count(renderer):
    import cv2

    frame = quality.bare_table(renderer, 1.2, point="a")
    again = quality.bare_table(renderer, 1.2, point="a")
    other = quality.bare_table(renderer, 1.2, point="b")
    assert np.array_equal(frame.sensed, again.sensed)
    assert not np.array_equal(frame.sensed, other.sensed)
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(4)
        threaded = quality.bare_table(renderer, 1.2, point="a")
        assert cv2.getNumThreads() == 4  # the matcher restores the caller's setting
    finally:
        cv2.setNumThreads(threads)
    assert np.array_equal(frame.sensed, threaded.sensed)


def test_a_view_renders_as_the_same_camera_of_the_model_would(renderer):
    import mujoco

    from scenegen.assets.catalog import active_catalog
    from scenegen.render.offscreen import View
    from scenegen.schema.scene import Camera
    from scenegen.sim import world

    cam = Camera(name="tilted", position=(1.2, 0.3, 1.4), lookat=(0.0, 0.0, 0.85), fovy=45.0)
    model = world.build_world(active_catalog(), (), (), None, [cam]).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cid = model.camera("tilted").id
    view = View(data.cam_xpos[cid].copy(), data.cam_xmat[cid].reshape(3, 3).copy(), 45.0)
    ids = {"arena": 1, "table": 2, "robot": 3}
    (fixed,) = renderer.render(model, data, ["tilted"], ids, [(160, 120)])
    (free,) = renderer.render(model, data, [view], ids, [(160, 120)])
    assert np.array_equal(fixed.depth, free.depth) and np.array_equal(fixed.seg, free.seg)
    assert np.array_equal(fixed.rgb, free.rgb)


def test_in_the_environment_the_depth_is_the_sensors(demo_batch: Path):
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.env.scenes import batch_scenes
    from scenegen.render.sensor import SENSORS

    scene = batch_scenes(demo_batch)[0]
    env = SceneEnv(scene, cameras=["front"], camera_size=(320, 240), render_each_step=False)
    try:
        env.reset_to(scene)
        exact = env.camera_observations()["front_depth"][..., 0]
        env.depth_sensor = (SENSORS["active_stereo"], "scene|0")
        sensed = env.camera_observations(image=False)["front_depth"][..., 0]
        again = env.camera_observations()["front_depth"][..., 0]  # with the colour frame drawn
    finally:
        env.close()
    seen = (exact > 0) & (exact < 2.0)  # the table and what stands on it
    both = seen & (sensed > 0)
    assert 0.6 < both.sum() / seen.sum() < 1.0  # holes, but mostly depth
    error = np.abs(sensed[both] - exact[both])
    assert np.median(error) < 0.01 and (error > 0).mean() > 0.9  # near, and not the exact frame
    assert (again > 0).sum() == pytest.approx((sensed > 0).sum(), rel=0.05)


def test_frames_through_the_sensor_are_cached_apart_from_the_exact_ones(demo_batch: Path, tmp_path: Path):
    from scenegen.env.scenes import batch_scenes
    from scenegen.perception.retrieval.frames import frames_key, render_missing, scene_frames

    scenes = batch_scenes(demo_batch)[:1]
    (exact,) = scene_frames(scenes, tmp_path)
    (sensed,) = scene_frames(scenes, tmp_path, sensor="active_stereo")
    assert frames_key(scenes[0]) != frames_key(scenes[0], sensor="active_stereo")
    assert np.array_equal(exact.seg, sensed.seg) and np.array_equal(exact.rgb, sensed.rgb)
    seen = (exact.depth > 0) & (exact.depth < 2.0)
    assert (sensed.depth[seen] == 0).any() and not np.array_equal(exact.depth, sensed.depth)
    assert render_missing(scenes, tmp_path, sensor="active_stereo") == 0  # cached: nothing rendered again


def test_the_commands_and_recipes_name_every_sensor():
    import typing

    from scenegen.cli import _parser
    from scenegen.render.sensor import SENSOR_NAMES
    from scenegen.runner.config import PipelineConfig

    recipe = typing.get_args(PipelineConfig.model_fields["sensor"].annotation)
    assert set(SENSOR_NAMES) == set(recipe)
    generate = _parser()._subparsers._group_actions[0].choices["generate"]
    (option,) = [a for a in generate._actions if "--sensor" in a.option_strings]
    assert set(option.choices) == set(SENSOR_NAMES)
