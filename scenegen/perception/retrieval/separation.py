"""Learned instance separation: what splits one object from another is learned from the simulator's
instance labels, not set by hand (issue 43; the ``instances`` design of docs/retrieval.md).

The candidate design splits the depth pixels above the table where neighbouring depths jump by more
than 4 cm, so a mug standing on a plate, or a knife lying on a can, is one region with what it
touches before anything learned sees it. Here a small fully convolutional network, the
:class:`Separator`, labels every foreground pixel (above the table, within its edges, not the robot:
``regions.foreground``) as an instance's **interior** or as a **boundary** pixel: one with a
pixel of another instance at least as high above the table within ``BAND`` px (contour-aware
segmentation, as DCAN learns it, trained on synthetic RGB-D as UOIS-Net and SD Mask R-CNN are). The
band lies on the lower object's side of a contact, so a thin object lying on another keeps its
interior. The connected interiors are the seeds; the other foreground pixels join a touching
region within ``GROW`` px, the lowest one first; regions of
``MIN_PIXELS`` or more are the candidates, which the crop classifier then names. A region crosses
from one object into another only where the network calls a whole band interior.

Input (B, 9, H, W) float32: RGB in [0, 1], depth relative to the foreground's median (per 10 cm,
clipped to [-1, 1]), the largest depth difference to a 4-neighbour (per ``JUMP``, clipped to [0,
2]: a feature at full resolution, not a rule), height above the table (per 10 cm, clipped), the
foreground mask, and two channels at the scale of a contact (per ``STEP``, clipped to [0, 2]): the
largest height difference to a 4-neighbour, and the height above the lowest foreground pixel within
``BAND`` px (which side of a step stands proud: a spoon 3 px wide on a plate is all proud, the
plate's band beside it is not). Separators saved before those two have 7 channels. Output (B, 1,
H, W) logits of "interior"; the loss counts foreground pixels only, boundary pixels weighted by
``BOUNDARY_WEIGHT``. The network runs on the foreground's bounding box.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

BAND = 2  # px: the boundary band's width on the lower object's side of a contact
GROW = 4  # px: how far a seed's region reaches past its interior (over the band)
MIN_SEED = 4  # px: a smaller interior component is noise, no seed
BOUNDARY_WEIGHT = 10.0  # loss weight of a boundary pixel (few foreground pixels are one)
PATCH = 80  # px: square training crops
INTERIOR_LOGIT = 0.0  # a pixel is interior where the network's logit exceeds this (probability 0.5)
OBJECT_LOGIT = 0.0  # a learned foreground's pixel is an object's where its logit exceeds this
OBJECT_WEIGHT = 5.0  # loss weight of an object's pixel in the object map (a fork is 60 px of a crop's 6,400)
SEPARATOR_STEPS = 3000  # training steps of 8 crops (the instances design's default)
# under the learned depth rule the separator also learns the object map: 12,000 steps (docs/sensor.md:
# the validation pilots, nominal overlap hit 0.76 at 3,000, 0.80 at 6,000, 0.88 at 12,000)
LEARNED_RULE_STEPS = 12000
JUMP = 0.04  # m: the scale of the depth-difference channel (the candidate design's split)
STEP = 0.01  # m: the scale of the two height channels at contacts (a spoon lies 6 mm proud of its plate)
CHANNELS = 9  # separators saved before the contact channels have 7 (config "separator" "channels")
MARGIN = 8  # px around the foreground's bounding box that the network sees at prediction time


def _largest_step(values: np.ndarray) -> np.ndarray:
    """(H, W) float32: the largest absolute difference of ``values`` to a 4-neighbour."""
    step = np.zeros(values.shape, np.float32)
    across, down = np.abs(np.diff(values, axis=1)), np.abs(np.diff(values, axis=0))
    step[:, 1:] = np.maximum(step[:, 1:], across)
    step[:, :-1] = np.maximum(step[:, :-1], across)
    step[1:, :] = np.maximum(step[1:, :], down)
    step[:-1, :] = np.maximum(step[:-1, :], down)
    return step


def check_channels(channels) -> None:
    """ValueError (one line) unless ``channels`` is a separator's input planes: 7 (saved before
    the contact channels) or ``CHANNELS``."""
    if type(channels) is not int or channels not in (7, CHANNELS):
        raise ValueError(f"separator channels {channels!r}: 7 or {CHANNELS}")


def separator_input(
    rgb: np.ndarray, depth: np.ndarray, keep: np.ndarray, height: np.ndarray, channels: int = CHANNELS
) -> np.ndarray:
    """(channels, H, W) float32 network input of one frame: ``rgb`` (H, W, 3) uint8, ``depth`` (H,
    W) m, ``keep`` (H, W) bool foreground, ``height`` (H, W) m above the table top. ``channels`` 7
    leaves out the two contact channels (separators saved before them)."""
    check_channels(channels)
    median = float(np.median(depth[keep])) if keep.any() else 1.0
    planes = [
        rgb.transpose(2, 0, 1).astype(np.float32) / 255.0,
        np.clip((depth - median) / 0.1, -1, 1)[None].astype(np.float32),
        np.clip(_largest_step(depth) / JUMP, 0, 2)[None],
        np.clip(height / 0.1, -1, 1)[None].astype(np.float32),
        keep[None].astype(np.float32),
    ]
    if channels == CHANNELS:  # at contacts: how high the step, and which side stands proud
        import cv2

        lifted = np.where(keep, height, 0.0)
        planes.append(np.clip(_largest_step(lifted) / STEP, 0, 2)[None])
        window = np.ones((2 * BAND + 1, 2 * BAND + 1), np.uint8)
        lowest = cv2.erode(np.where(keep, height, np.inf).astype(np.float32), window)
        proud = np.where(keep, height - lowest, 0.0)
        planes.append(np.clip(proud / STEP, 0, 2)[None].astype(np.float32))
    return np.concatenate(planes)


def interior_labels(seg: np.ndarray, keep: np.ndarray, height: np.ndarray, band: int = BAND) -> np.ndarray:
    """(H, W) int8 training labels: 1 interior, 0 boundary, -1 outside the foreground (not scored).
    A foreground pixel is boundary when a foreground pixel of another instance at least as high
    above the table (``height``, m) lies within ``band`` px (the square around it): the band lies on
    the lower object's side of a contact, so a knife on a plate, three pixels wide, keeps its
    interior and the plate gives up the band (by depth, the plate in front of the knife is nearer
    the camera: height, not depth, says what lies on what)."""
    pad = band
    ids = np.pad(np.where(keep, seg, -1), pad, constant_values=-1)
    up = np.pad(height.astype(np.float32), pad, constant_values=-np.inf)
    rows, cols = seg.shape
    boundary = np.zeros_like(keep)
    for dy in range(-band, band + 1):
        for dx in range(-band, band + 1):
            window = (slice(pad + dy, pad + dy + rows), slice(pad + dx, pad + dx + cols))
            other = ids[window]
            boundary |= (other >= 0) & (other != seg) & (up[window] >= height)
    labels = np.where(boundary, 0, 1).astype(np.int8)
    labels[~keep] = -1
    return labels


def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation), nn.ReLU(inplace=True)
    )


class Separator(nn.Module):
    """A narrow U-Net: a full-resolution stem (``width`` channels), 1/2 (2 x), 1/4 (4 x, a dilated
    block for context), decoded back to full resolution with skips; (B, channels, H, W) -> (B, 1, H,
    W) interior logits. Narrow at full resolution, where most of the CPU goes."""

    def __init__(self, width: int = 8, channels: int = CHANNELS, outputs: int = 1):
        super().__init__()
        self.width = w = width
        self.channels = channels
        self.outputs = outputs  # 1: interior; 2: interior and object (a learned foreground)
        self.stem = _block(channels, w)
        self.down1 = nn.Sequential(_block(w, 2 * w, stride=2), _block(2 * w, 2 * w))
        self.down2 = nn.Sequential(_block(2 * w, 4 * w, stride=2), _block(4 * w, 4 * w, dilation=2))
        self.up2 = _block(4 * w + 2 * w, 2 * w)
        self.up1 = _block(2 * w + w, w)
        self.head = nn.Conv2d(w, outputs, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.stem(x)
        d1 = self.down1(s)
        d2 = self.down2(d1)
        u2 = self.up2(torch.cat([F.interpolate(d2, size=d1.shape[-2:], mode="nearest"), d1], 1))
        u1 = self.up1(torch.cat([F.interpolate(u2, size=s.shape[-2:], mode="nearest"), s], 1))
        return self.head(u1)


def grow_regions(interior: np.ndarray, keep: np.ndarray, height: np.ndarray) -> list[np.ndarray]:
    """Candidate regions (H, W) bool from a predicted ``interior`` mask: its 4-connected components
    of ``MIN_SEED`` pixels or more are seeds; the other ``keep`` pixels within ``GROW`` px of a seed
    join it, the lowest seed (mean height) claiming first (the boundary band of a contact lies on
    the lower object's side); regions of ``MIN_PIXELS`` or more are kept. ``height`` (H, W) metres
    above the table. Computed on the foreground's box."""
    import cv2

    from scenegen.perception.retrieval.regions import MIN_PIXELS

    box = _box(keep)
    if box is None:
        return []
    inner, kept, high = interior[box], keep[box], height[box]
    count, labels = cv2.connectedComponents((inner & kept).astype(np.uint8), connectivity=4)
    if count <= 1:
        return []
    sizes = np.bincount(labels.ravel(), minlength=count)
    small = sizes < MIN_SEED
    small[0] = False
    labels[small[labels]] = 0
    sums = np.bincount(labels.ravel(), weights=high.ravel(), minlength=count)
    lowness = np.where(sizes > 0, -sums / np.maximum(sizes, 1), -np.inf)  # minus a seed's mean height
    lowness[0] = -np.inf
    # the lowest seed claims first: the band of a contact belongs to the lower object
    reach = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * GROW + 1, 2 * GROW + 1))
    for k in np.argsort(-lowness[1:], kind="stable") + 1:
        if sizes[k] == 0 or small[k]:
            continue
        claimed = cv2.dilate((labels == k).astype(np.uint8), reach).astype(bool) & kept & (labels == 0)
        labels[claimed] = k
    sizes = np.bincount(labels.ravel(), minlength=count)
    regions = []
    for k in np.nonzero(sizes >= MIN_PIXELS)[0]:
        if k == 0:
            continue
        region = np.zeros_like(keep)
        region[box] = labels == k
        regions.append(region)
    return regions


