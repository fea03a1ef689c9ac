"""Why a policy's episode failed: a rule-based labeller over the episode record and the expert labels.

Every attempt (one decision and the primitive it chose) gets its own cause, from the features of its
own part of the trace; the episode's ``failure`` is its first attempt's cause (what went wrong
first). Running out of time is not a cause but a flag beside it (``out_of_time``: the episode ran
into the task's time limit): version 1 of the transfer experiment tried a ``timing`` rule after the
others over the whole episode's trace, so its table was an artefact of the rules' order.

The rules, tried in this order on one attempt; the first that holds names its cause:

- ``perception``: at the attempt's decision the target's mask is empty or tiny (fewer than
  ``MIN_MASK`` pixels over every camera: the simulator's in the oracle setting, the retrieval head's
  prediction otherwise), or the predicted mask misses the target by the perception rules' version
  the episode records (``episode.info["perception_rules"]``; 1 where none is recorded: the centre
  rule, no centre on the target or mostly another object; 2: the overlap rule, IoU < 0.5 in a
  camera that sees the target, or a prediction in one that does not; scored against the
  segmentation: ``episode.info["perception"]``), or the robot touched other
  objects but never the target;
- ``grasp_choice`` (first attempt only: the expert labels are measured from the settled state): the
  expert labels say another primitive than the one chosen succeeds on this scene;
- ``control``: the hand never touched the target and never came within ``REACH`` of it (a controller
  or joint-limit failure: the target was not reached);
- ``dynamics``: the hand touched the target, then it slipped (lifted ``SLIP_LIFT`` or more, not held)
  or was pushed off (dropped ``PUSHED_OFF`` below where it rested);
- ``data_coverage``: the scene's (tag, target category) has fewer than ``MIN_COVERAGE`` labelled
  examples in the policy's training sources;
- else ``unknown``. A successful episode has no failure label ('').
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from scenegen.env.episodes import Episode
from scenegen.manipulation.task import TIME_LIMIT

MIN_MASK = 20  # pixels of the target over all cameras at the attempt's decision
REACH = 0.05  # m: closest approach of the grip site to the target that counts as reaching it
SLIP_LIFT = 0.01  # m
PUSHED_OFF = 0.03  # m
MIN_COVERAGE = 5  # labelled examples of the scene's (tag, category) in the training sources
LABELS = ("perception", "grasp_choice", "control", "dynamics", "data_coverage", "unknown")


def _mask_pixels(observation: Mapping, target_id: int) -> int:
    """Pixels of the target's mask the decision used: the predicted one where the observation holds
    a prediction, else the simulator's instance mask."""
    predicted = [v for k, v in observation.items() if k.endswith("_predicted_target")]
    if predicted:
        return int(sum(np.count_nonzero(v) for v in predicted))
    return int(
        sum(np.count_nonzero(v == target_id) for k, v in observation.items() if k.endswith("_segmentation"))
    )


def attempt_features(
    episode: Episode, target_id: int, attempt: int = -1, touched_other: bool = False
) -> dict:
    """What the rules read of one attempt (``attempt``: the index of its decision, default the
    last), from the trace rows between its decision and the next one (or the end), as plain numbers
    (a cache can keep them). Heights are relative to the target's height when the attempt began;
    ``duration`` is the episode's time at the attempt's end. ``touched_other``: the robot touched
    another object during the attempt (the task monitor measures it)."""
    trace = {k: np.asarray(v) for k, v in episode.trace.items()}
    decisions = episode.decisions
    attempt = attempt % len(decisions) if decisions else 0
    every = episode.trace_every  # trace row i holds step i * every (and the last row the end)
    first = decisions[attempt].step // every if decisions else 0  # at or just before the decision
    last = len(trace["time"])
    if decisions and attempt + 1 < len(decisions):
        last = decisions[attempt + 1].step // every + 1  # up to the next decision
    rows = slice(first, max(last, first + 1))
    height = trace["target_pos"][rows, 2]
    moved = height - height[0]  # relative to where the target was when the attempt began
    scores = episode.info.get("perception") or []
    score = scores[attempt] if decisions and attempt < len(scores) else None
    return {
        "mask_pixels": _mask_pixels(decisions[attempt].observation, target_id) if decisions else 0,
        "mask_missed": None if score is None else _missed(score, episode.info.get("perception_rules", 1)),
        "touched_target": bool(trace["robot_target_contacts"][rows].max(initial=0) > 0),
        "touched_other": bool(touched_other),
        "lift_max": float(moved.max(initial=0)),
        "lift_min": float(moved.min(initial=0)),
        "closest": float(
            np.linalg.norm(trace["eef_pos"][rows] - trace["target_pos"][rows], axis=1).min(initial=np.inf)
        ),
        "duration": float(trace["time"][rows][-1] - trace["time"][0]),
    }


