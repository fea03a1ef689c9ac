"""The proposal model (issue 63, point 3): a small network that scores a candidate action
(``manipulation/proposals.py``) from what the robot sees around it, learned from simulated outcomes,
as Dex-Net's grasp-quality networks are: sample candidates, score each, act on the best.

Input per candidate: for each camera (front, side), an oriented crop centred on the candidate's
point projected into the frame and turned so that its heading (the fingers' closing axis from above,
the approach from the side, the push or pull direction) runs along the crop's x axis; channels RGB
in [0, 1], depth relative to the candidate point's own (``DEPTH_RANGE`` metres either side, clipped,
scaled to [-1, 1]) and the target's mask (the head's prediction, or the simulator's in the oracle
setting): (2 x 5, CROP, CROP). Beside it the candidate's parameters as numbers
(:func:`candidate_features`). Output: one logit, the estimated chance that the attempt (and, for a
push or a pull, the grasp after it) lifts the target.

Checkpoints are a folder: model.safetensors and config.json, read safely (weights only).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from scenegen.core.rotations import camera_rotation
from scenegen.manipulation.proposals import STRIP, Candidate
from scenegen.perception.observation import CAMERAS, TargetView
from scenegen.schema.scene import Camera

CROP = 48  # px of the crop's side, at the cameras' 320 x 240
DEPTH_RANGE = 0.10  # m either side of the candidate point's depth the crop's depth channel spans
KINDS = ("top", "side", "push", "pull")  # a candidate's kind: a grasp's approach, or the action
FEATURES = len(KINDS) + 20
CHANNELS = 5 * len(CAMERAS)
MODEL_VERSION = 3  # 2: the heading against the seen footprint; 3: the fingers' line (candidate_features)
FINGER_STRIP = 0.015  # m either side of the fingers' line, across the heading
FINGER_HEIGHT = 0.04  # m over the grip site the fingers reach; above it the hand, which ``clear over`` sees
CLEAR_CAP = 0.10  # m: a clearance this large or more counts as free
# Training (version 3; the pilot in docs/policy.md): dropout before the head, weight decay, and a top
# grasp seen also with its heading reversed (a parallel gripper closing the other way round: the
# crop turned 180 degrees, the heading-signed numbers negated)
DROPOUT = 0.3
WEIGHT_DECAY = 0.05
SIGNED = (6, 7, 8, 9, 10, 19)  # offsets along and across, cos, sin, reach alignment, the line's offset


def kind(candidate: Candidate) -> str:
    return candidate.params["approach"] if candidate.action == "grasp" else candidate.action


def _point_and_heading(candidate: Candidate) -> tuple[np.ndarray, np.ndarray]:
    p = candidate.params
    point = p.get("position", p.get("contact"))
    heading = p.get("heading", p.get("direction", p.get("approach")))
    return np.asarray(point, float), np.asarray(heading, float)


def candidate_features(candidate: Candidate, view: TargetView) -> np.ndarray:
    """(FEATURES,) float32: the kind (one-hot); the point's height over the target's lowest seen
    point and under its highest; its offset from the target's centre along and across the heading;
    the heading's world cos and sin, and its alignment with the direction from the robot to the
    point; the seen footprint's major extent; a push's or pull's distance; then (version 2) the
    heading against the footprint's major axis as cos and sin of twice the angle (a closing axis and
    its reverse are one), the minor extent, and the footprint's span along the heading and across it
    (what closing fingers meet, what they straddle); then (version 3) the fingers' line
    (:func:`_finger_line`)."""
    point, heading = _point_and_heading(candidate)
    t = view.target
    offset = point[:2] - t.centre[:2]
    across = np.array([-heading[1], heading[0]])
    outward = point[:2] - np.asarray(view.robot_base)
    outward /= max(np.linalg.norm(outward), 1e-9)
    one_hot = [float(kind(candidate) == k) for k in KINDS]
    numbers = [
        point[2] - t.bottom_z,
        t.top_z - point[2],
        offset @ heading,
        offset @ across,
        heading[0],
        heading[1],
        heading @ outward,
        t.extent[0],
        candidate.params.get("distance", 0.0),
    ]
    turn = np.arctan2(heading[1], heading[0]) - t.yaw
    major, minor = t.extent
    along, across = abs(np.cos(turn)), abs(np.sin(turn))
    numbers += [np.cos(2 * turn), np.sin(2 * turn), minor, along * major + across * minor]
    numbers += [across * major + along * minor]
    numbers += _finger_line(point, heading, view)
    return np.asarray(one_hot + [float(v) for v in numbers], np.float32)


def _finger_line(point: np.ndarray, heading: np.ndarray, view: TargetView) -> list[float]:
    """(version 3) What the fingers meet on their line through the grip site along the heading: the
    seen target's span on that line and the grip site's offset from its middle; the line's top and
    bottom against the grip height; and the clearance from anything else seen (other objects,
    furniture) from 2 cm under the grip height: along the line up to the fingers' height, and over
    the grip site (``CLEAR_CAP`` when free). No look at what the target is."""
    across = np.array([-heading[1], heading[0]])
    points = np.asarray(view.target_points if view.target_points is not None else np.zeros((0, 3)), float)
    near = points[np.abs((points[:, :2] - point[:2]) @ across) < STRIP] if len(points) else points
    if len(near):
        along = (near[:, :2] - point[:2]) @ heading
        line = [along.max() - along.min(), 0.5 * (along.max() + along.min())]
        line += [np.percentile(near[:, 2], 98) - point[2], point[2] - np.percentile(near[:, 2], 2)]
    else:
        line = [0.0, 0.0, 0.0, 0.0]
    others = np.asarray(view.others, float).reshape(-1, 3)
    high = others[others[:, 2] > point[2] - 0.02]
    rel = high[:, :2] - point[:2]
    on_line = (np.abs(rel @ across) < FINGER_STRIP) & (high[:, 2] < point[2] + FINGER_HEIGHT)
    clear_along = np.abs(rel[on_line] @ heading).min(initial=CLEAR_CAP)
    over = high[np.linalg.norm(rel, axis=1) < FINGER_STRIP]
    clear_over = (over[:, 2] - point[2]).min(initial=CLEAR_CAP)
    return [*line, min(clear_along, CLEAR_CAP), min(clear_over, CLEAR_CAP)]


def project(cam: Camera, points: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2: column, row, of pixel centres' grid) and depth along the optical axis
    (N,) of world ``points`` (N, 3) in ``cam``'s frame of ``size`` (width, height): the inverse of
    ``perception.points.masked_points``."""
    width, height = size
    if (cam.width, cam.height) != (width, height):
        cam = cam.model_copy(update={"width": width, "height": height})
    k = cam.intrinsics()
    local = (np.asarray(points, float) - np.asarray(cam.position, float)) @ camera_rotation(
        cam.position, cam.lookat
    )
    z = -local[:, 2]
    u = local[:, 0] * k["fx"] / z + k["cx"] - 0.5
    v = -local[:, 1] * k["fy"] / z + k["cy"] - 0.5
    return np.stack([u, v], axis=1), z


