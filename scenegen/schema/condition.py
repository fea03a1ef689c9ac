"""The request a batch is generated for: task, target, rare-case tags, robot initial pose.

Condition semantics (shared/DESIGN.md): each rare-case tag is ``required``, ``forbidden`` or
``unspecified``; a tag not named is unspecified. The null condition (unconditional sampling) is a
separate notion of the generator, not a value of these fields.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator
from contextvars import ContextVar
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

TagState = Literal["required", "forbidden", "unspecified"]

# Task registry: what the target is for. A dict, documented here and in docs/conditions.md.
TASKS: dict[str, str] = {
    "retrieve": "grasp the target and lift it clear of its support",
    "upright": "stand a toppled target back on its upright resting pose",
    "clear": "move the objects around the target so that it can be grasped",
}

# Rare-case tags, measured on the settled scene (predicates arrive with the rare-case issue).
RARE_TAGS: tuple[str, ...] = (
    "near_edge",
    "under_overhang",
    "toppled",
    "occluded",
    "clutter",
    "stacked",
    "low_light",
    "on_floor",
)
TAGS: tuple[str, ...] = (*RARE_TAGS, "nominal")

# Panda joint limits (radians), from robosuite 1.5.2's robot model; the pose is checked against them.
PANDA_JOINT_LIMITS: tuple[tuple[float, float], ...] = (
    (-2.8973, 2.8973),
    (-1.7628, 1.7628),
    (-2.8973, 2.8973),
    (-3.0718, -0.0698),
    (-2.8973, 2.8973),
    (-0.0175, 3.7525),
    (-2.8973, 2.8973),
)
# Named initial poses. `home` is robosuite's Panda init_qpos.
ROBOT_POSES: dict[str, tuple[float, ...]] = {
    "home": (0.0, 0.19634954, 0.0, -2.61799388, 0.0, 2.94159265, 0.78539816),
    "ready": (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785),
}


_VOUCHED: ContextVar[frozenset[str]] = ContextVar("scenegen_vouched_categories", default=frozenset())


@contextlib.contextmanager
def vouched_categories(categories) -> Iterator[None]:
    """Within the block, ``categories`` are known too: a stored scene vouches for the categories of
    its own objects (they came from the user catalogs it was made with), so reading it needs none."""
    token = _VOUCHED.set(_VOUCHED.get() | frozenset(c for c in categories if isinstance(c, str)))
    try:
        yield
    finally:
        _VOUCHED.reset(token)


def vouch_for_objects(data, handler):
    """A wrap validator's body for a record holding ``objects``: validate it with their categories
    vouched for (:func:`vouched_categories`)."""
    objects = data.get("objects") if isinstance(data, dict) else None
    categories = [o.get("category") for o in objects or () if isinstance(o, dict)]
    with vouched_categories(categories):
        return handler(data)


def known_categories() -> tuple[str, ...]:
    """Object categories of the asset catalogs in use (the valid targets): the bundled catalog, the
    user catalogs a recipe names while it is validated (``assets.catalog.using_catalogs``), and those
    a stored scene vouches for (:func:`vouched_categories`)."""
    from scenegen.assets.catalog import active_catalog

    return tuple(sorted(set(active_catalog().categories) | _VOUCHED.get()))


def known_task(task: str) -> str:
    """``task`` if it is in the registry, else a ValueError listing the valid ones."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {', '.join(TASKS)}")
    return task


def known_pose_name(name: str) -> str:
    """``name`` if it names a robot pose, else a ValueError listing the valid names."""
    if name not in ROBOT_POSES:
        raise ValueError(f"unknown robot pose {name!r}; valid names: {', '.join(ROBOT_POSES)}")
    return name


