"""Projection repairs (propose/project.py): each rejection that names an object and measures a margin
moves it by that margin, and the real check, settle and predicates then pass on what failed; what
has no projection is left to re-denoising; the constants a proposer may not import agree with the
checks' and predicates' own."""

from __future__ import annotations

import math

import pytest

from scenegen.check.geometry import CheckSettings, run_checks
from scenegen.core import layout
from scenegen.propose import project as proj
from scenegen.propose import tag_projection as tp
from scenegen.propose.moves import SLACK
from scenegen.runner.config import load_pipeline
from scenegen.runner.process import process_proposal
from scenegen.schema.condition import Condition
from scenegen.schema.scene import Rejection
from scenegen.tags.predicates import TagSettings


@pytest.fixture(scope="module")
def config():
    return load_pipeline("pipelines/procedural.yaml", {"render": False}, "retrieve the mug")


@pytest.fixture(scope="module")
def accepted(config):
    """A procedural proposal of a mug on the table, 10 cm or more from its edges, that the pipeline
    accepts, with three or more other objects on the table, one of them a stack base within reach."""
    from scenegen.propose.procedural import ProceduralProposer

    proposer = ProceduralProposer(config.proposer, config.catalog())
    for proposal in proposer.propose(config.condition, range(40), 3):
        target = next(o for o in proposal.objects if o.name == proposal.target)
        on_table = [o for o in proposal.objects if o.support == "table" and o.name != proposal.target]
        inside = abs(target.position[0]) < 0.25 and abs(target.position[1]) < 0.35  # 10 cm off every edge
        base = any(
            layout.is_stack_base(config.catalog().get(o.asset)) and o.position[0] < 0.15 for o in on_table
        )
        if target.support != "table" or len(on_table) < 3 or not inside or not base:
            continue
        if process_proposal(proposal, config, config.catalog(), export=False).record is not None:
            return proposal
    raise AssertionError("no accepted proposal with a mug on the table and three others")


def outcome(proposal, config, **tags):
    condition = Condition(task="retrieve", target="mug", tags=tags)
    return process_proposal(
        proposal.model_copy(update={"condition": condition}), config, config.catalog(), False
    )


def moved(proposal, name, x=None, y=None):
    objects = tuple(
        o.model_copy(
            update={
                "position": (
                    x if x is not None else o.position[0],
                    y if y is not None else o.position[1],
                    o.position[2],
                )
            }
        )
        if o.name == name
        else o
        for o in proposal.objects
    )
    return proposal.model_copy(update={"objects": objects})


def test_the_constants_agree_with_the_checks_and_predicates():
    assert tp.CLUTTER_RADIUS == TagSettings().clutter_radius
    assert tp.CLUTTER_COUNT == TagSettings().clutter_count
    assert tp.NEAR_EDGE == TagSettings().near_edge_distance
    assert tp.LOW_LIGHT == TagSettings().low_light_irradiance
    assert tp.OVERHANG_COVER == TagSettings().overhang_cover
    assert tp.TOPPLED_DEG == pytest.approx(math.degrees(TagSettings().toppled_angle))
    assert tp.OCCLUDED == TagSettings().occluded_fraction
    assert (CheckSettings().reach_min, CheckSettings().reach_max) == layout.REACH


def test_out_of_the_workspace_moved_back_inside(accepted, config):
    other = next(o for o in accepted.objects if o.support == "table" and o.name != accepted.target)
    off = moved(accepted, other.name, x=0.47)
    results, _ = run_checks(off, config.catalog(), config.checks)
    failed = results[-1]
    assert failed.label == "out_of_workspace" and failed.detail == other.name
    rejection = Rejection(
        proposal_index=0,
        stage="check",
        label=failed.label,
        check=failed.check,
        value=failed.value,
        threshold=failed.threshold,
        detail=failed.detail,
    )
    fixed, names = proj.project(off, rejection, config.catalog())
    assert names[0] == other.name
    back, _ = run_checks(fixed, config.catalog(), config.checks)
    assert back[0].passed and back[0].value >= SLACK - 1e-6
    placed = next(o for o in fixed.objects if o.name == other.name)
    assert placed.projection_distance > 0.07  # the move is in its provenance