def candidate_crop(
    frames: Mapping[str, tuple], cameras: Mapping[str, Camera], candidate: Candidate
) -> np.ndarray:
    """(CHANNELS, CROP, CROP) float32: per camera of ``CAMERAS`` the oriented crop (module docstring)
    of ``frames[name] = (image (H, W, 3) uint8, depth (H, W) m, mask (H, W) bool)``."""
    import cv2

    point, heading = _point_and_heading(candidate)
    ahead = point + 0.05 * np.array([heading[0], heading[1], 0.0])
    out = []
    for name in CAMERAS:
        image, depth, mask = frames[name]
        depth = np.squeeze(depth).astype(np.float32)
        height, width = depth.shape
        pixels, depths = project(cameras[name], np.stack([point, ahead]), (width, height))
        uv, ahead_uv, z = pixels[0], pixels[1], depths[0]
        angle = np.degrees(np.arctan2(ahead_uv[1] - uv[1], ahead_uv[0] - uv[0]))
        turn = cv2.getRotationMatrix2D((float(uv[0]), float(uv[1])), float(angle), 1.0)
        turn[:, 2] += CROP / 2 - uv  # the candidate's pixel to the crop's centre
        channels = [*(np.asarray(image)[..., c].astype(np.float32) / 255.0 for c in range(3))]
        relative = np.clip((depth - z) / DEPTH_RANGE, -1.0, 1.0)
        relative[depth <= 0] = 1.0  # no depth: as far as the crop reaches
        channels += [relative, np.squeeze(mask).astype(np.float32)]
        for c in channels:
            warped = cv2.warpAffine(c, turn, (CROP, CROP), flags=cv2.INTER_LINEAR, borderValue=0.0)
            out.append(warped)
    return np.stack(out).astype(np.float32)


