"""Design (b) of the retrieval head, measured against the segmenter (model.py) before choosing
(docs/retrieval.md; benchmarks/retrieval_designs.py): object candidates from depth, and a small
learned classifier that picks the requested category among them.

Candidates, as unseen-object segmentation does it: the depth pixels whose world points lie above the
table within its edges, that are not the robot's own pixels (regions.py: ``foreground``), split
into regions where neighbouring depths jump by more than ``EDGE`` (connected components of what is
left), or, in the ``instances`` design, by the learned separation of separation.py. Each
region of at least ``MIN_PIXELS`` is a candidate. The classifier sees a candidate's RGB-D crop (its
long axis turned along the crop's width, ``CROP`` px) and its mask, and gives logits over "no object"
(furniture, a merged blob) and the categories; the target is the candidate with the highest probability of the
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

from scenegen.perception.retrieval.model import Prediction
from scenegen.perception.retrieval.regions import (  # noqa: F401 - the design's split, re-exported
    EDGE,
    MIN_PIXELS,
    DepthRule,
    candidate_regions,
    depth_edge_regions,
    foreground,
    robot_pixels,
)
from scenegen.perception.retrieval.separation import CHANNELS, LEARNED_RULE_STEPS, SEPARATOR_STEPS

CROP = 32  # px: the classifier's input size
FILL = 0.8  # of the crop's width the region's long axis fills


def candidate_crop(rgb: np.ndarray, depth: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(5, CROP, CROP) float32 of one region: RGB in [0, 1], depth relative to the region's median
    (per 10 cm, clipped to [-1, 1]) and the region's mask, turned so the region's long axis lies
    along the crop's width and scaled so it fills ``FILL`` of it (a fork and a spoon at any angle
    and distance look alike to the classifier but for their shapes)."""
    import cv2

    rows, cols = np.nonzero(region)
    centre = np.array([cols.mean(), rows.mean()])
    spread = np.stack([cols - centre[0], rows - centre[1]])
    values, vectors = np.linalg.eigh(np.cov(spread) + 1e-6 * np.eye(2))
    major = vectors[:, np.argmax(values)]
    length = max(float(np.ptp(spread.T @ major)) + 2.0, 4.0)
    turn = cv2.getRotationMatrix2D(
        (float(centre[0]), float(centre[1])),
        float(np.degrees(np.arctan2(major[1], major[0]))),
        FILL * CROP / length,
    )
    turn[:, 2] += CROP / 2 - centre
    median = float(np.median(depth[region]))
    channels = [
        *(rgb[..., c].astype(np.float32) / 255.0 for c in range(3)),
        np.clip((depth - median) / 0.1, -1, 1).astype(np.float32),
        region.astype(np.float32),
    ]
    return np.stack([cv2.warpAffine(c, turn, (CROP, CROP), flags=cv2.INTER_LINEAR) for c in channels])


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