def test_a_missed_near_edge_moved_by_its_margin_then_holds(accepted, config):
    first = outcome(accepted, config, near_edge="required")
    if first.record is not None:
        pytest.skip("the mug is near an edge already")
    assert first.rejection.label == "condition_unmet" and "near_edge" in first.rejection.detail
    fixed, names = proj.project(accepted, first.rejection, config.catalog())
    assert accepted.target in names
    after = outcome(fixed, config, near_edge="required")
    if after.record is None and after.rejection.label == "collision":  # moved into a neighbour: apart
        fixed, _ = proj.project(fixed, after.rejection, config.catalog())
        after = outcome(fixed, config, near_edge="required")
    assert after.record is not None, after.rejection.detail
    tags = after.record.tags
    assert tags["near_edge"].holds and tags["near_edge"].value <= TagSettings().near_edge_distance


def test_a_missed_low_light_scales_the_lights_below_the_threshold(accepted, config):
    first = outcome(accepted, config, low_light="required")
    assert first.rejection is not None and "low_light" in first.rejection.detail
    fixed, names = proj.project(accepted, first.rejection, config.catalog())
    assert names == ("lights",) and fixed.objects == accepted.objects
    after = outcome(fixed, config, low_light="required")
    assert after.record is not None, after.rejection.detail
    assert after.record.tags["low_light"].value == pytest.approx(
        0.9 * TagSettings().low_light_irradiance, rel=0.02
    )


def test_an_aimed_low_light_turns_the_lights_off_the_target_and_keeps_their_strength(accepted, config):
    """``proposer.light_projection: aim``: the lights whose cones hold the target are turned off it
    (intensities and ambient kept where turning is enough, as the reference darkens a target), and
    the real predicate then holds on the settled scene."""
    lights = tuple(  # every light aimed straight at the mug: turning, not dimming, must do it
        light.model_copy(update={"direction": tuple(_toward(light.position, accepted, config))})
        for light in accepted.lighting.lights
    )
    lit = accepted.model_copy(update={"lighting": accepted.lighting.model_copy(update={"lights": lights})})
    first = outcome(lit, config, low_light="required")
    assert first.rejection is not None and "low_light" in first.rejection.detail
    fixed, names = proj.project(lit, first.rejection, config.catalog(), light="aim")
    assert names == ("lights",) and fixed.objects == lit.objects
    assert sum(lit.lighting.ambient) / 3 < 0.9 * tp.LOW_LIGHT  # the ambient alone is dark enough here
    assert fixed.lighting.ambient == lit.lighting.ambient
    assert [x.intensity for x in fixed.lighting.lights] == [x.intensity for x in lit.lighting.lights]
    assert all(
        x.direction != y.direction for x, y in zip(fixed.lighting.lights, lit.lighting.lights, strict=True)
    )
    after = outcome(fixed, config, low_light="required")
    assert after.record is not None, after.rejection.detail
    assert after.record.tags["low_light"].holds
    with pytest.raises(ValueError, match="light_projection 'dim'"):
        tp.steps("dim")


def _toward(position, proposal, config):
    top = tp._target_top(proposal, config.catalog())
    d = [t - p for t, p in zip(top, position, strict=True)]
    norm = math.sqrt(sum(v * v for v in d))
    return [round(v / norm, 6) for v in d]


def test_a_missed_clutter_brings_the_nearest_others_in(accepted, config):
    first = outcome(accepted, config, clutter="required")
    if first.record is not None:
        pytest.skip("the mug is cluttered already")
    fixed, names = proj.project(accepted, first.rejection, config.catalog())
    assert names and accepted.target not in names
    after = outcome(fixed, config, clutter="required")
    if after.record is None:  # a push apart may have left a pair overlapping: the collision's projection
        assert after.rejection.label in ("collision", "out_of_workspace"), after.rejection.detail
    else:
        assert after.record.tags["clutter"].holds


