"""The proposal model's examples (issue 63, point 3): the labelled candidates of each layout's first
decision (``proposal_labels.py``), each seen as the model sees it (``policy/proposal_model.py``:
the oriented crops of both cameras and its features), with its label.

A candidate's label is its attempt's success; a push's or a pull's, where it was followed up, is
whether any grasp after it lifted the target (what the best next decision could make of it).

The crops are made from the decision point's frames, rendered again from the settled state (the
renderer is deterministic) through the simulator's masks (``oracle``) or a retrieval head's
prediction: a model trained or scored through a head ranks the same labelled candidates, its mask
channel and the view its features read from the head, so that its offline figure is still a lookup.
Cached per (scene, candidates, sight) under ``folder`` as .npz.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.physics import ControlPhysics, physics_named
from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.experiment.closed_loop import Workers, episode_env, loaded_perception
from scenegen.experiment.proposal_labels import DEFAULT_LABELS, LabelConfig, candidate_labels
from scenegen.experiment.sequences import ObservationStore, PathStore
from scenegen.manipulation.proposals import Candidate
from scenegen.policy.proposal_model import (
    CHANNELS,
    CROP,
    FEATURES,
    MODEL_VERSION,
    candidate_crop,
    candidate_features,
)
from scenegen.store.batch import atomic_write


def candidate_label(record: dict) -> bool:
    """A labelled candidate's training target (module docstring)."""
    if record["after"]:
        return bool(record["success"] or any(record["after"]))
    return bool(record["success"])


def seen_frames(env, perception) -> tuple[dict, dict, object]:
    """(frames per camera: image, depth, the target's mask; the cameras; the view) of ``env`` now,
    through ``perception`` (None: the simulator's masks)."""
    from scenegen.perception.observation import observe

    obs, view = observe(env, perception)
    frames = {}
    for name in env.cameras:
        if perception is None:
            mask = np.squeeze(obs[f"{name}_segmentation"]) == env.scene.target_id
        else:
            mask = np.squeeze(obs[f"{name}_predicted_target"]).astype(bool)
        frames[name] = (obs[f"{name}_image"], obs[f"{name}_depth"], mask)
    return frames, {c.name: c for c in env.scene.cameras}, view


def crops_of(scene: EnvScene, candidates: Sequence[dict], retrieval: Path | None, physics: ControlPhysics):
    """(crops (N, CHANNELS, CROP, CROP), features (N, FEATURES)) of ``candidates`` at ``scene``'s
    settled state seen through ``retrieval`` (None: the oracle); zeros where the target is not seen."""
    env = episode_env(scene, physics)
    env.reset_to(scene)
    frames, cameras, view = seen_frames(env, loaded_perception(retrieval))
    crops = np.zeros((len(candidates), CHANNELS, CROP, CROP), np.float32)
    features = np.zeros((len(candidates), FEATURES), np.float32)
    if view is not None:
        for i, c in enumerate(candidates):
            candidate = Candidate.from_dict(c)
            crops[i] = candidate_crop(frames, cameras, candidate)
            features[i] = candidate_features(candidate, view)
    return crops, features


def _job(job: tuple) -> tuple:
    kind, scene, (key, candidates, retrieval), physics = job
    began = time.process_time()
    crops, features = crops_of(scene, candidates, retrieval, physics)
    return kind, (key, crops, features), time.process_time() - began


@dataclass
class Examples:
    crops: np.ndarray  # (N, CHANNELS, CROP, CROP) float32
    features: np.ndarray  # (N, FEATURES) float32
    labels: np.ndarray  # (N,) float32 0/1
    scene: list[str]  # scene sha256 per example
    candidates: list[dict]

    def __len__(self) -> int:
        return len(self.labels)


def _cache_key(sha: str, candidates: Sequence[dict], sight: str) -> str:
    keys = {"scene": sha, "candidates": candidates, "sight": sight, "crop": CROP, "model": MODEL_VERSION}
    text = json.dumps(keys, sort_keys=True)  # the cache holds the features too: a new model version, anew
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def examples(
    scenes: Sequence[EnvScene],
    store: PathStore,
    views: ObservationStore,
    folder: Path,
    config: LabelConfig = DEFAULT_LABELS,
    retrieval: Path | None = None,
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
) -> Examples:
    """Every labelled first-decision candidate of ``scenes`` as an example, in scene order; crops
    cached under ``folder``."""
    from scenegen.experiment.sequences import NOMINAL, sight

    physics = physics_named(config.physics)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    seen = sight(retrieval, NOMINAL)
    records: dict[str, list[dict]] = {}
    for r in candidate_labels(scenes, store, views, config):
        records.setdefault(r["scene_sha256"], []).append(r)
    by_sha = {scene_sha256(s): s for s in scenes}
    order = [sha for sha in by_sha if sha in records]
    keys = {sha: _cache_key(sha, [r["candidate"] for r in records[sha]], seen) for sha in order}
    wanted = [
        ("crops", by_sha[sha], (keys[sha], [r["candidate"] for r in records[sha]], retrieval))
        for sha in order
        if not (folder / f"{keys[sha]}.npz").exists()
    ]
    with Workers(workers, physics) as pool:
        for _, (key, crops, features), _ in pool.map(wanted, run=_job):
            buffer = io.BytesIO()
            np.savez_compressed(buffer, crops=crops.astype(np.float16), features=features)
            atomic_write(folder / f"{key}.npz", buffer.getvalue())
            progress and progress("crops")
    crops, features, labels, scene, candidates = [], [], [], [], []
    for sha in order:
        with np.load(folder / f"{keys[sha]}.npz", allow_pickle=False) as data:
            crops.append(data["crops"].astype(np.float32))
            features.append(data["features"])
        labels += [float(candidate_label(r)) for r in records[sha]]
        scene += [sha] * len(records[sha])
        candidates += [r["candidate"] for r in records[sha]]
    if not order:
        empty = np.zeros((0, CHANNELS, CROP, CROP), np.float32)
        return Examples(empty, np.zeros((0, FEATURES), np.float32), np.zeros(0, np.float32), [], [])
    return Examples(
        np.concatenate(crops), np.concatenate(features), np.asarray(labels, np.float32), scene, candidates
    )
