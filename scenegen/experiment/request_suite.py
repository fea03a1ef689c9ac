"""Requests nobody tuned for (issue 46, point 1; ``benchmarks/request_suite.py``): "retrieve" requests
drawn at random from what the schema allows, not chosen.

A request is a target category, 2 or 3 required rare tags (never ``nominal``), sometimes one
forbidden tag, and a robot initial pose. Every required tag occurs for that category in the
reference set's training split (what the generator learned from); their combination need not:
composing what the data never shows together is the generator's job. The pose is ``home`` or
``ready`` (the only two the training layouts hold) with each joint moved by up to ``JITTER`` rad,
kept within the Panda's limits. Two halves, drawn with fixed seeds: ``tuning`` (seed 1), which may be
looked at and tuned on, and ``heldout`` (seed 2), run only to report.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from scenegen.schema.condition import PANDA_JOINT_LIMITS, RARE_TAGS, ROBOT_POSES, Condition

HALVES = {"tuning": 1, "heldout": 2}  # the seed of each half
JITTER = 0.1  # rad: the most each joint of the named pose is moved
FORBID_SHARE = 0.3  # the share of requests that also forbid one tag


@dataclass(frozen=True)
class Request:
    """One drawn request: ``target``, ``required`` and ``forbidden`` tags, the named pose it was
    jittered from and the joint angles (radians)."""

    target: str
    required: tuple[str, ...]
    forbidden: tuple[str, ...]
    pose_name: str
    robot_pose: tuple[float, ...]

    @property
    def text(self) -> str:
        """How a user would type it (the pose is given as joint angles, not by its name)."""
        words = ["retrieve the", self.target, *self.required, *(f"not {t}" for t in self.forbidden)]
        return " ".join(words)

    def condition(self) -> Condition:
        tags = dict.fromkeys(self.required, "required") | dict.fromkeys(self.forbidden, "forbidden")
        return Condition(task="retrieve", target=self.target, tags=tags, robot_pose=self.robot_pose)

    def as_dict(self) -> dict:
        return {
            "text": self.text,
            "target": self.target,
            "required": list(self.required),
            "forbidden": list(self.forbidden),
            "pose_name": self.pose_name,
            "robot_pose": list(self.robot_pose),
        }


def tags_by_category(rows: Sequence[dict]) -> dict[str, tuple[str, ...]]:
    """Per target category, the rare tags that occur for it in ``rows`` (reference rows)."""
    seen: Counter = Counter()
    for row in rows:
        for tag in RARE_TAGS:
            if row.get(f"tag_{tag}"):
                seen[(row["target_category"], tag)] += 1
    out: dict[str, list[str]] = {}
    for category, tag in sorted(seen):
        out.setdefault(category, []).append(tag)
    return {c: tuple(sorted(t, key=RARE_TAGS.index)) for c, t in out.items()}


def draw_requests(rows: Sequence[dict], count: int, seed: int) -> list[Request]:
    """``count`` requests drawn with ``seed`` (module docstring); categories with fewer than two
    rare tags in ``rows`` are never drawn."""
    rng = np.random.default_rng(seed)
    tags = {c: t for c, t in tags_by_category(rows).items() if len(t) >= 2}
    categories = sorted(tags)
    limits = np.array(PANDA_JOINT_LIMITS)
    out = []
    for _ in range(count):
        target = categories[rng.integers(len(categories))]
        own = tags[target]
        k = min(int(rng.integers(2, 4)), len(own))
        required = tuple(sorted(rng.choice(own, size=k, replace=False).tolist(), key=RARE_TAGS.index))
        forbidden: tuple[str, ...] = ()
        if rng.random() < FORBID_SHARE:
            others = [t for t in RARE_TAGS if t not in required]
            forbidden = (others[rng.integers(len(others))],)
        pose_name = sorted(ROBOT_POSES)[rng.integers(len(ROBOT_POSES))]
        pose = np.asarray(ROBOT_POSES[pose_name]) + rng.uniform(-JITTER, JITTER, size=7)
        pose = np.clip(pose, limits[:, 0], limits[:, 1])
        out.append(Request(target, required, forbidden, pose_name, tuple(round(float(q), 6) for q in pose)))
    return out


def suite(rows: Sequence[dict], half: str, count: int = 30) -> list[Request]:
    """One half of the suite: ``tuning`` or ``heldout`` (its fixed seed)."""
    if half not in HALVES:
        raise ValueError(f"half {half!r}: one of {', '.join(HALVES)}")
    return draw_requests(rows, count, HALVES[half])