def test_what_has_no_projection_is_left_to_denoising(accepted, config):
    for label, detail, stage in [
        ("condition_unmet", "forbidden clutter = 4.0 objects (threshold 3.0)", "tag"),
        (
            "condition_unmet",
            "required near_edge = 0.2 m (threshold 0.03); forbidden occluded = 0.7 fraction (threshold 0.5)",
            "tag",
        ),
        ("unstable", "not still within max_time", "settle"),
        ("unrealistic", "", "tag"),
    ]:
        rejection = Rejection(proposal_index=0, stage=stage, label=label, check="x", detail=detail)
        assert proj.project(accepted, rejection, config.catalog()) is None, label


def test_without_denoising_only_projections_repair(accepted, config):
    """generator_v3's repairs: a projection where there is one (a step named ``project``), else none,
    so the index ends and the next proposal is fresh; at most PROJECT_RUN projections in a row."""
    from scenegen.propose.diffusion import PROJECT_RUN, DiffusionProposer

    v3 = load_pipeline("pipelines/generator_v3.yaml", {"render": False}, "retrieve the mug")
    proposer = DiffusionProposer(v3.proposer, v3.catalog())
    other = next(o for o in accepted.objects if o.support == "table" and o.name != accepted.target)
    off = moved(accepted, other.name, x=0.47)
    outside = Rejection(
        proposal_index=0,
        stage="check",
        label="out_of_workspace",
        check="workspace",
        detail=other.name,
        value=-0.07,
        threshold=0.0,
    )
    crowded = Rejection(
        proposal_index=0,
        stage="tag",
        label="condition_unmet",
        check="condition",
        detail="forbidden clutter = 4.0 objects (threshold 3.0)",
    )
    assert proposer.repair(off, crowded, 1) is None
    child = off
    for attempt in range(1, PROJECT_RUN + 1):
        child = proposer.repair(child.model_copy(update={"objects": off.objects}), outside, attempt)
        assert child is not None and child.repairs[-1].method == "project"
        assert child.repairs[-1].resampled[0] == other.name
    assert (
        proposer.repair(child.model_copy(update={"objects": off.objects}), outside, PROJECT_RUN + 1) is None
    )


def test_a_missed_occluded_sets_the_tallest_other_between_target_and_camera(accepted, config):
    first = outcome(accepted, config, occluded="required")
    if first.record is not None:
        pytest.skip("the mug is hidden already")
    fixed, names = proj.project(accepted, first.rejection, config.catalog())
    after = outcome(fixed, config, occluded="required")
    measured = after.record.tags["occluded"] if after.record is not None else None
    if measured is None:  # the occluder may land on another object: the collision's projection next
        assert after.rejection.label in ("collision", "condition_unmet"), after.rejection.detail
        if after.rejection.label == "condition_unmet":
            value = float(after.rejection.detail.split("= ")[1].split(" ")[0])
            before = float(first.rejection.detail.split("= ")[1].split(" ")[0])
            assert value > before  # more of the target hidden than before
    else:
        assert measured.holds