def frame_candidates(
    frames, cameras, robot: np.ndarray, split=depth_edge_regions
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(camera index, region mask, crop) of every candidate of a scene's frames. ``cameras``: the
    :class:`~scenegen.schema.scene.Camera` parameters (any order; matched to the frames by name);
    ``robot`` (K, H, W): the robot's own pixels (:func:`robot_pixels`, or the environment's
    self-filter at decision time). ``split(rgb, depth, robot, camera)``: a frame's regions (the
    design's: depth edges, or the learned separation of separation.py)."""
    cameras = {c.name: c for c in cameras}
    out = []
    for k, name in enumerate(frames.cameras):
        for region in split(frames.rgb[k], frames.depth[k], robot[k], cameras[name]):
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
    scenes,
    frames,
    categories: Sequence[str],
    out: Path,
    steps: int = 6000,
    seed: int = 0,
    lr: float = 3e-3,
    alpha: float = 1.0,
    description: dict | None = None,
    progress: bool = False,
    split=depth_edge_regions,
    design: dict | None = None,
    device: str = "cpu",
    recipe=None,
) -> dict:
    """Train a :class:`CandidateClassifier` on every candidate of the scenes' frames (regions by
    ``split``, see :func:`frame_candidates`); save it. ``design``: what config.json says of the
    design (default: the ``candidate_classifier`` kind; separation.py's ``instances`` adds its
    separator).
    Batches of 64 are balanced over the labels (a fork is rarer than a box); within a label a
    candidate is drawn by its scene's weight in the seed's mixture (generated sources weighted
    ``alpha``, as the segmenter's and the policy's training draw scenes; ``recipe``: another
    MixtureRecipe, e.g. a transfer arm's); each crop is flipped along
    either axis at random and its colours scaled (dim scenes are a rare case). ``device``: where the
    weights and batches live (scenegen/devices.py; batches are drawn on the CPU either way)."""
    from tqdm import tqdm

    from scenegen.devices import resolve_device
    from scenegen.env.mixture import scene_weights
    from scenegen.perception.retrieval.train import default_recipe

    torch.manual_seed(seed)
    started = time.process_time()
    recipe = recipe or default_recipe(scenes, alpha)
    weights = scene_weights(recipe, scenes)
    crops, labels, scene_of = [], [], []
    bar = tqdm(zip(scenes, frames, strict=True), total=len(scenes), desc="candidates", disable=not progress)
    for i, (scene, f) in enumerate(bar):
        for k, region, crop in frame_candidates(f, scene.cameras, robot_pixels(f, scene), split):
            crops.append(crop)
            labels.append(region_label(region, f.seg[k], scene, categories))
            scene_of.append(i)
    if not crops:
        raise ValueError(
            f"no candidate region in the {len(scenes)} training scenes' frames: the region split found no "
            "object (train on more scenes, or the separator longer: --separator-steps)"
        )
    x, y = torch.from_numpy(np.stack(crops)), torch.tensor(labels)
    candidates_cpu = time.process_time() - started
    on = resolve_device(device)
    model = CandidateClassifier(list(categories)).to(on)
    optimiser = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    rng = np.random.default_rng(seed)
    members = [np.nonzero(y.numpy() == c)[0] for c in range(1 + len(categories))]
    members = [m for m in members if weights[np.asarray(scene_of)[m]].sum() > 0]
    draw = [weights[np.asarray(scene_of)[m]] / weights[np.asarray(scene_of)[m]].sum() for m in members]
    losses = []
    for step in tqdm(range(steps), desc="training", disable=not progress):
        for group in optimiser.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        index = torch.from_numpy(
            np.array([rng.choice(members[c], p=draw[c]) for c in rng.integers(len(members), size=64)])
        )
        batch = x[index].clone()
        for axis in (-1, -2):
            flip = torch.from_numpy(rng.random(64) < 0.5)
            batch[flip] = batch[flip].flip(axis)
        batch[:, :3] = (
            batch[:, :3] * torch.from_numpy(rng.uniform(0.35, 1.25, (64, 1, 1, 1)).astype(np.float32))
        ).clamp(0, 1)
        loss = F.cross_entropy(model(batch.to(on)), y[index].to(on))
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
        "seed": seed,
        "scenes": len(scenes),
        "effective_shares": recipe.effective_shares(),
        "data": description or {},
    }
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model.cpu()
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out / "model.safetensors"))
    config = (design or {"kind": "candidate_classifier"}) | {
        "categories": list(categories),
        "width": model.width,
    }
    (out / "config.json").write_text(json.dumps(config | {"training": summary}, indent=1) + "\n")
    return summary


def default_separator_steps(rule: DepthRule) -> int:
    """The separator's training steps under ``rule``: a learned rule's separator also learns the
    object map and needs more (separation.LEARNED_RULE_STEPS)."""
    return LEARNED_RULE_STEPS if rule.learned else SEPARATOR_STEPS


