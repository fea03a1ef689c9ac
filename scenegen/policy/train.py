"""Training the baseline policy on labelled scene sources mixed by a recipe.

A labelled source is a pair (scenes, labels): a batch or reference table and the expert labels
``scenegen label`` wrote for it. Each labelled scene's decision-point observation (the front camera,
rendered once from its settled state) becomes one example whose targets are the success bits of every
primitive it was labelled with. Batches are drawn by a :class:`~scenegen.env.mixture.MixtureSampler`
(by default the seed's loss over the sources: reference and real sources in the real role, batches in
the synthetic one, weighted ``alpha``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from scenegen.core.files import sha256_file
from scenegen.env.mixture import MixtureRecipe, MixtureSampler
from scenegen.env.physics import DEFAULT_PHYSICS
from scenegen.env.scenes import EnvScene, load_scenes
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.policy.labels import CAMERA_SIZE, current, scene_sha256, target_category
from scenegen.policy.network import PrimitivePolicy, observation_tensor

CAMERA = "front"  # the policy looks through the front camera, at the labeller's CAMERA_SIZE


@dataclass
class Examples:
    """``x`` (N, 5, H, W) observations, ``y`` (N, P) success bits, ``known`` (N, P) which bits were
    labelled (by the primitive's current version); ``scenes`` the N scenes, ``primitives`` the P
    names."""

    x: np.ndarray
    y: np.ndarray
    known: np.ndarray
    scenes: list[EnvScene]
    primitives: list[str]
    stale: int = 0  # label rows left out: an older primitive version or the state ablation
    inputs: str = "rgbd"  # what x holds: camera crops, or the state ablation's features


def policy_input(obs: dict, target_id: int | None = None) -> np.ndarray:
    """The network input (5, H, W) from a camera observation dict (the front camera's frames): the
    target's mask is the retrieval head's prediction where the observation holds one
    (``front_predicted_target``), else the simulator's instance mask of ``target_id`` (oracle)."""
    predicted = obs.get(f"{CAMERA}_predicted_target")
    if predicted is not None:
        mask = np.squeeze(predicted).astype(bool)
    else:
        mask = np.squeeze(obs[f"{CAMERA}_segmentation"]) == target_id
    return observation_tensor(obs[f"{CAMERA}_image"], obs[f"{CAMERA}_depth"], mask)


def render_observation(env, scene: EnvScene) -> np.ndarray:
    """The network input of ``scene`` at its settled state."""
    env.reset_to(scene)
    return policy_input(env.camera_observations(), scene.target_id)


def labelled_examples(
    sources: Sequence[tuple[Path, Path]],
    split: str | None = "train",
    env=None,
    progress: bool = False,
    physics: str = DEFAULT_PHYSICS,
) -> Examples:
    """Examples of every labelled scene of every (scenes, labels) pair, from the label rows simulated
    under ``physics``."""
    import pyarrow.parquet as pq

    from scenegen.env.robosuite_env import SceneEnv

    primitives = list(PRIMITIVES)
    by_sha: dict[str, EnvScene] = {}
    bits: dict[str, dict[str, bool]] = {}
    stale = 0
    for scenes_path, labels_path in sources:
        for scene in load_scenes(scenes_path, split):
            by_sha.setdefault(scene_sha256(scene), scene)
        for row in pq.read_table(labels_path).to_pylist():
            if not current(row, physics=physics):
                stale += 1
                continue
            bits.setdefault(row["scene_sha256"], {})[row["primitive"]] = bool(row["success"])
    shas = [sha for sha in by_sha if sha in bits]
    if not shas:
        why = (
            f" ({stale} rows of older primitive versions, another observation or physics, or an unjudged "
            f"time: relabel, or name their --physics)"
            if stale
            else ""
        )
        raise ValueError(f"no labelled scene: the labels name none of the given scenes (same split?){why}")
    own = env is None
    env = env or SceneEnv(by_sha[shas[0]], cameras=[CAMERA], camera_size=CAMERA_SIZE, render_each_step=False)
    try:
        frames = tqdm(shas, desc="observations", disable=not progress)
        x = np.stack([render_observation(env, by_sha[sha]) for sha in frames])
    finally:
        if own:
            env.close()
    y = np.array([[bits[sha].get(p, False) for p in primitives] for sha in shas], dtype=np.float32)
    known = np.array([[p in bits[sha] for p in primitives] for sha in shas])
    return Examples(x, y, known, [by_sha[sha] for sha in shas], primitives, stale)


def coverage(examples: Examples) -> dict[tuple[str, str], int]:
    """Labelled examples per (tag, target category) ('nominal' for a scene holding no rare tag): what
    the failure labeller's ``data_coverage`` rule compares against."""
    counts: dict[tuple[str, str], int] = {}
    for scene in examples.scenes:
        category = target_category(scene)
        for tag in [t for t, held in scene.tags.items() if held and t != "nominal"] or ["nominal"]:
            counts[(tag, category)] = counts.get((tag, category), 0) + 1
    return counts


def train_policy(
    examples: Examples,
    out: Path,
    steps: int = 500,
    batch_size: int = 32,
    alpha: float = 1.0,
    seed: int = 0,
    lr: float = 1e-3,
    recipe: MixtureRecipe | None = None,
    data: dict | None = None,
    progress: bool = False,
) -> dict:
    """Train a :class:`PrimitivePolicy` for ``steps`` batches drawn by the mixture; save it to ``out``
    (safetensors + config.json with the losses and the recipe's effective shares)."""
    torch.manual_seed(seed)
    if recipe is None:
        sizes: dict[str, dict[str, int]] = {"real": {}, "synthetic": {}}
        for scene in examples.scenes:
            role = "synthetic" if scene.origin == "synthetic" else "real"
            sizes[role][scene.source] = sizes[role].get(scene.source, 0) + 1
        if not sizes["real"]:  # only generated scenes: they are the whole loss
            sizes["real"], sizes["synthetic"], alpha = sizes["synthetic"], {}, 0.0
        recipe = MixtureRecipe.seed_loss(sizes["real"], sizes["synthetic"], alpha)
    sampler = MixtureSampler(recipe, examples.scenes, num_samples=steps * batch_size, seed=seed)
    order = np.fromiter(iter(sampler), dtype=np.int64).reshape(steps, batch_size)
    model = PrimitivePolicy(examples.primitives, inputs=examples.inputs)
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    x, y = torch.from_numpy(examples.x), torch.from_numpy(examples.y)
    known = torch.from_numpy(examples.known.astype(np.float32))
    losses, started = [], time.process_time()
    for batch in tqdm(order, desc="training", disable=not progress):
        index = torch.from_numpy(batch)
        logits = model(x[index])
        per_bit = torch.nn.functional.binary_cross_entropy_with_logits(logits, y[index], reduction="none")
        loss = (per_bit * known[index]).sum() / known[index].sum().clamp(min=1)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(round(loss.item(), 6))
    summary = {
        "steps": steps,
        "batch_size": batch_size,
        "seed": seed,
        "examples": len(examples.scenes),
        "stale_label_rows": examples.stale,
        "coverage": sorted([tag, category, n] for (tag, category), n in coverage(examples).items()),
        "effective_shares": sampler.effective_shares(),
        "losses": losses,
        "cpu_seconds": round(time.process_time() - started, 2),
        "data": data or {},
    }
    model.eval().save(out, {"training": summary})
    return summary


def data_description(sources: Sequence[tuple[Path, Path]]) -> dict:
    """The labelled sources as the checkpoint records them (paths and the labels' sha256)."""
    return {
        "sources": [
            {"scenes": str(s), "labels": str(lab), "labels_sha256": sha256_file(lab)} for s, lab in sources
        ]
    }
