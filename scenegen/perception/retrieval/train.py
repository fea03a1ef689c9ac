"""Training the retrieval head on scene sources mixed by a recipe (``scenegen retrieval train``).

An example is one scene's decision-point frames (front and side, cached renders: frames.py); its
labels are the segmentation's instances mapped to their categories (every object's pixels, not only
the target's: in simulation they are free, in the world each labelled scene is an annotated one).
Batches of scenes are drawn by a :class:`~scenegen.env.mixture.MixtureSampler` (by default the seed's
loss over the sources: reference and real sources in the real role, generated batches in the
synthetic one, weighted ``alpha``), as ``policy train`` draws them. Augmentation (brightness, a
horizontal flip) comes from ``SeedSequence([seed, step])``, so a run is a function of its seed and
a resumed run equals an uninterrupted one: the state (weights, optimiser, losses) is saved every
``SAVE_EVERY`` steps under ``<out>/_resume`` and removed when the checkpoint is written.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from scenegen.env.mixture import MixtureRecipe, MixtureSampler
from scenegen.env.scenes import EnvScene
from scenegen.perception.retrieval.frames import Frames
from scenegen.perception.retrieval.model import DEPTH_SCALE, RetrievalHead

SAVE_EVERY = 100  # steps between resume states
OBJECT_WEIGHT = 5.0  # cross-entropy weight of an object pixel against a background one (objects are small)
BRIGHTNESS = (0.35, 1.25)  # range of the colour scale drawn per image (dim scenes are a rare case)


@dataclass
class RetrievalData:
    """``rgb`` (N, K, H, W, 3) uint8, ``depth`` (N, K, H, W) float16 metres, ``labels`` (N, K, H/2,
    W/2) uint8 (0 background, 1 + i category i) for N scenes of K cameras; ``categories``; ``seg``
    the frames' instance ids."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    scenes: list[EnvScene]
    categories: list[str]
    seg: np.ndarray  # (N, K, H, W) int16 instance ids: the fine stage's true regions


def category_map(scene: EnvScene, seg: np.ndarray, categories: Sequence[str]) -> np.ndarray:
    """(H, W) uint8: 0 where no object is, 1 + the category's index where one is."""
    lookup = np.zeros(max(scene.segmentation.values()) + 1, np.uint8)
    for obj in scene.objects:
        if obj.category in categories:
            lookup[scene.segmentation[obj.name]] = 1 + list(categories).index(obj.category)
    seg = np.clip(seg, 0, len(lookup) - 1)
    return lookup[seg]


def half(labels: np.ndarray) -> np.ndarray:
    """(..., H, W) -> (..., H/2, W/2): a cell takes the largest class of its 2 x 2 block, so a thin
    object's pixels survive the halving."""
    *lead, h, w = labels.shape
    return labels.reshape(*lead, h // 2, 2, w // 2, 2).max(axis=(-3, -1))


def retrieval_data(
    scenes: Sequence[EnvScene], frames: Iterable[Frames], categories: Sequence[str]
) -> RetrievalData:
    """The training arrays of ``scenes`` from their ``frames`` (in the same order)."""
    rgb, depth, labels, seg = [], [], [], []
    for scene, f in zip(scenes, frames, strict=True):
        rgb.append(f.rgb)
        depth.append(f.depth.astype(np.float16))
        labels.append(half(category_map(scene, f.seg, categories)))
        seg.append(f.seg.astype(np.int16))
    return RetrievalData(
        np.stack(rgb), np.stack(depth), np.stack(labels), list(scenes), list(categories), np.stack(seg)
    )


def batch_tensors(data: RetrievalData, scenes: np.ndarray, rng: np.random.Generator | None = None):
    """(B*K, 4, H, W) inputs and (B*K, H/2, W/2) labels of the scenes ``scenes`` (all cameras).
    With ``rng``, the training view: a ``CROP`` window around a random object pixel (the network is
    fully convolutional, so it sees whole frames at test time; crops cost a third of a frame),
    brightness scaled, half of them flipped left to right."""
    rgb = data.rgb[scenes].reshape(-1, *data.rgb.shape[2:])
    depth = data.depth[scenes].reshape(-1, *data.depth.shape[2:])
    labels = data.labels[scenes].reshape(-1, *data.labels.shape[2:])
    if rng is not None:
        rgb, depth, labels = _crops(rgb, depth, labels, rng)
    rgb = rgb.astype(np.float32) / 255.0
    depth = depth.astype(np.float32) / DEPTH_SCALE
    labels = labels.astype(np.int64)
    if rng is not None:
        rgb = np.clip(rgb * rng.uniform(*BRIGHTNESS, size=(len(rgb), 1, 1, 1)).astype(np.float32), 0.0, 1.0)
        flip = rng.random(len(rgb)) < 0.5
        rgb[flip], depth[flip], labels[flip] = rgb[flip, :, ::-1], depth[flip, :, ::-1], labels[flip, :, ::-1]
    x = np.concatenate([rgb.transpose(0, 3, 1, 2), depth[:, None]], axis=1)
    return torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(labels))


