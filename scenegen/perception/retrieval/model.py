"""The retrieval head's network (design (a), docs/retrieval.md): a small fully convolutional
segmenter whose output has one plane per object category; the requested category selects its plane.

Input (B, 4, H, W) float32: RGB scaled to [0, 1] and depth in metres divided by ``DEPTH_SCALE``, at
the planner's frame size (320 x 240). Output (B, 1 + C, H / 2, W / 2) logits: background and one
class per category of ``categories`` (softmax over them). Every object's pixels supervise its own
category's plane, so one image teaches every category it shows, not only the requested one; the
output is at half resolution with a full-resolution stem and skip, so a 3 cm spoon (2-3 pixels wide
at 320 x 240) keeps its pixels. Checkpoints are safetensors plus a JSON config.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

DEPTH_SCALE = 2.0  # m: depth / 2 lies in [0, 1] for the table-top cameras


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


def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class RetrievalHead(nn.Module):
    """A 3-level U-Net: stem at 1/2 (``width`` channels), 1/4 (3 x), 1/8 (6 x, two dilated blocks
    for context), decoded back to 1/2 with skips; a 1 x 1 head gives (B, 1 + C, H / 2, W / 2) logits.
    Narrow where the resolution is high: the half-resolution levels cost most of the CPU."""

    def __init__(self, categories: list[str], width: int = 8):
        super().__init__()
        self.categories = list(categories)
        self.width = width
        w = width
        self.stem = nn.Sequential(_block(4, w, stride=2), _block(w, w))
        self.down1 = nn.Sequential(_block(w, 3 * w, stride=2), _block(3 * w, 3 * w))
        self.down2 = nn.Sequential(
            _block(3 * w, 6 * w, stride=2), _block(6 * w, 6 * w, dilation=2), _block(6 * w, 6 * w, dilation=4)
        )
        self.up1 = _block(6 * w + 3 * w, 3 * w)
        self.up2 = _block(3 * w + w, w)
        self.head = nn.Conv2d(w, 1 + len(self.categories), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        half = self.stem(x)
        quarter = self.down1(half)
        eighth = self.down2(quarter)
        y = F.interpolate(eighth, size=quarter.shape[-2:], mode="bilinear", align_corners=False)
        y = self.up1(torch.cat([y, quarter], 1))
        y = F.interpolate(y, size=half.shape[-2:], mode="bilinear", align_corners=False)
        y = self.up2(torch.cat([y, half], 1))
        return self.head(y)

    def category_index(self, category: str) -> int:
        """The output plane of ``category`` (1-based: plane 0 is the background)."""
        if category not in self.categories:
            raise ValueError(
                f"category {category!r}: this retrieval head knows {', '.join(self.categories)}; "
                "train one on scenes that hold it"
            )
        return 1 + self.categories.index(category)

    def save(self, folder: Path, extra: dict | None = None) -> None:
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.contiguous() for k, v in self.state_dict().items()}
        save_file(tensors, str(folder / "model.safetensors"))
        config = {"kind": "retrieval_head", "categories": self.categories, "width": self.width}
        config |= {"depth_scale": DEPTH_SCALE, "rule": "argmax"}
        (folder / "config.json").write_text(json.dumps(config | (extra or {}), indent=1) + "\n")

    @classmethod
    def load(cls, folder: Path) -> RetrievalHead:
        """The head of a checkpoint folder; CheckpointError (one line, naming the file) otherwise."""
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
        if config.get("kind") != "retrieval_head":
            raise CheckpointError(f"{folder / 'config.json'}: kind: 'retrieval_head' expected; " + remedy)
        model = cls(
            names_field(config, "categories", folder, "category"), int_field(config, "width", folder, 2, 256)
        )
        try:
            model.load_state_dict(load_file(str(folder / "model.safetensors")))
        except Exception as exc:  # noqa: BLE001 - safetensors' own error type, shape mismatches, I/O
            raise checkpoint_error(folder / "model.safetensors", exc, remedy) from None
        model.trained_on = config.get("training", {})
        return model.eval()


def head_input(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(4, H, W) float32 network input from one camera's RGB (H, W, 3) uint8 and depth (H, W) m."""
    rgb = np.asarray(rgb, np.float32).transpose(2, 0, 1) / 255.0
    return np.concatenate([rgb, np.squeeze(depth).astype(np.float32)[None] / DEPTH_SCALE])
