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


def test_a_depth_rule_mends_holes_then_smooths_and_exact_depths_rule_leaves_a_frame_as_it_is():
    from scenegen.perception.retrieval.regions import DEPTH_RULES, DepthRule

    depth = np.full((12, 12), 1.0, np.float32)
    depth[:, 6:] = 1.2
    depth[3, 2] = depth[8, 9] = 0.0  # no return
    depth[5, 4] = 1.3  # one outlier
    assert DEPTH_RULES["exact"] == DepthRule() and DepthRule().mend(depth) is depth
    filled = DepthRule(fill=True).mend(depth)
    assert filled[3, 2] == 1.0 and filled[8, 9] == pytest.approx(1.2) and filled[5, 4] == pytest.approx(1.3)
    smooth = DepthRule(fill=True, median=5).mend(depth)
    assert smooth[5, 4] == 1.0 and (smooth > 0).all()  # the outlier is gone, no hole is left
    assert smooth[:, :5].max() == 1.0 and smooth[:, 7:].min() == pytest.approx(1.2)  # the step stays put


def test_a_depth_rule_is_read_from_a_checkpoint_config_or_refused_in_one_line():
    from scenegen.perception.retrieval.regions import DEPTH_RULES, DepthRule

    rule = DEPTH_RULES["mended_5mm"]
    assert DepthRule.from_config(rule.config(), "c.json") == rule
    assert DepthRule.from_config({"above": 0}, "c.json") == DepthRule(above=0.0)  # an int is a number
    bad = [
        ({"fill": 1}, "depth_rule fill 1 is not a bool"),
        ({"median": 4}, "median 4: 0 .none., 3 or 5"),
        ({"above": 0.5}, "above 0.5 m"),
        ({"blur": 3}, "keys fill, median, above, robot_margin, table_fit"),
        ([], "must be an object"),
    ]
    for spec, message in bad:
        with pytest.raises(ValueError, match=message) as caught:
            DepthRule.from_config(spec, "c.json")
        assert str(caught.value).startswith("c.json: ") and len(str(caught.value).splitlines()) == 1


def test_a_learned_field_holds_every_pixel_whose_ray_meets_the_table_whatever_its_depth_reads(table):
    from scenegen.perception.retrieval.regions import DEPTH_RULES, TABLE_HALF, table_rays

    frame, camera = table
    top = (frame.seg == frame.ids["table"]) & (frame.exact > 0)
    rays = table_rays(camera, frame.exact.shape)
    assert rays[top].all() and not table_rays(camera, frame.exact.shape, margin=-0.6).any()
    narrow = table_rays(camera, frame.exact.shape, margin=-0.2)
    assert 0 < narrow.sum() < rays.sum()
    wrong = np.where(top, 5.0, frame.exact).astype(np.float32)  # the sensor read the floor, far below
    rule = DEPTH_RULES["learned"]
    nobody = np.zeros_like(top)
    keep, _ = rule.foreground(wrong, nobody, camera)
    assert keep[top].all()  # off the table by its depth, on it by its ray
    keep, _ = DEPTH_RULES["mended_5mm"].foreground(wrong, nobody, camera)
    assert not keep[top].any()
    assert TABLE_HALF == (0.4, 0.5)
