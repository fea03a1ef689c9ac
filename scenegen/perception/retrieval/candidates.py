"""Design (b) of the retrieval head, measured against the segmenter (model.py) before choosing
(docs/retrieval.md; benchmarks/retrieval_designs.py): object candidates from depth, and a small
learned classifier that picks the requested category among them.

Candidates, as unseen-object segmentation does it: the depth pixels whose world points lie above the
table (``ABOVE_TABLE``) within its edges, that are not the robot's own pixels, split into regions
where neighbouring depths jump by more than ``EDGE`` (connected components of what is left). Each
region of at least ``MIN_PIXELS`` is a candidate. The classifier sees a candidate's RGB-D crop (its
box with a margin, resized to ``CROP`` px) and its mask, and gives logits over "no object" (furniture,
a merged blob) and the categories; the target is the candidate with the highest probability of the
requested category above the threshold. Labels are the majority instance under each region.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from scenegen.perception.points import masked_points
from scenegen.perception.retrieval.perceive import Prediction

EDGE = 0.04  # m: a jump in depth between neighbouring pixels that separates two regions (measured: 1 cm cut
# the sides of objects seen at a grazing angle into pieces; docs/retrieval.md)
MIN_PIXELS = 20  # a smaller region is no candidate (as the planner's MIN_POINTS)
CROP = 32  # px: the classifier's input size
MARGIN = 0.2  # of the region's box, added around it for the crop
TABLE_TOP, TABLE_HALF, TABLE_MARGIN = 0.8, (0.4, 0.5), 0.05
ABOVE_TABLE = 0.0015  # m: a fork lies 3 mm high; simulated depth is exact (a real sensor needs more)


def candidate_regions(depth: np.ndarray, robot_mask: np.ndarray, camera) -> list[np.ndarray]:
    """(H, W) bool masks of the candidate regions of one frame (depth in metres, the robot's own
    pixels, the scene's :class:`~scenegen.schema.scene.Camera`)."""
    import cv2

    height, width = depth.shape
    everything = np.ones_like(depth, bool)
    points = masked_points(np.where(depth > 0, depth, 1.0), everything, camera).reshape(height, width, 3)
    keep = (
        (depth > 0)
        & ~robot_mask
        & (points[..., 2] > TABLE_TOP + ABOVE_TABLE)
        & (np.abs(points[..., 0]) <= TABLE_HALF[0] + TABLE_MARGIN)
        & (np.abs(points[..., 1]) <= TABLE_HALF[1] + TABLE_MARGIN)
    )
    edge = np.zeros_like(keep)
    edge[:, 1:] |= np.abs(np.diff(depth, axis=1)) > EDGE
    edge[1:, :] |= np.abs(np.diff(depth, axis=0)) > EDGE
    count, regions = cv2.connectedComponents((keep & ~edge).astype(np.uint8), connectivity=4)
    sizes = np.bincount(regions.ravel(), minlength=count)
    return [regions == k for k in range(1, count) if sizes[k] >= MIN_PIXELS]


def candidate_crop(rgb: np.ndarray, depth: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(5, CROP, CROP) float32: RGB in [0, 1], depth relative to the region's median (per 10 cm),
    the region's mask, over the region's box with a margin."""
    import cv2

    rows, cols = np.nonzero(region)
    top, bottom, left, right = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    dy, dx = int((bottom - top) * MARGIN) + 2, int((right - left) * MARGIN) + 2
    top, left = max(0, top - dy), max(0, left - dx)
    bottom, right = min(region.shape[0], bottom + dy), min(region.shape[1], right + dx)
    window = (slice(top, bottom), slice(left, right))
    median = float(np.median(depth[region]))
    channels = [
        *(rgb[window][..., c].astype(np.float32) / 255.0 for c in range(3)),
        np.clip((depth[window] - median) / 0.1, -1, 1).astype(np.float32),
        region[window].astype(np.float32),
    ]
    return np.stack([cv2.resize(c, (CROP, CROP), interpolation=cv2.INTER_AREA) for c in channels])


class CandidateClassifier(nn.Module):
    """Conv(5 -> w -> 2w -> 4w, stride 2) + global average pool + linear: (B, 5, CROP, CROP) ->
    (B, 1 + C) logits ("no object" and the categories)."""

    def __init__(self, categories: list[str], width: int = 16):
        super().__init__()
        self.categories, self.width = list(categories), width
        w = width
        self.features = nn.Sequential(
            nn.Conv2d(5, w, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(w, 2 * w, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(2 * w, 4 * w, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        self.head = nn.Linear(4 * w, 1 + len(self.categories))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


def frame_candidates(frames, scene) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(camera index, region mask, crop) of every candidate of a scene's frames (the robot's own
    pixels from the renderer's robot instance, as the environment's self-filter gives them)."""
    cameras = {c.name: c for c in scene.cameras}
    out = []
    for k, name in enumerate(frames.cameras):
        robot = frames.seg[k] == scene.segmentation["robot"]
        for region in candidate_regions(frames.depth[k], robot, cameras[name]):
            out.append((k, region, candidate_crop(frames.rgb[k], frames.depth[k], region)))
    return out


def region_label(region: np.ndarray, seg: np.ndarray, scene, categories: Sequence[str]) -> int:
    """0 ("no object") or 1 + the category index of the instance under most of the region."""
    ids, counts = np.unique(seg[region], return_counts=True)
    instance = int(ids[np.argmax(counts)])
    by_id = {scene.segmentation[o.name]: o.category for o in scene.objects}
    category = by_id.get(instance)
    return 0 if category is None or category not in categories else 1 + list(categories).index(category)


def train_classifier(
    scenes, frames, categories: Sequence[str], out: Path, epochs: int = 12, seed: int = 0, lr: float = 3e-3
) -> dict:
    """Train a :class:`CandidateClassifier` on every candidate of the scenes' frames; save it."""
    torch.manual_seed(seed)
    started = time.process_time()
    crops, labels = [], []
    for scene, f in zip(scenes, frames, strict=True):
        for k, region, crop in frame_candidates(f, scene):
            crops.append(crop)
            labels.append(region_label(region, f.seg[k], scene, categories))
    x, y = torch.from_numpy(np.stack(crops)), torch.tensor(labels)
    candidates_cpu = time.process_time() - started
    model = CandidateClassifier(list(categories))
    optimiser = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    rng = np.random.default_rng(seed)
    steps, losses = epochs * (len(x) // 64 + 1), []
    for step in range(steps):
        for group in optimiser.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        index = torch.from_numpy(rng.integers(len(x), size=64))
        batch = x[index]
        flip = torch.from_numpy(rng.random(64) < 0.5)
        batch[flip] = batch[flip].flip(-1)
        loss = F.cross_entropy(model(batch), y[index])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(round(loss.item(), 6))
    summary = {
        "candidates": len(x),
        "no_object_share": round(float((y == 0).float().mean()), 4),
        "steps": steps,
        "losses": losses,
        "candidate_cpu_seconds": round(candidates_cpu, 1),
        "cpu_seconds": round(time.process_time() - started, 1),
    }
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out / "model.safetensors"))
    config = {"kind": "candidate_classifier", "categories": list(categories), "width": model.width}
    (out / "config.json").write_text(json.dumps(config | {"training": summary}, indent=1) + "\n")
    return summary


class CandidatePicker:
    """Design (b) at prediction time: candidates, the classifier, the best region of a category."""

    threshold = 0.5

    def __init__(self, folder: Path):
        from safetensors.torch import load_file

        config = json.loads((Path(folder) / "config.json").read_text())
        self.model = CandidateClassifier(config["categories"], config["width"])
        self.model.load_state_dict(load_file(str(Path(folder) / "model.safetensors")))
        self.model.eval()

    def predict(self, frames, scene, category: str) -> list[Prediction]:
        """The predicted target region per camera of ``frames``."""
        candidates = frame_candidates(frames, scene)
        empty = np.zeros(frames.depth.shape[1:], bool)
        predictions = [Prediction(empty, 0.0) for _ in frames.cameras]
        if not candidates:
            return predictions
        with torch.no_grad():
            p = torch.softmax(self.model(torch.from_numpy(np.stack([c for _, _, c in candidates]))), 1)
        column = 1 + self.model.categories.index(category)
        for (k, region, _), prob in zip(candidates, p[:, column].numpy(), strict=True):
            if prob > self.threshold and prob > predictions[k].score:
                predictions[k] = Prediction(region, float(prob))
        return predictions
