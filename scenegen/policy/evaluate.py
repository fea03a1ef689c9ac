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
from scenegen.env.scenes import EnvScene
from scenegen.policy.failures import failure_label
from scenegen.policy.labels import CAMERA_SIZE, scene_sha256, target_category
from scenegen.policy.network import PrimitivePolicy
from scenegen.policy.primitives import PRIMITIVES
from scenegen.policy.rollout import run_primitive
from scenegen.policy.task import TIME_LIMIT, feasible
from scenegen.policy.train import CAMERA, policy_input

ATTEMPTS = 3


def run_episode(env, policy: PrimitivePolicy, scene: EnvScene, episode_id: str, expert=(), coverage=None):
    """One closed-loop episode on ``scene``; returns the finished Episode (failure label in info)."""
    env.reset_to(scene)
    recorder = EpisodeRecorder(env, episode_id, observation_kind="rgbd")
    recorder.episode.scene |= {
        "tags": [t for t, held in scene.tags.items() if held and t != "nominal"],
        "target_category": target_category(scene),
    }
    tried: set[str] = set()
    success = False
    start = float(env.sim.data._data.time)
    for _ in range(min(ATTEMPTS, len(policy.primitives))):  # each primitive at most once
        if float(env.sim.data._data.time) - start >= TIME_LIMIT:  # the task's time limit: no new attempt
            break
        obs = env.camera_observations()
        x = policy_input(obs, scene.target_id)
        choice = policy.choose(torch.from_numpy(x), exclude=tried)
        tried.add(choice)
        outcome, _ = run_primitive(env, choice, recorder)
        if outcome.success:
            success = True
            break
    episode = recorder.finish(success)
    episode.info["failure"] = failure_label(episode, scene.target_id, expert, coverage)
    episode.info["attempts"] = len(tried)
    return episode


def evaluate(
    checkpoint: Path,
    scenes: Sequence[EnvScene],
    out: Path,
    labels: Path | None = None,
    progress: bool = False,
) -> dict:
    """Run the policy on every feasible scene; write episodes under ``out`` and ``summary.json``."""
    from tqdm import tqdm

    from scenegen.env.robosuite_env import SceneEnv

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
        scenes[0], cameras=[CAMERA, "side"], camera_size=CAMERA_SIZE, render_each_step=False, horizon=6000
    )
    results = []
    try:
        for i, scene in enumerate(tqdm(scenes, desc="episodes", disable=not progress)):
            episode = run_episode(
                env,
                policy,
                scene,
                f"{i:04d}_{scene.scene_id}",
                expert.get(scene_sha256(scene), ()),
                coverage,
            )
            write_episode(out / episode.episode_id, episode)
            results.append((episode.success, episode.info["failure"]))
    finally:
        env.close()
    summary = {
        "checkpoint": str(checkpoint),
        "episodes": len(results),
        "success_rate": round(sum(s for s, _ in results) / len(results), 4),
        "failures": dict(Counter(f for s, f in results if not s)),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