CROP = (128, 192)  # (H, W) px of a training view, even so that it halves onto the label grid


def _crops(rgb, depth, labels, rng):
    height, width = rgb.shape[1:3]
    ch, cw = CROP
    out_rgb, out_depth, out_labels = [], [], []
    for i in range(len(rgb)):
        rows, cols = np.nonzero(labels[i])
        if len(rows):
            k = rng.integers(len(rows))
            cy, cx = (
                2 * rows[k] + rng.integers(-ch // 3, ch // 3),
                2 * cols[k] + rng.integers(-cw // 3, cw // 3),
            )
        else:
            cy, cx = rng.integers(height), rng.integers(width)
        top = int(np.clip(cy - ch // 2, 0, height - ch)) // 2 * 2
        left = int(np.clip(cx - cw // 2, 0, width - cw)) // 2 * 2
        out_rgb.append(rgb[i, top : top + ch, left : left + cw])
        out_depth.append(depth[i, top : top + ch, left : left + cw])
        out_labels.append(labels[i, top // 2 : (top + ch) // 2, left // 2 : (left + cw) // 2])
    return np.stack(out_rgb), np.stack(out_depth), np.stack(out_labels)


def class_weights(labels: np.ndarray, categories: int) -> np.ndarray:
    """Cross-entropy weights (1 + C,): background 1; a category ``OBJECT_WEIGHT`` times the square
    root of (the median category's pixel count / its own), within [1, 4] times that: the rarer
    categories (a fork is a few pixels wide) are not drowned by the large ones."""
    counts = np.bincount(labels.ravel(), minlength=1 + categories)[1:].astype(np.float64)
    seen = counts[counts > 0]
    median = np.median(seen) if len(seen) else 1.0
    scale = np.clip(np.sqrt(median / np.maximum(counts, 1.0)), 1.0, 4.0)
    return np.concatenate([[1.0], OBJECT_WEIGHT * scale]).astype(np.float32)


def default_recipe(scenes: Sequence[EnvScene], alpha: float) -> MixtureRecipe:
    """The seed's loss over the scenes' sources: generated ones in the synthetic role, weighted alpha."""
    sizes: dict[str, dict[str, int]] = {"real": {}, "synthetic": {}}
    for scene in scenes:
        role = "synthetic" if scene.origin == "synthetic" else "real"
        sizes[role][scene.source] = sizes[role].get(scene.source, 0) + 1
    if not sizes["real"]:  # only generated scenes: they are the whole loss
        sizes["real"], sizes["synthetic"], alpha = sizes["synthetic"], {}, 0.0
    return MixtureRecipe.seed_loss(sizes["real"], sizes["synthetic"], alpha)


def _save_state(folder: Path, model, optimiser, step: int, losses: list[float], cpu: float, key: str) -> None:
    from safetensors.torch import save_file

    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_file(
        {k: v.cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp / "model.safetensors")
    )
    state = optimiser.state_dict()
    tensors = {f"{i}.{name}": value for i, s in state["state"].items() for name, value in s.items()}
    save_file({k: v.cpu().contiguous() for k, v in tensors.items()}, str(tmp / "optimiser.safetensors"))
    meta = {"step": step, "losses": losses, "cpu_seconds": cpu, "key": key, "groups": state["param_groups"]}
    (tmp / "state.json").write_text(json.dumps(meta) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)


def _load_state(folder: Path, model, optimiser, key: str) -> tuple[int, list[float], float]:
    """Restore a resume state made by the same training (``key``); (0, [], 0) when there is none."""
    from safetensors.torch import load_file

    try:
        meta = json.loads((folder / "state.json").read_text())
    except (OSError, ValueError):
        return 0, [], 0.0
    if meta.get("key") != key:
        return 0, [], 0.0
    model.load_state_dict(load_file(str(folder / "model.safetensors")))
    flat = load_file(str(folder / "optimiser.safetensors"))
    state: dict[int, dict] = {}
    for name, value in flat.items():
        index, field = name.split(".", 1)
        state.setdefault(int(index), {})[field] = value
    optimiser.load_state_dict({"state": state, "param_groups": meta["groups"]})
    return int(meta["step"]), list(meta["losses"]), float(meta["cpu_seconds"])


def train_head(
    data: RetrievalData,
    out: Path,
    steps: int = 1500,
    batch_size: int = 8,
    alpha: float = 1.0,
    seed: int = 0,
    lr: float = 3e-3,
    width: int = 8,
    recipe: MixtureRecipe | None = None,
    description: dict | None = None,
    progress: bool = False,
    stop_after: int | None = None,
    device: str = "cpu",
) -> dict | None:
    """Train a :class:`RetrievalHead` for ``steps`` batches of ``batch_size`` scenes (each with all
    its cameras) drawn by the mixture; save it to ``out`` (safetensors + config.json with the losses,
    the recipe's effective shares and the CPU seconds) and return the training summary. Resumes from
    ``<out>/_resume``. ``stop_after``: stop at that step, leaving the resume state and no checkpoint
    (a run split over several calls; returns None). ``device``: where the weights and batches live
    (scenegen/devices.py; batches are drawn on the CPU either way)."""
    from tqdm import tqdm

    from scenegen.devices import resolve_device

    on = resolve_device(device)

    out = Path(out)
    torch.manual_seed(seed)
    recipe = recipe or default_recipe(data.scenes, alpha)
    sampler = MixtureSampler(recipe, data.scenes, num_samples=steps * batch_size, seed=seed)
    order = np.fromiter(iter(sampler), dtype=np.int64).reshape(steps, batch_size)
    model = RetrievalHead(data.categories, width).to(on)
    optimiser = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    weight = torch.from_numpy(class_weights(data.labels, len(data.categories))).to(on)
    key = json.dumps([steps, batch_size, seed, lr, width, alpha, order[:4].tolist(), len(data.scenes)])
    resume = out / "_resume"
    start, losses, cpu = _load_state(resume, model, optimiser, key)
    model.train()
    clock = time.process_time()
    bar = tqdm(range(start, steps), initial=start, total=steps, desc="training", disable=not progress)
    for step in bar:
        for group in optimiser.param_groups:  # cosine decay, a function of the step: resumable
            group["lr"] = lr * 0.5 * (1 + math.cos(math.pi * step / steps))
        x, y = batch_tensors(data, order[step], np.random.default_rng([seed, step]))
        x, y = x.to(on), y.to(on)
        loss = F.cross_entropy(model(x), y, weight=weight)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(round(loss.item(), 6))
        if step + 1 < steps and ((step + 1) % SAVE_EVERY == 0 or step + 1 == stop_after):
            _save_state(resume, model, optimiser, step + 1, losses, cpu + time.process_time() - clock, key)
        if step + 1 == stop_after and step + 1 < steps:
            return None
    summary = {
        "steps": steps,
        "batch_size": batch_size,
        "seed": seed,
        "lr": lr,
        "scenes": len(data.scenes),
        "images": int(data.rgb.shape[0] * data.rgb.shape[1]),
        "effective_shares": sampler.effective_shares(),
        "losses": losses,
        "cpu_seconds": round(cpu + time.process_time() - clock, 1),
        "data": description or {},
    }
    model.cpu().eval().save(out, {"training": summary})
    shutil.rmtree(resume, ignore_errors=True)
    return summary