class Condition(BaseModel):
    """A generation request.

    Fields:
        task: a key of ``TASKS``.
        target: an object category of the asset catalog (``spoon``, ``mug``, ...).
        tags: rare-case tag -> ``required`` / ``forbidden`` / ``unspecified``; absent = unspecified.
        robot_pose: 7 Panda joint angles in radians, or the name of a pose in ``ROBOT_POSES``.
        text: optional free text, parsed by :func:`parse_request` into the fields above; a word the
            parser cannot place is an error.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str = "retrieve"
    target: str = "spoon"
    tags: dict[str, TagState] = Field(default_factory=dict)
    robot_pose: tuple[float, float, float, float, float, float, float] = ROBOT_POSES["home"]
    text: str | None = None

    @model_validator(mode="before")
    @classmethod
    def _apply_text(cls, data):
        if not isinstance(data, dict) or not data.get("text"):
            return data
        parsed = parse_request(data["text"])
        merged = dict(data)
        for key, value in parsed.items():
            if key == "tags":
                tags = dict(merged.get("tags") or {})
                for tag, state in value.items():
                    if tags.get(tag, state) != state:
                        raise ValueError(f"text: tag {tag!r} is {state} in the text but {tags[tag]} in tags")
                    tags[tag] = state
                merged["tags"] = tags
            elif key in data and _canonical(key, data[key]) != _canonical(key, value):
                raise ValueError(f"text: says {key}={value!r} but the field {key} is {data[key]!r}")
            else:
                merged[key] = value
        return merged

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        return known_task(task)

    @field_validator("target")
    @classmethod
    def _known_target(cls, target: str) -> str:
        categories = known_categories()
        if target not in categories:
            raise ValueError(f"unknown target {target!r}; valid targets: {', '.join(categories)}")
        return target

    @field_validator("tags")
    @classmethod
    def _known_tags(cls, tags: dict[str, TagState]) -> dict[str, TagState]:
        for tag in tags:
            if tag not in TAGS:
                raise ValueError(f"unknown tag {tag!r}; valid tags: {', '.join(TAGS)}")
        # Drop explicit "unspecified" and sort, so equal requests compare and hash equal.
        return {t: tags[t] for t in sorted(tags) if tags[t] != "unspecified"}

    @field_validator("robot_pose", mode="before")
    @classmethod
    def _named_pose(cls, pose):
        return ROBOT_POSES[known_pose_name(pose)] if isinstance(pose, str) else pose

    @field_validator("robot_pose")
    @classmethod
    def _within_limits(cls, pose: tuple[float, ...]) -> tuple[float, ...]:
        for i, (q, (lo, hi)) in enumerate(zip(pose, PANDA_JOINT_LIMITS, strict=True)):
            if not math.isfinite(q) or not lo <= q <= hi:
                raise ValueError(f"joint {i + 1} angle {q} rad is outside the Panda's range [{lo}, {hi}]")
        return pose

    def required(self) -> list[str]:
        return [t for t, s in self.tags.items() if s == "required"]

    def forbidden(self) -> list[str]:
        return [t for t, s in self.tags.items() if s == "forbidden"]


# Words the parser accepts without meaning; everything else must be a task, target, tag or pose.
_FILLER = frozenset(
    "a an the with and in on at its is has robot starts start pose from of to scene where".split()
)
_NEGATIONS = frozenset({"not", "no", "without"})


def parse_request(text: str) -> dict:
    """Parse free text such as ``"retrieve the spoon near edge, not clutter, robot at home"``.

    Grammar (case-insensitive, punctuation ignored): task names, target categories, tag names (with
    ``_`` or a space between words), ``not``/``no``/``without`` before a tag to forbid it, and
    robot pose names. Filler words (``the``, ``with``, ``robot`` ...) are skipped. Any other word is
    an error naming it: a request is never silently half-understood.
    """
    words = re.findall(r"[a-z0-9_]+", text.lower())
    categories = set(known_categories())
    out: dict = {"tags": {}}
    negate = False
    i = 0
    while i < len(words):
        word = words[i]
        two = f"{word}_{words[i + 1]}" if i + 1 < len(words) else None
        if two in TAGS:
            word, i = two, i + 1
        if word in _NEGATIONS:
            if negate:
                raise ValueError("text: 'not' twice in a row; write 'not TAG' once")
            negate = True
        elif word in TAGS:
            out["tags"][word] = "forbidden" if negate else "required"
            negate = False
        elif word in TASKS:
            _set_once(out, "task", word)
        elif word in categories:
            _set_once(out, "target", word)
        elif word in ROBOT_POSES:
            _set_once(out, "robot_pose", word)
        elif word not in _FILLER:
            import difflib

            close = difflib.get_close_matches(word, [*TASKS, *categories, *TAGS, *ROBOT_POSES], n=2)
            hint = f" (did you mean {' or '.join(close)}?)" if close else ""
            raise ValueError(
                f"text: cannot place the word {_shown(word)}{hint}; use task names ({', '.join(TASKS)}), "
                f"tags ({', '.join(TAGS)}), 'not' before a tag, robot poses ({', '.join(ROBOT_POSES)}) "
                f"or targets ({', '.join(sorted(categories))})"
            )
        if negate and word not in _NEGATIONS:
            raise ValueError(f"text: 'not' must be followed by a tag, got {_shown(word)}")
        i += 1
    if negate:
        raise ValueError("text: 'not' at the end must be followed by a tag")
    if not out["tags"]:
        del out["tags"]
    return out


def _canonical(key: str, value):
    """A field value in comparable form: pose names become their joint angles (rounded to 1e-6 rad)."""
    if key == "robot_pose":
        pose = ROBOT_POSES.get(value, value) if isinstance(value, str) else value
        return tuple(round(float(q), 6) for q in pose)
    return value


def _shown(word: str, limit: int = 32) -> str:
    """A word of the user's request as an error message quotes it: at most ``limit`` characters."""
    return repr(word) if len(word) <= limit else repr(word[:limit]) + f"... ({len(word)} characters)"


def _set_once(out: dict, key: str, value: str) -> None:
    if key in out and out[key] != value:
        raise ValueError(f"text: names two values for {key}: {out[key]!r} and {value!r}")
    out[key] = value