class ProposalNet(nn.Module):
    """Conv(CHANNELS -> w -> 2w -> 2w, stride 2) + global average pool, joined with the candidate's
    features through an MLP: ((B, CHANNELS, CROP, CROP), (B, FEATURES)) -> (B,) logits."""

    def __init__(self, width: int = 16):
        super().__init__()
        self.width = width
        self.conv = nn.Sequential(
            nn.Conv2d(CHANNELS, width, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(width, 2 * width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(2 * width, 2 * width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        self.head = nn.Sequential(
            nn.Dropout(DROPOUT),
            nn.Linear(2 * width + FEATURES, 4 * width),
            nn.ReLU(),
            nn.Linear(4 * width, 1),
        )

    def forward(self, crops: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.conv(crops), features], dim=1)).squeeze(1)


class ProposalModel:
    """A trained :class:`ProposalNet` with what it was trained under (``config``)."""

    def __init__(self, net: ProposalNet, config: dict):
        self.net = net.eval()
        self.config = config

    def scores(self, crops: np.ndarray, features: np.ndarray) -> np.ndarray:
        """Estimated success (N,) of N candidates from their crops and features."""
        if len(crops) == 0:
            return np.zeros(0)
        with torch.no_grad():
            logits = self.net(torch.from_numpy(crops), torch.from_numpy(features))
        return torch.sigmoid(logits).numpy().astype(float)

    def rank(
        self,
        candidates: Sequence[Candidate],
        view: TargetView,
        frames: Mapping[str, tuple],
        cameras: Mapping[str, Camera],
    ) -> np.ndarray:
        """The candidates' estimated success, in their order."""
        if not candidates:
            return np.zeros(0)
        crops = np.stack([candidate_crop(frames, cameras, c) for c in candidates])
        features = np.stack([candidate_features(c, view) for c in candidates])
        return self.scores(crops, features)

    def save(self, folder: Path) -> None:
        from safetensors.torch import save_file

        from scenegen.store.batch import atomic_write

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().contiguous() for k, v in self.net.state_dict().items()}
        save_file(state, str(folder / "model.safetensors"))
        atomic_write(folder / "config.json", json.dumps(self.config, indent=1, sort_keys=True) + "\n")

    @classmethod
    def load(cls, folder: Path) -> ProposalModel:
        """The model in ``folder``; ``CheckpointError`` (one line, naming the file) when it is not one."""
        from safetensors.torch import load_file

        from scenegen.core.files import CheckpointError

        folder = Path(folder)
        config_path, weights = folder / "config.json", folder / "model.safetensors"
        if not config_path.is_file() or not weights.is_file():
            raise CheckpointError(f"{folder}: not a proposal model (config.json and model.safetensors)")
        try:
            config = json.loads(config_path.read_text())
            if config.get("kind") != "proposals" or config.get("version") != MODEL_VERSION:
                raise ValueError(f"kind {config.get('kind')!r} version {config.get('version')!r}")
            net = ProposalNet(int(config["width"]))
            net.load_state_dict(load_file(str(weights)))
        except (ValueError, KeyError, TypeError, RuntimeError) as exc:
            message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CheckpointError(
                f"{folder}: not a proposal model of version {MODEL_VERSION}: {message}"
            ) from exc
        return cls(net, config)


def train_model(
    crops: np.ndarray,
    features: np.ndarray,
    labels: np.ndarray,
    steps: int = 2000,
    batch: int = 64,
    width: int = 16,
    seed: int = 0,
    device: str = "cpu",
    config: dict | None = None,
) -> ProposalModel:
    """A model trained on (crops, features) -> labels (0/1) by binary cross-entropy, the positives
    weighted by the negatives' share (most candidates fail), with ``WEIGHT_DECAY``, ``DROPOUT`` and
    each top grasp seen half the time with its heading reversed (``SIGNED``); batches and flips drawn
    from ``seed``'s stream on the CPU, so a device changes no draw."""
    torch.manual_seed(seed)
    net = ProposalNet(width).to(device)
    labels = np.asarray(labels, np.float32)
    positives = max(float(labels.sum()), 1.0)
    weight = torch.tensor((len(labels) - positives) / positives, device=device).clamp(1.0, 20.0)
    optimiser = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=WEIGHT_DECAY)
    loss_fn = nn.BCEWithLogitsLoss(pos_weight=weight)
    generator = torch.Generator().manual_seed(seed)
    x, f, y = torch.from_numpy(crops), torch.from_numpy(features), torch.from_numpy(labels)
    sign = torch.ones(FEATURES)
    sign[list(SIGNED)] = -1.0
    net.train()
    for _ in range(steps):
        index = torch.randint(len(y), (batch,), generator=generator)
        xb, fb = x[index], f[index]
        turn = (torch.rand(batch, generator=generator) < 0.5) & (fb[:, KINDS.index("top")] > 0.5)
        xb = torch.where(turn[:, None, None, None], xb.flip(2, 3), xb)
        fb = torch.where(turn[:, None], fb * sign, fb)
        loss = loss_fn(net(xb.to(device), fb.to(device)), y[index].to(device))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    net = net.cpu()
    meta = {"kind": "proposals", "version": MODEL_VERSION, "width": width, "steps": steps, "seed": seed}
    return ProposalModel(net, {**meta, **(config or {}), "examples": len(y), "positives": int(labels.sum())})