def test_anticipate_occluded_sets_the_occluder_before_the_first_check(accepted, config):
    """A required occluded, which only the settled scene measures: left to the checks by default;
    with ``occluded`` the tallest other object is set between target and camera before any check,
    the step the repair takes after a miss, and the real predicate then measures more of the target
    hidden than without it."""
    asked = accepted.model_copy(
        update={"condition": Condition(task="retrieve", target="mug", tags={"occluded": "required"})}
    )
    assert proj.anticipated(asked, config.catalog()) == asked
    placed = proj.anticipated(asked, config.catalog(), occluded=True)
    stepped, names = tp.occluded(asked, "required", 0.0, tp.OCCLUDED, config.catalog())
    occluder = names[0]
    assert placed != asked and occluder != asked.target
    assert next(o for o in placed.objects if o.name == occluder).position[:2] == pytest.approx(
        next(o for o in stepped.objects if o.name == occluder).position[:2], abs=0.06
    )  # where the step put it, give or take the push apart that follows (max_shift)

    def hidden(proposal) -> float:
        result = process_proposal(proposal, config, config.catalog(), False)
        if result.record is not None:
            return result.record.tags["occluded"].value
        assert result.rejection.label == "condition_unmet", result.rejection
        return float(result.rejection.detail.split("= ")[1].split(" ")[0])

    assert hidden(placed) > hidden(asked)


def test_anticipated_places_the_request_s_geometric_tags_before_any_check(accepted, config):
    """near_edge and clutter measured by the proposer on the placed scene and projected before the
    first check: the real predicates then hold after settling."""
    condition = Condition(
        task="retrieve", target="mug", tags={"near_edge": "required", "clutter": "required"}
    )
    asked = accepted.model_copy(update={"condition": condition})
    placed = proj.anticipated(asked, config.catalog())
    target = next(o for o in placed.objects if o.name == placed.target)
    assert tp.edge_margin(config.catalog(), target) <= tp.NEAR_EDGE
    result = process_proposal(placed, config, config.catalog(), False)
    if result.record is None:  # settling or a push apart may still undo it: the repairs' business
        assert result.rejection.label in ("collision", "unstable", "condition_unmet"), result.rejection
    else:
        assert result.record.tags["near_edge"].holds and result.record.tags["clutter"].holds
    plain = accepted.model_copy(update={"condition": Condition(task="retrieve", target="mug")})
    assert proj.anticipated(plain, config.catalog()) == plain  # nothing asked, nothing outside: unchanged


@pytest.mark.parametrize("tag", ["toppled", "stacked", "on_floor", "low_light", "under_overhang"])
def test_a_missed_discrete_tag_or_light_is_met_after_settling(accepted, config, tag):
    """toppled (the likeliest pose that is not upright), stacked (onto the nearest free stack base),
    on_floor (onto the floor strip), low_light (the unshadowed bound projected below the threshold)
    projected before any check; the real predicates measure the tag on the settled scene."""
    plain = accepted.model_copy(update={"condition": Condition(task="retrieve", target="mug")})
    state = "forbidden" if tp.before_check(plain, tag, config.catalog())[2] else "required"
    condition = Condition(task="retrieve", target="mug", tags={tag: state})
    asked = accepted.model_copy(update={"condition": condition})
    placed = proj.anticipated(asked, config.catalog())
    assert tp.before_check(placed, tag, config.catalog())[2] == (state == "required")
    result = process_proposal(placed, config, config.catalog(), False)
    if tag == "stacked" and result.record is None:  # a base too small or round may not hold it still
        assert result.rejection.label in ("unstable", "fell_off", "condition_unmet"), result.rejection
        return
    assert result.record is not None, result.rejection
    assert result.record.tags[tag].holds == (state == "required")


def test_the_light_bound_is_at_least_what_the_predicate_measures(accepted, config):
    """No shadow in the bound: it is at or above the settled scene's measured irradiance."""
    result = process_proposal(accepted, config, config.catalog(), False)
    measured = result.record.tags["low_light"].value
    assert tp.irradiance_bound(accepted, config.catalog()) >= measured - 1e-3