def _missed(score: dict, rules: int) -> bool:
    from scenegen.perception.retrieval.evaluate import perception_missed

    return perception_missed(score, rules)


def attempt_cause(
    features: Mapping,
    primitive: str,
    expert: Sequence[dict],
    tags: Sequence[str],
    category: str | None,
    coverage: Mapping[tuple[str, str], int] | None = None,
    first: bool = True,
) -> str:
    """The cause of one failed attempt from its :func:`attempt_features`, the primitive it ran, the
    scene's expert rows (read on the ``first`` attempt only), its rare tags (``['nominal']`` for
    none) and target category."""
    missed = features.get("mask_missed") or features["mask_pixels"] < MIN_MASK
    if missed or (features["touched_other"] and not features["touched_target"]):
        return "perception"
    if first and any(row["success"] and row["primitive"] != primitive for row in expert):
        return "grasp_choice"
    if not features["touched_target"] and features["closest"] > REACH:
        return "control"
    moved = features["lift_max"] >= SLIP_LIFT or features["lift_min"] <= -PUSHED_OFF
    if features["touched_target"] and moved:
        return "dynamics"
    if coverage is not None and min(coverage.get((tag, category), 0) for tag in tags) < MIN_COVERAGE:
        return "data_coverage"
    return "unknown"


def out_of_time(duration: float) -> bool:
    """Whether an episode that lasted ``duration`` simulated seconds ran into the time limit."""
    return duration >= TIME_LIMIT


def failure_labels(
    episode: Episode,
    target_id: int,
    expert: Sequence[dict] = (),
    coverage: Mapping[tuple[str, str], int] | None = None,
) -> dict:
    """``{"failure": the first attempt's cause, "attempt_failures": [a cause per attempt],
    "out_of_time": bool}`` of ``episode`` (failure '' and no causes when it succeeded).

    ``expert``: the scene's expert label rows (``primitive``, ``success``); ``coverage``: labelled
    training examples per (tag, target category); the scene's tags and category come from
    ``episode.scene`` (``tags``, ``target_category``); ``episode.info["touched_other"]``, if present,
    a flag per attempt."""
    duration = float(episode.trace["time"][-1] - episode.trace["time"][0]) if episode.trace["time"] else 0.0
    if episode.success:
        return {"failure": "", "attempt_failures": [], "out_of_time": False}
    touched = list(episode.info.get("touched_other", []))
    causes = [
        attempt_cause(
            attempt_features(episode, target_id, k, touched[k] if k < len(touched) else False),
            decision.choice.get("primitive", ""),
            expert,
            episode.scene.get("tags") or ["nominal"],
            episode.scene.get("target_category"),
            coverage,
            first=k == 0,
        )
        for k, decision in enumerate(episode.decisions)
    ] or ["perception"]  # no decision at all: nothing was seen to act on
    return {"failure": causes[0], "attempt_failures": causes, "out_of_time": out_of_time(duration)}


def failure_label(
    episode: Episode,
    target_id: int,
    expert: Sequence[dict] = (),
    coverage: Mapping[tuple[str, str], int] | None = None,
) -> str:
    """The failure label of ``episode``: its first attempt's cause ('' when it succeeded)."""
    return failure_labels(episode, target_id, expert, coverage)["failure"]
