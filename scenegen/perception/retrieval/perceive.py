"""The retrieval head at decision time: frames and the requested category in, the target's pixels
out, per camera (:func:`predict_target`, :class:`RetrievalPerception`), with no segmentation read.

A prediction on one camera's frame: the pixels where the requested category is the most likely class,
split into connected regions; the region with the largest summed probability of the category is the
target (a scene may hold a second object of the category: the planner wants one instance).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from scenegen.perception.retrieval.model import RetrievalHead, head_input


@dataclass(frozen=True)
class Prediction:
    """One camera's predicted target: ``mask`` (H, W) bool (empty: the category is nowhere the
    most likely class),
    ``score`` its summed probability."""

    mask: np.ndarray
    score: float

    @property
    def empty(self) -> bool:
        return not self.mask.any()


def predict_target(
    head: RetrievalHead, rgb: np.ndarray, depth: np.ndarray, category: str
) -> list[Prediction]:
    """The predicted target region in each of K frames: ``rgb`` (K, H, W, 3) uint8, ``depth`` (K, H,
    W) metres."""
    import cv2

    x = torch.from_numpy(np.stack([head_input(c, d) for c, d in zip(rgb, depth, strict=True)]))
    with torch.no_grad():
        logits = head(x)
        planes = torch.nn.functional.interpolate(
            torch.softmax(logits, 1), size=x.shape[-2:], mode="bilinear", align_corners=False
        ).numpy()
    index = head.category_index(category)
    predictions = []
    for p in planes:
        # the category's pixels: where it is the most likely class (background included); a fixed
        # probability threshold missed thin utensils whose probability is split between fork and
        # spoon (docs/retrieval.md)
        chosen = (p.argmax(0) == index).astype(np.uint8)
        count, regions = cv2.connectedComponents(chosen, connectivity=8)
        if count <= 1:
            predictions.append(Prediction(np.zeros(chosen.shape, bool), 0.0))
            continue
        sums = np.bincount(regions.ravel(), weights=p[index].ravel(), minlength=count)
        sums[0] = -1.0  # the background region
        best = int(np.argmax(sums))
        predictions.append(Prediction(regions == best, float(sums[best])))
    return predictions


class RetrievalPerception:
    """What :func:`~scenegen.perception.observation.observe` asks of a learned perception: the
    target's mask in each camera's frame of an observation (``<cam>_image``, ``<cam>_depth``),
    given the requested category. ``name`` says which head (its checkpoint folder)."""

    def __init__(self, head: RetrievalHead, name: str = "retrieval"):
        self.head = head
        self.name = name

    @classmethod
    def load(cls, checkpoint) -> RetrievalPerception:
        return cls(RetrievalHead.load(checkpoint), str(checkpoint))

    def target_masks(self, obs: dict, cameras: Sequence[str], category: str) -> dict[str, np.ndarray]:
        """(H, W) bool mask of the predicted target per camera."""
        rgb = np.stack([obs[f"{c}_image"] for c in cameras])
        depth = np.stack([np.squeeze(obs[f"{c}_depth"], -1) for c in cameras])
        predictions = predict_target(self.head, rgb, depth, category)
        return {c: p.mask for c, p in zip(cameras, predictions, strict=True)}