@pytest.mark.parametrize("tag", ["clutter", "occluded", "stacked"])
def test_a_tag_asked_of_a_target_on_the_floor_is_met_on_the_floor(accepted, config, tag):
    """on_floor with clutter, occluded or stacked: the neighbours, the occluder or the stack base are
    brought down onto the floor strip beside the target (nothing left floating over it), the
    workspace and reachability checks take a stack standing on the floor as on the floor, and the
    real predicates measure both tags on the settled scene."""
    condition = Condition(task="retrieve", target="mug", tags={"on_floor": "required", tag: "required"})
    small = [o for o in accepted.objects if o.name != accepted.target and o.support == "table"]
    small = min(small, key=lambda o: layout.footprint_radius(config.catalog().get(o.asset), o.resting_pose))
    z = small.position[2] - layout.TABLE_TOP_Z + layout.FLOOR.z
    bottle = config.catalog().get("bottle").resting_poses[0]  # upright, taller than the mug
    extra = {  # on the floor's far end: two more of the smallest, so that three fit beside the mug; a
        # bottle, tall enough to hide the mug from a camera 45 degrees above it
        "clutter": [
            small.model_copy(update={"name": f"obj{8 + k}_x", "support": "floor", "position": (-0.3, y, z)})
            for k, y in enumerate((0.6, 0.76))
        ],
        "occluded": [
            small.model_copy(
                update={
                    "name": "obj8_x",
                    "asset": "bottle",
                    "support": "floor",
                    "resting_pose": 0,
                    "quat": bottle.quat,
                    "position": (-0.3, 0.76, layout.FLOOR.z + bottle.height),
                }
            )
        ],
    }.get(tag, [])
    asked = accepted.model_copy(update={"condition": condition, "objects": (*accepted.objects, *extra)})
    placed = proj.anticipated(asked, config.catalog())
    if tag != "clutter":  # what the proposer cannot measure (occluded) or repairs after the check
        first = process_proposal(placed, config, config.catalog(), False)
        if first.record is None and first.rejection.label == "condition_unmet":
            placed = proj.project(placed, first.rejection, config.catalog())[0]
    target = next(o for o in placed.objects if o.name == placed.target)
    assert layout.stack_ground(placed, target.name) == "floor"
    for o in placed.objects:  # each object over the region of the ground its stack stands on
        region = layout.FLOOR if layout.stack_ground(placed, o.name) == "floor" else None
        if region is not None:
            assert region.margin(o.position[:2]) >= 0, o
    result = process_proposal(placed, config, config.catalog(), False)
    assert result.record is not None, result.rejection
    assert result.record.tags["on_floor"].holds and result.record.tags[tag].holds


@pytest.mark.parametrize(("shelf_y", "mug_y", "along"), [(0.3, 0.3, False), (0.2, 0.25, True)])
def test_a_near_edge_projection_keeps_a_required_under_overhang(accepted, config, shelf_y, mug_y, along):
    """A mug under the shelf (turned to open toward the +y edge) asked near_edge and under_overhang:
    moved alone toward the edge while it stays under the board, or with the shelf when alone it
    would leave it; the real predicates then measure both on the settled scene."""
    shelf = next(p for p in accepted.furniture if p.kind == "shelf")
    shelf = shelf.model_copy(update={"position": (0.0, shelf_y, 0.0), "yaw": math.pi / 2})
    mug = next(o for o in accepted.objects if o.name == accepted.target)
    mug = mug.model_copy(update={"position": (0.0, mug_y, mug.position[2])})
    condition = Condition(
        task="retrieve", target="mug", tags={"near_edge": "required", "under_overhang": "required"}
    )
    asked = accepted.model_copy(update={"objects": (mug,), "furniture": (shelf,), "condition": condition})
    assert tp.covering(asked, config.catalog(), mug.name) == shelf
    placed, _ = tp.near_edge(asked, "required", 0.2, tp.NEAR_EDGE, config.catalog())
    moved_mug = placed.objects[0].position[1] - mug_y
    moved_shelf = placed.furniture[0].position[1] - shelf_y
    assert moved_mug > 0 and moved_shelf == pytest.approx(moved_mug if along else 0.0, abs=1e-6)
    result = process_proposal(placed, config, config.catalog(), False)
    assert result.record is not None, result.rejection
    assert result.record.tags["near_edge"].holds and result.record.tags["under_overhang"].holds