def _box(keep: np.ndarray) -> tuple[slice, slice] | None:
    rows, cols = np.nonzero(keep)
    if not len(rows):
        return None
    height, width = keep.shape
    top, left = max(rows.min() - MARGIN, 0), max(cols.min() - MARGIN, 0)
    bottom, right = min(rows.max() + MARGIN + 1, height), min(cols.max() + MARGIN + 1, width)
    return slice(top, bottom), slice(left, right)


class SeparatorRegions:
    """The ``instances`` design's region split of one frame: the separator's interior map on the
    foreground's bounding box, grown into regions (:func:`grow_regions`)."""

    def __init__(self, model: Separator, rule=None):
        from scenegen.perception.retrieval.regions import DepthRule

        self.model = model.eval()
        self.rule = rule or DepthRule()  # the foreground's options (frames come mended by the caller)

    def interior(
        self, rgb: np.ndarray, depth: np.ndarray, keep: np.ndarray, height: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) bool predicted interior of one frame, and its foreground: ``keep``, or where a
        separator with an object map (``outputs`` 2) calls a pixel of ``keep`` an object's; the
        interior lies inside it."""
        out = np.zeros_like(keep)
        box = _box(keep)
        if box is None:
            return out, keep
        x = separator_input(rgb[box], depth[box], keep[box], height[box], self.model.channels)
        with torch.no_grad():
            logits = self.model(torch.from_numpy(x)[None])[0].numpy()
        if self.model.outputs == 2:
            objects = np.zeros_like(keep)
            objects[box] = (logits[1] > OBJECT_LOGIT) & keep[box]
            keep = objects
        out[box] = (logits[0] > INTERIOR_LOGIT) & keep[box]
        return out, keep

    def __call__(self, rgb, depth, robot, camera) -> list[np.ndarray]:
        keep, height = self.rule.foreground(depth, robot, camera)
        interior, keep = self.interior(rgb, depth, keep, height)
        return grow_regions(interior, keep, height)


def _patch_corner(pool: np.ndarray, shape: tuple[int, int], rng: np.random.Generator) -> tuple[int, int]:
    """The top-left corner of a ``PATCH`` crop centred (as the frame's edges allow) on a pixel drawn
    from ``pool`` (N, 2) rows and columns."""
    height, width = shape
    r, c = pool[rng.integers(len(pool))] if len(pool) else (height // 2, width // 2)
    return int(np.clip(r - PATCH // 2, 0, height - PATCH)), int(np.clip(c - PATCH // 2, 0, width - PATCH))


def _pieces(mask: np.ndarray) -> list[np.ndarray]:
    """The 8-connected pieces of ``mask``, each (N, 2) rows and columns; one empty array for none."""
    import cv2

    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return [np.zeros((0, 2), np.int64)]
    rows, cols = np.nonzero(labels)
    owner = labels[rows, cols]
    order = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[order], np.arange(1, count + 1))
    both = np.stack([rows[order], cols[order]], 1)
    return [both[bounds[i] : bounds[i + 1]] for i in range(count - 1)]


def contact_groups(seg: np.ndarray, labels: np.ndarray) -> list[np.ndarray]:
    """A frame's boundary pixels, (N, 2) rows and columns, one group per instance they belong to
    (one per contact with what lies on it, as a rule)."""
    rows, cols = np.nonzero(labels == 0)
    owner = seg[rows, cols]
    return [np.stack([rows[owner == i], cols[owner == i]], 1) for i in np.unique(owner)]


def train_separator(
    inputs: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    weights: np.ndarray,
    contacts: Sequence[list[np.ndarray]],
    steps: int = SEPARATOR_STEPS,
    seed: int = 0,
    lr: float = 3e-3,
    width: int = 8,
    batch: int = 8,
    progress: bool = False,
    device: str = "cpu",
    objects: Sequence[np.ndarray] | None = None,
) -> tuple[Separator, dict]:
    """A :class:`Separator` trained on frames' ``inputs`` (each (C, H, W)) and ``labels``
    (each (H, W) int8, :func:`interior_labels`). Half of a batch's crops are centred on any
    foreground pixel of a frame drawn by its ``weights`` (its scene's weight in the mixture); the
    other half on a boundary pixel: a frame with contacts drawn by weight, one of its
    ``contacts`` (:func:`contact_groups`) with equal chance, a pixel of it (a knife's thin contact
    with a can counts as much as a box's long one with a plate). Crops of ``PATCH`` px, flipped at
    random, colours scaled (dim scenes are a rare case). ``objects``: per frame (H, W) int8 object
    labels of a learned foreground (1 an object's pixel, 0 the table's, -1 not scored; see
    :func:`separator_frames`): the model then has a second output, the object map, whose loss is
    added. Returns the model and a summary (losses, CPU-seconds); the model on the CPU, wherever it
    trained (``device``, scenegen/devices.py)."""
    from tqdm import tqdm

    from scenegen.devices import resolve_device

    on = resolve_device(device)
    torch.manual_seed(seed)
    started = time.process_time()
    rng = np.random.default_rng([seed, 43])
    model = Separator(width, len(inputs[0]), 1 if objects is None else 2).to(on)
    optimiser = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    p = np.asarray(weights, float) / np.sum(weights)
    if objects is None:
        anywhere = [[np.argwhere(y >= 0)] for y in labels]
    else:  # a learned foreground: each object piece with equal chance (a fork's 60 px as a box's 1,000)
        anywhere = [_pieces(o == 1) for o in objects]
    touching = np.array([bool(c) for c in contacts])
    q = np.where(touching, p, 0.0)
    q = q / q.sum() if q.sum() > 0 else p
    losses = []
    for step in tqdm(range(steps), desc="separator", disable=not progress):
        for group in optimiser.param_groups:
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        frames = rng.choice(len(inputs), size=batch, p=p)
        on_contact = rng.choice(len(inputs), size=batch, p=q)
        xs, ys, os_ = [], [], []
        for k in range(batch):
            f = on_contact[k] if k % 2 == 0 and contacts[on_contact[k]] else frames[k]
            groups = contacts[f]
            if k % 2 == 0 and groups:
                pool = groups[rng.integers(len(groups))]
            else:
                pieces = anywhere[f]
                pool = pieces[rng.integers(len(pieces))] if len(pieces) > 1 else pieces[0]
            r, c = _patch_corner(pool, labels[f].shape, rng)
            x = inputs[f][:, r : r + PATCH, c : c + PATCH]
            y = labels[f][r : r + PATCH, c : c + PATCH]
            o = None if objects is None else objects[f][r : r + PATCH, c : c + PATCH]
            if rng.random() < 0.5:
                x, y = x[:, :, ::-1], y[:, ::-1]
                o = None if o is None else o[:, ::-1]
            xs.append(np.ascontiguousarray(x, dtype=np.float32))
            ys.append(np.ascontiguousarray(y))
            if o is not None:
                os_.append(np.ascontiguousarray(o))
        x, y = torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys)).long()
        x[:, :3] = (
            x[:, :3] * torch.from_numpy(rng.uniform(0.35, 1.25, (batch, 1, 1, 1)).astype(np.float32))
        ).clamp(0, 1)
        x, y = x.to(on), y.to(on)
        weight = torch.where(y == 0, BOUNDARY_WEIGHT, 1.0) * (y >= 0)
        out = model(x)
        loss = (
            F.binary_cross_entropy_with_logits(out[:, 0], (y == 1).float(), reduction="none") * weight
        ).sum() / weight.sum().clamp(min=1.0)
        if objects is not None:  # the object map, over every scored pixel of the crops
            o = torch.from_numpy(np.stack(os_)).to(on)
            scored = torch.where(o == 1, OBJECT_WEIGHT, 1.0) * (o >= 0)
            loss = loss + (
                F.binary_cross_entropy_with_logits(out[:, 1], (o == 1).float(), reduction="none") * scored
            ).sum() / scored.sum().clamp(min=1.0)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(round(loss.item(), 6))
    summary = {"steps": steps, "losses": losses, "cpu_seconds": round(time.process_time() - started, 1)}
    return model.cpu().eval(), summary


def separator_frames(
    scenes, frames, channels: int = CHANNELS, rule=None
) -> tuple[list, list, list, list[int], list | None]:
    """The separator's training frames of ``scenes``: per camera frame its input (float16, see
    :func:`separator_input`), its labels (:func:`interior_labels`), its contacts
    (:func:`contact_groups`) and its scene's position; the
    robot's pixels and the instance ids come from the frames' segmentation (training only).
    ``rule``: the region step's ``regions.DepthRule`` (frames come mended by it). Under a
    ``learned`` rule also each frame's object labels (int8: 1 a pixel of an object or a piece of
    furniture, 0 the table's, -1 off the table or the robot's), else None; the interior labels
    then cover the objects' pixels."""
    from scenegen.perception.observation import BACKGROUND
    from scenegen.perception.retrieval.regions import DepthRule, robot_pixels

    rule = rule or DepthRule()
    inputs, labels, contacts, scene_of = [], [], [], []
    objects = [] if rule.learned else None
    for i, (scene, f) in enumerate(zip(scenes, frames, strict=True)):
        cameras = {c.name: c for c in scene.cameras}
        robot = robot_pixels(f, scene)
        background = [scene.segmentation[name] for name in BACKGROUND]
        for k, name in enumerate(f.cameras):
            keep, height = rule.foreground(f.depth[k], robot[k], cameras[name])
            inputs.append(separator_input(f.rgb[k], f.depth[k], keep, height, channels).astype(np.float16))
            if objects is not None:
                thing = keep & ~np.isin(f.seg[k], background)
                objects.append(np.where(keep, thing, -1).astype(np.int8))
                keep = thing
            labels.append(interior_labels(f.seg[k], keep, height))
            contacts.append(contact_groups(f.seg[k], labels[-1]))
            scene_of.append(i)
    return inputs, labels, contacts, scene_of, objects


def load_separator(folder, config: dict, remedy: str, rule=None) -> SeparatorRegions:
    """The region split of an ``instances`` checkpoint folder (its separator.safetensors), under
    ``rule`` (its ``regions.DepthRule``)."""
    from safetensors.torch import load_file

    from scenegen.core.files import checkpoint_error, int_field

    spec = config.get("separator")
    if not isinstance(spec, dict):
        raise checkpoint_error(Path(folder) / "config.json", ValueError("no 'separator' object"), remedy)
    channels = spec.get("channels", 7)  # saved before the contact channels: 7
    try:
        check_channels(channels)
    except ValueError as exc:
        raise checkpoint_error(Path(folder) / "config.json", exc, remedy) from None
    outputs = spec.get("outputs", 1)  # saved before learned foregrounds: 1
    if type(outputs) is not int or outputs not in (1, 2):
        problem = ValueError(f"separator outputs {outputs!r}: 1 or 2")
        raise checkpoint_error(Path(folder) / "config.json", problem, remedy)
    model = Separator(int_field(spec, "width", folder, 2, 64), channels, outputs)
    try:
        model.load_state_dict(load_file(str(Path(folder) / "separator.safetensors")))
    except Exception as exc:  # noqa: BLE001 - safetensors' own error type, shape mismatches, I/O
        raise checkpoint_error(Path(folder) / "separator.safetensors", exc, remedy) from None
    return SeparatorRegions(model, rule)
