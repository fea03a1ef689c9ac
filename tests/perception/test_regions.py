"""The region step's foreground options for a depth sensor (perception/retrieval/regions.py): heights
from a plane fitted to the frame's own table points, and a margin around the robot's pixels; without
them the foreground is what it was on exact depth."""

from __future__ import annotations

import numpy as np
import pytest

from scenegen.perception.retrieval.regions import TABLE_TOP, foreground
from scenegen.render import stereo_quality as quality
from scenegen.schema.scene import Camera
from scenegen.sim import world


@pytest.fixture(scope="module")
def table():
    from scenegen.render.offscreen import SceneRenderer

    renderer = SceneRenderer()
    try:
        frame = quality.bare_table(renderer, 1.2)
    finally:
        renderer.close()
    top = world.TABLE_TOP_Z
    camera = Camera(name=quality.CAMERA, position=(0.1, 0.0, top + 1.2), lookat=(0.1001, 0.0, top))
    return frame, camera


def test_a_table_seen_a_few_millimetres_high_is_no_object_once_its_plane_is_fitted(table):
    frame, camera = table
    assert TABLE_TOP == pytest.approx(world.TABLE_TOP_Z)
    top = (frame.seg == frame.ids["table"]) & (frame.exact > 0)
    nobody = np.zeros_like(top)
    raised = np.where(frame.exact > 0, frame.exact - 0.004, 0.0).astype(np.float32)  # 4 mm nearer
    keep, _ = foreground(frame.exact, nobody, camera)
    assert not keep[top].any()  # exact depth: the table is no object
    keep, lift = foreground(raised, nobody, camera)
    assert keep[top].mean() > 0.95 and np.median(lift[top]) == pytest.approx(0.004, abs=5e-4)
    keep, lift = foreground(raised, nobody, camera, table_fit=True)
    assert keep[top].mean() < 0.01 and np.abs(np.median(lift[top])) < 5e-4


def test_a_margin_round_the_robots_pixels_keeps_them_out(table):
    frame, camera = table
    raised = np.where(frame.exact > 0, frame.exact - 0.02, 0.0).astype(np.float32)  # all 2 cm up
    robot = np.zeros(frame.exact.shape, bool)
    robot[200:220, 300:320] = True
    keep, _ = foreground(raised, robot, camera)
    assert not keep[robot].any() and keep[196:224, 296:324].sum() > 0
    keep, _ = foreground(raised, robot, camera, robot_margin=4)
    assert not keep[196:224, 296:324].any() and keep[190:194, 290:294].all()
