"""The proposal model's candidates (issue 63, point 1): drawn by one generic sampler from what the
robot sees, on a plan grid, and executed for real through robosuite's controller."""

from __future__ import annotations

import functools
import sys

import numpy as np
import pytest
from scenes import place, proposal

from scenegen.assets.catalog import load_catalog
from scenegen.core.layout import FURNITURE_HOME
from scenegen.env.scenes import proposal_scene
from scenegen.experiment.sequences import candidate_token, decision_token
from scenegen.manipulation import proposals
from scenegen.manipulation.primitives import PlanGrid
from scenegen.manipulation.proposals import Candidate, SamplerConfig, sample_candidates
from scenegen.manipulation.rollout import run_candidate
from scenegen.manipulation.task import LIFT_HEIGHT
from scenegen.perception.observation import observe
from scenegen.perception.robot_state import finger_gap
from scenegen.schema.scene import FurniturePlacement, Light, Lighting

LIGHT = Lighting(lights=(Light(position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), intensity=0.8),))
SHELF = FurniturePlacement(name="shelf", kind="shelf", position=(*FURNITURE_HOME["shelf"], 0.0))
GRID = PlanGrid(metres=0.005, degrees=10.0)


@functools.cache
def catalog():
    return load_catalog()


def can_scene(x: float = 0.1, y: float = 0.0, shelf: bool = False):
    """A soda can standing at (x, y), optionally under the shelf's board."""
    furniture = [SHELF] if shelf else []
    can = place(catalog(), "can", "soda_can", x, y, pose=1, yaw=0.6, furniture=furniture)
    return proposal_scene(proposal([can], furniture, lighting=LIGHT), f"can_{x}_{y}_{shelf}")


def mug_scene(pose: int):
    """A mug upright (resting pose 2) or lying on its side (pose 0: toppled)."""
    mug = place(catalog(), "mug", "mug", 0.1, 0.0, pose=pose, yaw=0.6)
    return proposal_scene(proposal([mug], lighting=LIGHT), f"mug_{pose}")


@pytest.fixture(scope="module")
def env():
    from scenegen.env.robosuite_env import SceneEnv

    options = {"cameras": ["front", "side"], "camera_size": (320, 240), "render_each_step": False}
    env = SceneEnv(can_scene(), horizon=2000, **options)
    yield env
    env.close()


def _view(env, scene):
    env.reset_to(scene)
    _, view = observe(env)
    assert view is not None and view.target_points is not None
    return view


def _lines(function, *args, **kwargs) -> tuple[set[int], object]:
    """The lines of proposals.py that ``function(*args)`` runs, and its result."""
    ran: set[int] = set()

    def trace(frame, event, arg):
        if frame.f_code.co_filename == proposals.__file__ and event == "line":
            ran.add(frame.f_lineno)
        return trace

    sys.settrace(trace)
    try:
        result = function(*args, **kwargs)
    finally:
        sys.settrace(None)
    return ran, result


def test_an_upright_and_a_toppled_mug_get_their_candidates_from_one_code_path(env):
    upright, toppled = _view(env, mug_scene(2)), _view(env, mug_scene(0))
    assert catalog().get("mug").resting_poses[0].upright is False
    assert abs(toppled.target.height - upright.target.height) > 0.01  # they lie differently, as seen
    lines_up, up = _lines(sample_candidates, upright, np.random.default_rng(0), grid=GRID)
    lines_down, down = _lines(sample_candidates, toppled, np.random.default_rng(0), grid=GRID)
    assert lines_up == lines_down and len(lines_up) > 20
    assert up != down
    for view, candidates in ((upright, up), (toppled, down)):
        points = view.target_points
        for c in candidates:
            at = np.asarray(c.params.get("position", c.params.get("contact")))
            horizontal = c.action == "pull" or c.params.get("approach") == "side"
            margin = 0.01 + (proposals.REACH_IN if horizontal else 0.0)  # a side hand reaches in
            assert np.all(at[:2] >= points[:, :2].min(0) - margin) and np.all(
                at[:2] <= points[:, :2].max(0) + margin
            )
            assert points[:, 2].min() - 0.005 <= at[2] <= points[:, 2].max() + 0.005, c


