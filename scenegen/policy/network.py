"""The baseline policy: a small CNN that maps the decision-point observation to a success estimate per
primitive, and chooses the primitive it rates highest.

Input (B, 5, H, W) float32, a crop around the target: RGB scaled to [0, 1], depth in metres divided
by ``DEPTH_SCALE``, and the target's instance mask (the fraction of each cell on the target).
Output (B, P) logits, one per primitive in ``primitives`` order; trained with a per-primitive binary
cross-entropy on the expert labels (every labelled scene teaches every primitive, success or not).
Checkpoints are safetensors plus a JSON config.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import nn

DEPTH_SCALE = 2.0  # m: depth / 2 lies in [0, 1] for the table-top cameras
INPUT_SIZE = (96, 72)  # (width, height) the crop is resized to
CROP = 0.5  # the crop around the target: half the frame's width and height


def observation_tensor(image: np.ndarray, depth: np.ndarray, target_mask: np.ndarray) -> np.ndarray:
    """(5, H, W) float32 network input (H, W = ``INPUT_SIZE``) from one camera's frames and the
    target's mask (H, W) bool: the simulator's (oracle) or the retrieval head's.

    The frames are cropped to ``CROP`` (a fraction of the frame) around the target's mask, so small
    targets (a 3 cm spoon) keep enough pixels, and resized with area averaging: the mask channel holds
    the fraction of each cell that is target, never rounded away."""
    import cv2

    depth = np.squeeze(depth).astype(np.float32)
    mask = np.squeeze(target_mask).astype(np.float32)
    height, width = mask.shape
    ch, cw = int(height * CROP), int(width * CROP)
    rows, cols = np.nonzero(mask)
    cy, cx = (rows.mean(), cols.mean()) if len(rows) else (height / 2, width / 2)
    top = int(np.clip(cy - ch / 2, 0, height - ch))
    left = int(np.clip(cx - cw / 2, 0, width - cw))
    window = (slice(top, top + ch), slice(left, left + cw))
    channels = [
        *(image[window][..., c].astype(np.float32) / 255.0 for c in range(3)),
        depth[window] / DEPTH_SCALE,
        mask[window],
    ]
    return np.stack([cv2.resize(c, INPUT_SIZE, interpolation=cv2.INTER_AREA) for c in channels])


INPUTS = ("rgbd", "state")  # what the network reads: the camera crop, or the state ablation's features


class PrimitivePolicy(nn.Module):
    """``rgbd``: Conv(5->16->32->64, stride 2) + global average pool + linear head: (B, 5, H, W) ->
    (B, P). ``state`` (the ablation): an MLP over :func:`~scenegen.perception.observation.state_features`,
    (B, STATE_SIZE) -> (B, P)."""

    def __init__(self, primitives: list[str], width: int = 32, inputs: str = "rgbd"):
        super().__init__()
        if inputs not in INPUTS:
            raise ValueError(f"inputs {inputs!r}: choose one of {', '.join(INPUTS)}")
        self.primitives = list(primitives)
        self.width = width
        self.inputs = inputs
        self.trained_on: dict = {}  # the checkpoint's training summary (data, coverage, losses)
        if inputs == "state":
            from scenegen.perception.observation import STATE_SIZE

            self.features = nn.Sequential(
                nn.Linear(STATE_SIZE, 2 * width), nn.ReLU(), nn.Linear(2 * width, 2 * width), nn.ReLU()
            )
            self.head = nn.Linear(2 * width, len(self.primitives))
            return
        self.features = nn.Sequential(
            nn.Conv2d(5, width // 2, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(width // 2, width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        self.head = nn.Linear(2 * width, len(self.primitives))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))

    def choose(self, x: torch.Tensor, exclude: set[str] = frozenset()) -> str:
        """The primitive with the highest predicted success for one observation (5, H, W)."""
        with torch.no_grad():
            logits = self(x[None])[0].clone()
        for i, name in enumerate(self.primitives):
            if name in exclude:
                logits[i] = -torch.inf
        return self.primitives[int(torch.argmax(logits))]

    def save(self, folder: Path, extra: dict | None = None) -> None:
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        save_file(
            {k: v.contiguous() for k, v in self.state_dict().items()}, str(folder / "model.safetensors")
        )
        config = {"primitives": self.primitives, "width": self.width, "input_size": list(INPUT_SIZE)}
        config["inputs"] = self.inputs
        (folder / "config.json").write_text(json.dumps(config | (extra or {}), indent=1) + "\n")

    @classmethod
    def load(cls, folder: Path) -> PrimitivePolicy:
        """The policy of a checkpoint folder; CheckpointError (one line, naming the file) otherwise."""
        from safetensors.torch import load_file

        from scenegen.core.files import (
            CheckpointError,
            checkpoint_error,
            int_field,
            names_field,
            read_checkpoint_config,
        )

        folder = Path(folder)
        remedy = "train one with `scenegen policy train --out DIR`"
        config = read_checkpoint_config(folder, "policy", remedy)
        primitives = names_field(config, "primitives", folder, "primitive")
        width = int_field(config, "width", folder, 2, 1024)
        try:
            model = cls(primitives, width, config.get("inputs", "rgbd"))
        except (KeyError, TypeError, ValueError, AssertionError, RuntimeError) as exc:
            raise checkpoint_error(folder / "config.json", exc, remedy) from None
        try:
            model.load_state_dict(load_file(str(folder / "model.safetensors")))
        except Exception as exc:  # noqa: BLE001 - safetensors' own error type, shape mismatches, I/O
            raise checkpoint_error(folder / "model.safetensors", exc, remedy) from None
        training = config.get("training", {})
        coverage = training.get("coverage", []) if isinstance(training, dict) else None
        if not isinstance(coverage, list) or not all(_coverage_cell(cell) for cell in coverage):
            raise CheckpointError(
                f"{folder / 'config.json'}: training.coverage: a list of [tag, category, count] expected; "
                + remedy
            )
        model.trained_on = training
        return model.eval()


def _coverage_cell(cell) -> bool:
    """A ``[tag, category, count]`` entry of a checkpoint's training coverage."""
    return (
        isinstance(cell, list)
        and len(cell) == 3
        and all(isinstance(x, str) for x in cell[:2])
        and isinstance(cell[2], int)
    )