def train_instances(
    scenes,
    frames,
    categories: Sequence[str],
    out,
    steps: int = 6000,
    seed: int = 0,
    alpha: float = 1.0,
    description: dict | None = None,
    progress: bool = False,
    separator_steps: int | None = None,
    width: int = 8,
    channels: int = CHANNELS,
    device: str = "cpu",
    recipe=None,
    rule=None,
) -> dict:
    """The ``instances`` design: a :class:`Separator` trained on the scenes' instance labels, then
    the crop classifier trained on the regions it gives (as it will see them at prediction time);
    both saved in ``out`` (separator.safetensors, model.safetensors, config.json). ``frames``: the
    scenes' frames, a sequence (read twice). Scenes are drawn by the seed's mixture (``alpha``; or
    ``recipe``), as the classifier draws them. ``channels``: the separator's input planes
    (separation.py: 9; 7 as separators were saved before the contact channels). ``rule``: the
    region step's ``regions.DepthRule`` (default exact depth's; another is saved in config.json as
    ``depth_rule`` and applied at prediction time). ``separator_steps``: default ``SEPARATOR_STEPS``,
    ``LEARNED_RULE_STEPS`` under a learned rule. Returns the classifier's summary with the
    separator's under ``separator``."""
    from safetensors.torch import save_file

    from scenegen.env.mixture import scene_weights
    from scenegen.perception.retrieval.separation import SeparatorRegions, separator_frames, train_separator
    from scenegen.perception.retrieval.train import default_recipe

    started = time.process_time()
    rule = rule or DepthRule()
    if separator_steps is None:
        separator_steps = default_separator_steps(rule)
    if rule.mends:
        frames = [rule.mend_frames(f) for f in frames]
    inputs, labels, contacts, scene_of, objects = separator_frames(scenes, frames, channels, rule)
    recipe = recipe or default_recipe(scenes, alpha)  # the mixture both parts draw scenes by
    weights = scene_weights(recipe, scenes)[scene_of]
    model, summary = train_separator(
        inputs,
        labels,
        weights,
        contacts,
        separator_steps,
        seed,
        width=width,
        progress=progress,
        device=device,
        objects=objects,
    )
    del inputs, labels, contacts, objects
    summary["cpu_seconds"] = round(time.process_time() - started, 1)  # frames' inputs included
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out / "separator.safetensors"))
    spec = {"width": width, "channels": channels} | ({"outputs": 2} if rule.learned else {})
    design = {"kind": "instances", "separator": spec | {"training": summary}}
    if rule != DepthRule():  # exact depth's rule is left out: such checkpoints keep their bytes
        design["depth_rule"] = rule.config()
    result = train_classifier(
        scenes,
        frames,
        categories,
        out,
        steps,
        seed,
        alpha=alpha,
        description=description,
        progress=progress,
        split=SeparatorRegions(model, rule),
        design=design,
        device=device,
        recipe=recipe,
    )
    return result | {"separator": summary, "cpu_seconds": round(time.process_time() - started, 1)}


class CandidatePicker:
    """Design (b) at prediction time: candidates, the classifier, the best region of a category."""

    threshold = 0.5

    def __init__(self, folder: Path):
        from safetensors.torch import load_file

        from scenegen.core.files import (
            CheckpointError,
            checkpoint_error,
            int_field,
            names_field,
            read_checkpoint_config,
        )

        folder = Path(folder)
        remedy = "train one with `scenegen retrieval train --out DIR`"
        config = read_checkpoint_config(folder, "retrieval head", remedy)
        categories = names_field(config, "categories", folder, "category")
        self.model = CandidateClassifier(categories, int_field(config, "width", folder, 2, 256))
        try:
            self.model.load_state_dict(load_file(str(folder / "model.safetensors")))
        except Exception as exc:  # noqa: BLE001 - safetensors' own error type, shape mismatches, I/O
            raise checkpoint_error(folder / "model.safetensors", exc, remedy) from None
        self.model.eval()
        self.split = depth_edge_regions
        self.rule = DepthRule()
        if config.get("kind") == "instances":
            from scenegen.perception.retrieval.separation import load_separator

            if "depth_rule" in config:
                try:
                    self.rule = DepthRule.from_config(config["depth_rule"], folder / "config.json")
                except ValueError as exc:
                    raise CheckpointError(f"{exc}; {remedy}") from None
            self.split = load_separator(folder, config, remedy, self.rule)

    def predict(self, frames, cameras, category: str, robot: np.ndarray) -> list[Prediction]:
        """The predicted target region per camera of ``frames``: ``cameras`` their parameters,
        ``robot`` (K, H, W) the robot's own pixels, ``category`` the requested one."""
        if category not in self.model.categories:  # a user catalog's category, say
            raise ValueError(
                f"category {category!r}: this retrieval head knows {', '.join(self.model.categories)}; "
                "train one on scenes that hold it (scenegen retrieval train), or use the oracle"
            )
        candidates = frame_candidates(self.rule.mend_frames(frames), cameras, robot, self.split)
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