def bowl_scene():
    """A bowl standing upright: wider than the hand spans."""
    bowl = place(catalog(), "bowl", "bowl", 0.1, 0.0, pose=1, yaw=0.3)
    return proposal_scene(proposal([bowl], lighting=LIGHT), "bowl_upright")


def test_a_top_grasp_closes_across_what_it_sees_from_both_sides_or_on_a_rim(env):
    """Its centre lies on a line of visible points along its closing axis: midway between the line's
    extremes where the hand spans them, EDGE_IN inside an end where it does not (a bowl's rim); the
    grip site never under the line's mid-height. A standing can, a lying mug and a bowl alike."""
    config = SamplerConfig(top=16, side=0, push=0, pull=0)
    spans = {"narrow": 0, "wide": 0}
    for scene in (can_scene(), mug_scene(0), bowl_scene()):
        view = _view(env, scene)
        points = np.asarray(view.target_points)
        for c in sample_candidates(view, np.random.default_rng(5), config):
            axis, at = np.asarray(c.params["heading"]), np.asarray(c.params["position"])
            across = np.array([-axis[1], axis[0]])
            line = points[np.abs((points[:, :2] - at[:2]) @ across) < proposals.STRIP - 1e-9]
            assert len(line) > 0, c
            along = line[:, :2] @ axis
            lo, hi, u = along.min(), along.max(), at[:2] @ axis
            if hi - lo <= proposals.MAX_GRASP_WIDTH:
                spans["narrow"] += 1
                assert u == pytest.approx(0.5 * (lo + hi), abs=1e-6), c
            else:
                spans["wide"] += 1
                assert min(abs(u - lo), abs(hi - u)) == pytest.approx(proposals.EDGE_IN, abs=1e-6), c
            heights = np.percentile(line[:, 2], [2, 98])
            assert heights.mean() - 1e-9 <= at[2] <= heights[1] + 1e-9, c
    assert spans["narrow"] > 0 and spans["wide"] > 0  # both rules ran


def test_a_horizontal_hand_reaches_past_the_surface_it_sees_and_stays_clear_of_the_table(env):
    view = _view(env, can_scene())
    points = np.asarray(view.target_points)
    config = SamplerConfig(top=0, side=12, push=0, pull=4)
    reaches = []
    for c in sample_candidates(view, np.random.default_rng(3), config):
        heading = np.asarray(c.params.get("heading", c.params.get("approach")))
        at = np.asarray(c.params["position"])
        # the grip site is a visible point moved along the approach: into the body, never back out
        back = at[:2] - points[:, :2]
        along = back @ heading
        across = np.abs(back @ np.array([-heading[1], heading[0]]))
        fits = (across < 1e-9) & (along > -1e-9) & (along <= proposals.REACH_IN + 1e-9)
        assert fits.any(), c
        reaches.append(along[fits].max())
        low = np.percentile(points[:, 2], 2)
        assert at[2] >= low + proposals.SIDE_CLEARANCE - 1e-9, c
    assert max(reaches) > 0.02  # some reach well inside


def test_the_sampler_is_seeded_counts_its_kinds_and_lands_on_the_grid(env):
    view = _view(env, can_scene())
    config = SamplerConfig(top=5, side=4, push=3, pull=2)
    first = sample_candidates(view, np.random.default_rng(7), config)
    assert first == sample_candidates(view, np.random.default_rng(7), config)
    assert first != sample_candidates(view, np.random.default_rng(8), config)
    kinds = [(c.action, c.params.get("approach") if c.action == "grasp" else None) for c in first]
    assert (
        kinds
        == [("grasp", "top")] * 5 + [("grasp", "side")] * 4 + [("push", None)] * 3 + [("pull", None)] * 2
    )
    snapped = sample_candidates(view, np.random.default_rng(7), config, grid=GRID)
    assert 0 < len(snapped) <= config.total
    for c in snapped:
        assert c == Candidate(c.action, GRID.snap(c.params))  # on the grid already
        for name in ("heading", "direction"):
            if name in c.params:
                angle = np.degrees(np.arctan2(*c.params[name][::-1]))
                assert angle / GRID.degrees == pytest.approx(round(angle / GRID.degrees), abs=1e-6)
    dense = PlanGrid(metres=0.2, degrees=90.0)  # a coarse grid merges candidates
    assert len(sample_candidates(view, np.random.default_rng(7), config, grid=dense)) < config.total


