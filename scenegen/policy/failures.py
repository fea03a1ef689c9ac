"""Why a policy's episode failed: a rule-based labeller over the episode record and the expert labels.

The rules, tried in this order; the first that holds names the failure:

- ``perception``: at the first decision the target's instance mask is empty or tiny (fewer than
  ``MIN_MASK`` pixels over every camera), or the robot touched other objects but never the target;
- ``grasp_choice``: the expert labels say another primitive than the ones the policy chose succeeds
  on this scene;
- ``control``: the hand never touched the target and never came within ``REACH`` of it (a controller
  or joint-limit failure: the target was not reached);
- ``dynamics``: the hand touched the target, then it slipped (lifted ``SLIP_LIFT`` or more, not held)
  or was pushed off (dropped ``PUSHED_OFF`` below where it rested);
- ``data_coverage``: the scene's (tag, target category) has fewer than ``MIN_COVERAGE`` labelled
  examples in the policy's training sources;
- ``timing``: the episode ran into the time limit;
- else ``unknown``. A successful episode has no failure label ('').
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from scenegen.env.episodes import Episode
from scenegen.policy.task import TIME_LIMIT

MIN_MASK = 20  # pixels of the target over all cameras at the first decision
REACH = 0.05  # m: closest approach of the grip site to the target that counts as reaching it
SLIP_LIFT = 0.01  # m
PUSHED_OFF = 0.03  # m
MIN_COVERAGE = 5  # labelled examples of the scene's (tag, category) in the training sources
LABELS = ("perception", "grasp_choice", "control", "dynamics", "data_coverage", "timing", "unknown")


def _mask_pixels(episode: Episode, target_id: int) -> int:
    if not episode.decisions:
        return 0
    first = episode.decisions[0].observation
    return int(sum(np.count_nonzero(v == target_id) for k, v in first.items() if k.endswith("_segmentation")))


def episode_features(episode: Episode, target_id: int) -> dict:
    """What the rules read from an episode record, as plain numbers (a cache can keep them)."""
    trace = {k: np.asarray(v) for k, v in episode.trace.items()}
    lift = trace["target_pos"][:, 2] - trace["target_pos"][0, 2]
    return {
        "mask_pixels": _mask_pixels(episode, target_id),
        "touched_target": bool(trace["robot_target_contacts"].max(initial=0) > 0),
        "touched_other": bool(episode.info.get("robot_touched_other", False)),
        "lift_max": float(lift.max(initial=0)),
        "lift_min": float(lift.min(initial=0)),
        "closest": float(np.linalg.norm(trace["eef_pos"] - trace["target_pos"], axis=1).min(initial=np.inf)),
        "duration": float(trace["time"][-1] - trace["time"][0]),
    }


def failure_label(
    episode: Episode,
    target_id: int,
    expert: Sequence[dict] = (),
    coverage: Mapping[tuple[str, str], int] | None = None,
) -> str:
    """The failure label of ``episode`` ('' when it succeeded).

    ``expert``: the scene's expert label rows (``primitive``, ``success``); ``coverage``: labelled
    training examples per (tag, target category); the scene's tags and category come from
    ``episode.scene`` (``tags``, ``target_category``)."""
    if episode.success:
        return ""
    return label_from_features(
        episode_features(episode, target_id),
        {d.choice.get("primitive") for d in episode.decisions},
        expert,
        episode.scene.get("tags") or ["nominal"],
        episode.scene.get("target_category"),
        coverage,
    )


def label_from_features(
    features: Mapping,
    chosen: set[str],
    expert: Sequence[dict],
    tags: Sequence[str],
    category: str | None,
    coverage: Mapping[tuple[str, str], int] | None = None,
) -> str:
    """The failure label of a failed episode from its :func:`episode_features`, the primitives it
    chose, the scene's expert rows, its rare tags (``['nominal']`` for none) and target category."""
    if features["mask_pixels"] < MIN_MASK or (features["touched_other"] and not features["touched_target"]):
        return "perception"
    if any(row["success"] and row["primitive"] not in chosen for row in expert):
        return "grasp_choice"
    if not features["touched_target"] and features["closest"] > REACH:
        return "control"
    moved = features["lift_max"] >= SLIP_LIFT or features["lift_min"] <= -PUSHED_OFF
    if features["touched_target"] and moved:
        return "dynamics"
    if coverage is not None and min(coverage.get((tag, category), 0) for tag in tags) < MIN_COVERAGE:
        return "data_coverage"
    if features["duration"] >= TIME_LIMIT:
        return "timing"
    return "unknown"
