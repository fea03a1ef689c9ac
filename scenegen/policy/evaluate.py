"""Closed-loop evaluation of a policy: observe, choose a primitive, execute it, re-observe, up to
``ATTEMPTS`` attempts per scene; one episode record per scene, with its trace and failure label.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import torch

from scenegen.env.episodes import EpisodeRecorder, write_episode
from scenegen.env.physics import DEFAULT_PHYSICS
from scenegen.env.scenes import EnvScene
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.rollout import run_primitive
from scenegen.manipulation.task import TIME_LIMIT, feasible
from scenegen.policy.failures import failure_labels
from scenegen.policy.labels import CAMERA_SIZE, scene_sha256, target_category
from scenegen.policy.network import PrimitivePolicy
from scenegen.policy.train import CAMERA, policy_input

ATTEMPTS = 3
ORACLE = "oracle"  # the retrieval setting that reads the simulator's instance masks (each panel's ceiling)


def run_episode(
    env,
    policy: PrimitivePolicy,
    scene: EnvScene,
    episode_id: str,
    expert=(),
    coverage=None,
    perception=None,
):
    """One closed-loop episode on ``scene``; returns the finished Episode (failure labels in info).

    ``perception``: the learned target finder (a :class:`~scenegen.perception.retrieval.perceive.
    RetrievalPerception`) every decision and re-observation goes through, or None for the oracle
    (the simulator's instance masks). With one, each decision's prediction is scored against the
    true segmentation afterwards (``info["perception"]``: per decision, per camera IoU, hit, wrong
    object, miss): scoring is the only reader of the segmentation."""
    from scenegen.perception.observation import observe

    env.reset_to(scene)
    recorder = EpisodeRecorder(env, episode_id, observation_kind="rgbd")
    recorder.episode.scene |= {
        "tags": [t for t, held in scene.tags.items() if held and t != "nominal"],
        "target_category": target_category(scene),
    }
    tried: set[str] = set()
    touched_other: list[bool] = []
    scores: list[dict] = []
    success = False
    start = float(env.sim.data._data.time)
    episode_clock = (start, float(env.target_pose()[0][2]))
    for _ in range(min(ATTEMPTS, len(policy.primitives))):  # each primitive at most once
        if float(env.sim.data._data.time) - start >= TIME_LIMIT:  # the task's time limit: no new attempt
            break
        observed = observe(env, perception)
        if perception is not None:
            from scenegen.perception.retrieval.evaluate import score_observation

            scores.append(score_observation(env, observed[0]))
        x = policy_input(observed[0], scene.target_id if perception is None else None)
        choice = policy.choose(torch.from_numpy(x), exclude=tried)
        tried.add(choice)
        outcome, _ = run_primitive(
            env, choice, recorder, episode=episode_clock, perception=perception, observed=observed
        )
        touched_other.append(outcome.other_touched)
        if outcome.success:
            success = True
            break
    info = {"touched_other": touched_other, "perception_kind": "oracle" if perception is None else "learned"}
    if perception is not None:
        from scenegen.perception.retrieval.evaluate import PERCEPTION_RULES

        info["perception"] = scores
        info["perception_rules"] = PERCEPTION_RULES  # how failures.py reads the scores
    episode = recorder.finish(success, **info)
    episode.info |= failure_labels(episode, scene.target_id, expert, coverage)
    episode.info["attempts"] = len(tried)
    return episode


def evaluate(
    checkpoint: Path,
    scenes: Sequence[EnvScene],
    out: Path,
    labels: Path | None = None,
    progress: bool = False,
    retrieval: Path | str | None = None,
    physics: str = DEFAULT_PHYSICS,
) -> dict:
    """Run the policy on every feasible scene; write episodes under ``out`` and ``summary.json``.
    ``retrieval``: the retrieval head's checkpoint folder the policy sees through, or ``"oracle"`` /
    None for the simulator's instance masks; ``physics``: what the episodes are simulated under (a
    name of ``env.physics.PHYSICS``)."""
    from tqdm import tqdm

    from scenegen.env.robosuite_env import SceneEnv

    perception = None
    head_sha256 = None
    if retrieval is not None and str(retrieval) != ORACLE:
        from scenegen.core.files import folder_sha256
        from scenegen.perception.retrieval.perceive import RetrievalPerception

        perception = RetrievalPerception.load(retrieval)
        head_sha256 = folder_sha256(Path(retrieval))  # the head as loaded: its whole folder
    policy = PrimitivePolicy.load(checkpoint)
    unknown = sorted(set(policy.primitives) - set(PRIMITIVES))
    if unknown:
        raise ValueError(f"{checkpoint}: chooses primitives this code lacks ({', '.join(unknown)}): retrain")
    coverage = {(tag, category): n for tag, category, n in policy.trained_on.get("coverage", [])} or None
    expert: dict[str, list[dict]] = {}
    if labels is not None:
        import pyarrow.parquet as pq

        for row in pq.read_table(labels).to_pylist():
            expert.setdefault(row["scene_sha256"], []).append(row)
    scenes = [s for s in scenes if feasible(s)]
    if not scenes:
        raise ValueError("no feasible scene to evaluate (targets on the floor are out of reach)")
    out = Path(out)
    env = SceneEnv(
        scenes[0],
        cameras=[CAMERA, "side"],
        camera_size=CAMERA_SIZE,
        render_each_step=False,
        horizon=6000,
        physics=physics,
    )
    results, first_hits, first_overlaps = [], [], []
    try:
        for i, scene in enumerate(tqdm(scenes, desc="episodes", disable=not progress)):
            episode = run_episode(
                env,
                policy,
                scene,
                f"{i:04d}_{scene.scene_id}",
                expert.get(scene_sha256(scene), ()),
                coverage,
                perception,
            )
            write_episode(out / episode.episode_id, episode)
            results.append((episode.success, episode.info["failure"], episode.info["out_of_time"]))
            first_hits.extend(score["hit"] for score in episode.info.get("perception", [])[:1])
            first_overlaps.extend(score["hit_iou"] for score in episode.info.get("perception", [])[:1])
    finally:
        env.close()
    summary = {
        "checkpoint": str(checkpoint),
        "perception": ORACLE if perception is None else str(retrieval),
        "episodes": len(results),
        "success_rate": round(sum(s for s, _, _ in results) / len(results), 4),
        "failures": dict(Counter(f for s, f, _ in results if not s)),
        "out_of_time": sum(late for s, _, late in results if not s),
        "physics": env.physics.key(),  # what the episodes were simulated under
    }
    if perception is not None:
        from scenegen.perception.retrieval.evaluate import PERCEPTION_RULES

        summary["perception_sha256"] = head_sha256
        summary["perception_rules"] = PERCEPTION_RULES
    if first_hits:
        summary["first_decision_target_hit"] = round(sum(first_hits) / len(first_hits), 4)
        summary["first_decision_overlap_hit"] = round(sum(first_overlaps) / len(first_overlaps), 4)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