def test_a_candidate_names_a_known_action_and_a_view_without_points_is_refused(env):
    with pytest.raises(ValueError, match="candidate action 'throw'"):
        Candidate("throw", {})
    view = _view(env, can_scene())
    bare = type(view)(view.target, view.others, view.robot_base, view.hand_closing)
    with pytest.raises(ValueError, match="no target points"):
        sample_candidates(bare, np.random.default_rng(0))


def test_a_candidates_token_keys_its_action_versions_and_parameters():
    c = Candidate("grasp", {"approach": "top", "position": [0.1, 0.0, 0.85], "heading": [1.0, 0.0]})
    token = candidate_token(c)
    assert token.startswith(f"grasp@1s{proposals.SAMPLER_VERSION}:")
    assert token == candidate_token(Candidate.from_dict(c.as_dict()))
    moved = Candidate("grasp", {**c.params, "position": [0.1, 0.005, 0.85]})
    assert candidate_token(moved) != token
    # a hand planner's plan with the same numbers is another attempt: the name and version lead
    assert decision_token("top_grasp", c.params).split(":")[1] == token.split(":")[1]
    assert decision_token("top_grasp", c.params) != token


def test_a_top_grasp_candidate_lifts_an_upright_can_and_one_beside_it_does_not(env):
    view = _view(env, can_scene())
    t = view.target
    top = [float(t.centre[0]), float(t.centre[1]), t.top_z - 0.03]
    on = Candidate("grasp", {"approach": "top", "position": top, "heading": [0.0, 1.0]})
    outcome = run_candidate(env, on)
    assert outcome.success and outcome.lift >= LIFT_HEIGHT, outcome
    env.reset_to(can_scene())
    beside = Candidate("grasp", {**on.params, "position": [top[0], top[1] + 0.09, top[2]]})
    missed = run_candidate(env, beside)
    assert not missed.success and missed.lift < 0.01
    # the fingers felt nothing: open, risen, over before a lift and hold would have ended it
    assert finger_gap(env) > 0.03 and missed.time < outcome.time - 1.0, (missed.time, outcome.time)


def test_a_side_grasp_candidate_lifts_an_upright_can_from_the_robots_side(env):
    view = _view(env, can_scene())
    t = view.target
    grip = [float(t.centre[0]), float(t.centre[1]), t.bottom_z + 0.03]
    side = Candidate("grasp", {"approach": "side", "position": grip, "heading": [1.0, 0.0]})
    outcome = run_candidate(env, side)
    assert outcome.success and outcome.lift >= LIFT_HEIGHT, outcome


def test_a_push_moves_the_target_along_its_direction_and_ends_open_without_a_lift(env):
    view = _view(env, can_scene(y=0.3))
    before = env.target_pose()[0].copy()
    t = view.target
    contact = [float(t.centre[0]), float(t.centre[1] + 0.5 * t.extent[1]), t.bottom_z + 0.015]
    push = Candidate("push", {"contact": contact, "direction": [0.0, -1.0], "distance": 0.10})
    outcome = run_candidate(env, push)
    moved = env.target_pose()[0] - before
    assert not outcome.success and outcome.lift < 0.02
    assert -0.16 < moved[1] < -0.05 and abs(moved[0]) < 0.04, moved
    assert finger_gap(env) > 0.03  # open: the next decision starts from a free hand


def test_a_pull_drags_a_can_out_from_under_the_shelf_and_lets_go(env):
    view = _view(env, can_scene(x=0.17, y=0.27, shelf=True))
    before = env.target_pose()[0].copy()
    t = view.target
    grip = [float(t.centre[0]), float(t.centre[1]), t.bottom_z + 0.03]
    pull = Candidate("pull", {"position": grip, "approach": [1.0, 0.0], "distance": 0.20})
    outcome = run_candidate(env, pull)
    moved = env.target_pose()[0] - before
    assert not outcome.success and moved[0] < -0.08, moved  # towards the robot, out in the open
    assert finger_gap(env) > 0.03
