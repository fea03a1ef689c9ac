"""The generation request: validation of its fields and the free-text parser."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from scenegen.schema.condition import (
    PANDA_JOINT_LIMITS,
    ROBOT_POSES,
    TAGS,
    TASKS,
    Condition,
    known_categories,
    parse_request,
)

HOME = ROBOT_POSES["home"]


def test_defaults_are_a_valid_request():
    c = Condition()
    assert c.task == "retrieve"
    assert c.target == "spoon"
    assert c.tags == {}
    assert c.robot_pose == HOME
    assert c.text is None
    assert c.required() == [] and c.forbidden() == []


def test_explicit_fields_and_named_pose():
    c = Condition(
        task="upright",
        target="mug",
        tags={"toppled": "required", "clutter": "forbidden", "near_edge": "unspecified"},
        robot_pose="ready",
    )
    assert (c.task, c.target) == ("upright", "mug")
    assert c.robot_pose == ROBOT_POSES["ready"]
    # "unspecified" is the absence of a tag; tags are sorted so equal requests compare equal.
    assert c.tags == {"clutter": "forbidden", "toppled": "required"}
    assert list(c.tags) == ["clutter", "toppled"]
    assert c.required() == ["toppled"] and c.forbidden() == ["clutter"]
    assert c == Condition(
        task="upright",
        target="mug",
        tags={"toppled": "required", "clutter": "forbidden"},
        robot_pose=ROBOT_POSES["ready"],
    )


def test_every_catalog_category_is_a_valid_target():
    for category in known_categories():
        assert Condition(target=category).target == category


def test_condition_is_frozen():
    c = Condition()
    with pytest.raises(ValidationError):
        c.task = "clear"


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        ("task", "juggle", ["unknown task 'juggle'", *TASKS]),
        ("target", "banana", ["unknown target 'banana'", *known_categories()]),
        ("tags", {"sparkly": "required"}, ["unknown tag 'sparkly'", *TAGS]),
        ("robot_pose", "crouch", ["unknown robot pose 'crouch'", *ROBOT_POSES]),
    ],
)
def test_unknown_choice_lists_the_valid_ones(field, value, expected):
    with pytest.raises(ValidationError) as info:
        Condition(**{field: value})
    message = str(info.value)
    for fragment in expected:
        assert fragment in message


def test_tag_state_must_be_one_of_three():
    with pytest.raises(ValidationError, match="required"):
        Condition(tags={"clutter": "maybe"})


@pytest.mark.parametrize(("joint", "value"), [(1, 3.0), (4, 0.0), (6, -0.5), (7, math.nan), (2, math.inf)])
def test_robot_pose_outside_joint_limits_is_rejected(joint, value):
    pose = list(HOME)
    pose[joint - 1] = value
    with pytest.raises(ValidationError, match=f"joint {joint} angle"):
        Condition(robot_pose=tuple(pose))


def test_robot_pose_at_the_joint_limits_is_accepted():
    lows = tuple(lo for lo, _ in PANDA_JOINT_LIMITS)
    highs = tuple(hi for _, hi in PANDA_JOINT_LIMITS)
    assert Condition(robot_pose=lows).robot_pose == lows
    assert Condition(robot_pose=highs).robot_pose == highs


def test_robot_pose_needs_seven_angles():
    with pytest.raises(ValidationError):
        Condition(robot_pose=HOME[:6])


def test_extra_keys_are_forbidden():
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        Condition(tagz={"clutter": "required"})


def test_parse_request_reads_task_target_tags_and_pose():
    parsed = parse_request("retrieve the spoon near edge, not clutter, robot at home")
    assert parsed == {
        "task": "retrieve",
        "target": "spoon",
        "tags": {"near_edge": "required", "clutter": "forbidden"},
        "robot_pose": "home",
    }


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Upright the MUG; toppled!", {"task": "upright", "target": "mug", "tags": {"toppled": "required"}}),
        (
            "clear a bowl under_overhang",
            {"task": "clear", "target": "bowl", "tags": {"under_overhang": "required"}},
        ),
        ("without low light, no on floor", {"tags": {"low_light": "forbidden", "on_floor": "forbidden"}}),
        ("", {}),
    ],
)
def test_parse_request_grammar(text, expected):
    assert parse_request(text) == expected


def test_condition_from_text():
    c = Condition(text="retrieve the spoon near edge, not clutter, robot at home")
    assert c.task == "retrieve"
    assert c.target == "spoon"
    assert c.tags == {"clutter": "forbidden", "near_edge": "required"}
    assert c.robot_pose == HOME
    assert c.text == "retrieve the spoon near edge, not clutter, robot at home"


def test_text_agreeing_with_explicit_fields_is_accepted():
    c = Condition(task="upright", target="mug", tags={"toppled": "required"}, text="upright the mug toppled")
    assert c.tags == {"toppled": "required"}


def test_unknown_word_is_named():
    with pytest.raises(ValueError, match="cannot place the word 'quickly'"):
        parse_request("retrieve the spoon quickly")
    with pytest.raises(ValidationError, match="'quickly'"):
        Condition(text="retrieve the spoon quickly")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"task": "upright", "text": "retrieve the spoon"}, "task"),
        ({"target": "mug", "text": "retrieve the spoon"}, "target"),
        ({"tags": {"clutter": "required"}, "text": "retrieve the spoon not clutter"}, "clutter"),
        ({"robot_pose": "ready", "text": "robot at home"}, "robot_pose"),
    ],
)
def test_text_conflicting_with_a_field_is_rejected(kwargs, match):
    with pytest.raises(ValidationError, match=match):
        Condition(**kwargs)


def test_text_naming_two_values_is_rejected():
    with pytest.raises(ValueError, match="two values for target"):
        parse_request("retrieve the spoon and the mug")


def test_negation_must_precede_a_tag():
    with pytest.raises(ValueError, match="at the end"):
        parse_request("retrieve the spoon not")
    with pytest.raises(ValueError, match="must be followed by a tag, got 'spoon'"):
        parse_request("retrieve not spoon")


def test_condition_from_text_round_trips_through_json():
    c = Condition(text="retrieve the spoon near edge, robot at home")
    assert Condition.model_validate(c.model_dump(mode="json")) == c


def test_double_negation_is_an_error():
    with pytest.raises(ValueError, match="'not' twice"):
        parse_request("retrieve the spoon not not clutter")
