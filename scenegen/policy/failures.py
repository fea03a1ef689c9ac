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
    trace = {k: np.asarray(v) for k, v in episode.trace.items()}
    touched_target = trace["robot_target_contacts"].max(initial=0) > 0
    touched_anything = episode.info.get("robot_touched_other", False)
    if _mask_pixels(episode, target_id) < MIN_MASK or (touched_anything and not touched_target):
        return "perception"
    chosen = {d.choice.get("primitive") for d in episode.decisions}
    if any(row["success"] and row["primitive"] not in chosen for row in expert):
        return "grasp_choice"
    lift = trace["target_pos"][:, 2] - trace["target_pos"][0, 2]
    closest = np.linalg.norm(trace["eef_pos"] - trace["target_pos"], axis=1).min(initial=np.inf)
    if not touched_target and closest > REACH:
        return "control"
    if touched_target and (lift.max(initial=0) >= SLIP_LIFT or lift.min(initial=0) <= -PUSHED_OFF):
        return "dynamics"
    if coverage is not None:
        tags = episode.scene.get("tags") or ["nominal"]
        category = episode.scene.get("target_category")
        if min(coverage.get((tag, category), 0) for tag in tags) < MIN_COVERAGE:
            return "data_coverage"
    if trace["time"][-1] - trace["time"][0] >= TIME_LIMIT:
        return "timing"
    return "unknown"
