"""The retrieval head at decision time: frames and the requested category in, the target's pixels
out, per camera (:func:`predict_target`, :class:`RetrievalPerception`), with no segmentation read.

A prediction on one camera's frame: the pixels where the requested category is the most likely class,
split into connected regions; the region with the largest summed probability of the category is the
target (a scene may hold a second object of the category: the planner wants one instance).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from scenegen.perception.retrieval.frames import Frames
from scenegen.perception.retrieval.model import Prediction, RetrievalHead, head_input


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
    target's mask in each camera's frame of an observation (``<cam>_image``, ``<cam>_depth``,
    ``<cam>_robot_mask``), given the requested category; either design (a segmenter, or depth
    candidates with a classifier: docs/retrieval.md). ``name`` says which checkpoint."""

    def __init__(self, predict, name: str = "retrieval"):
        self.predict = predict  # (frames, cameras, category, robot masks) -> a Prediction per camera
        self.name = name

    @classmethod
    def load(cls, checkpoint) -> RetrievalPerception:
        """The perception of a checkpoint folder of either design (its config.json's ``kind``)."""
        from scenegen.core.files import read_checkpoint_config
        from scenegen.perception.retrieval.candidates import CandidatePicker

        remedy = "train one with `scenegen retrieval train --out DIR`"
        kind = read_checkpoint_config(checkpoint, "retrieval head", remedy).get("kind")
        if kind in ("candidate_classifier", "instances"):
            return cls(CandidatePicker(checkpoint).predict, str(checkpoint))
        head = RetrievalHead.load(checkpoint)

        def segmenter(frames, cameras, category, robot):  # it reads the frames' RGB-D only
            return predict_target(head, frames.rgb, frames.depth, category)

        return cls(segmenter, str(checkpoint))

    def target_masks(
        self, obs: dict, cameras: Sequence[str], category: str, parameters
    ) -> dict[str, np.ndarray]:
        """(H, W) bool mask of the predicted target per camera named in ``cameras``, from what a
        robot has: the frames of ``obs``, the cameras' ``parameters`` (``Camera`` models), the
        robot's own pixels and the requested ``category``."""
        rgb = np.stack([obs[f"{c}_image"] for c in cameras])
        depth = np.stack([np.squeeze(obs[f"{c}_depth"], -1) for c in cameras])
        robot = np.stack([np.squeeze(obs[f"{c}_robot_mask"], -1) for c in cameras])
        predictions = self.predict(Frames(tuple(cameras), rgb, depth, None), parameters, category, robot)
        return {c: p.mask for c, p in zip(cameras, predictions, strict=True)}
