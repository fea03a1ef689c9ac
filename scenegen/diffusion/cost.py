"""Differentiable scene costs for cost guidance, computed on (predicted clean) token tensors.

Soft versions of what the checks and predicates decide, in metres, so that their gradient can bend a
sample toward a valid scene that holds the request. Discrete fields enter as probabilities (presence
by a sigmoid, asset, resting pose and support by a softmax), objects as discs whose radius is the
geometric mean of the footprint's half extents in that pose (the ellipse in its bounding box: a
plate's radius, a lying knife's 3 cm rather than its 10 cm half length; real overlaps left after
decoding are pushed apart by propose/separate.py).

- ``penetration``: sum over pairs of present objects at about the same height, neither stacked on
  another, of the overlap of their discs;
- ``table_bounds``: how far the disc of an object on the table leaves the table top;
- ``robot_clearance``: overlap of the discs with a keep-out disc around the robot's base column;
- ``reach`` (when the shoulder position is given): how far the flagged target's centre lies outside
  the arm's envelope, 3 cm inside the reachability check's [0.25, 0.95] m around the shoulder
  (weighted by the probability that the target is not on the floor, which is exempt);
- soft required predicates, each on the slot the sample flags as target: ``near_edge`` (disc
  beyond 3 cm from the nearest side edge), ``clutter`` (missing neighbours within 0.2 m),
  ``on_floor`` (probability that its support is not the floor), ``stacked`` (that it is not stacked),
  ``toppled`` (that its resting pose is upright), ``under_overhang`` (that no shelf is present, or
  that its centre is not under the shelf's board, or that it rests on the shelf), ``low_light``
  (ambient + unshadowed direct light on an upward surface at the target above 0.22, an upper bound of
  the predicate's irradiance, which also counts shadows). ``occluded`` has no soft version.

Presence is each slot's own sign; decoding also caps the objects at the scene token's count, which
the terms ignore (a slot beyond the count still pushes and counts as a neighbour).

Every term is >= 0 and 0 on scenes that satisfy it; :meth:`SceneCost.__call__` returns their
weighted sum per sample.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME, footprint_half_extents
from scenegen.diffusion.encoding import (
    AMBIENT_CENTRE,
    AMBIENT_SCALE,
    FURNITURE_KINDS,
    FURNITURE_SCALE,
    INTENSITY_CENTRE,
    INTENSITY_SCALE,
    LIGHT_SCALE,
    LIGHT_WIDTH,
    SUPPORTS,
    TINT_SCALE,
    XY_SCALE,
    SceneEncoding,
)

ROBOT_BASE_XY = (-0.56, 0.0)
ROBOT_KEEP_OUT = 0.2  # m around the base column
SHARPNESS = 8.0  # presence logits are +-1; sigmoid(8 x) is ~0 or ~1 away from 0
REACH, REACH_MARGIN = (0.25, 0.95), 0.03  # m: CheckSettings.reach_min / reach_max, and a margin
LOW_LIGHT_BOUND = 0.22  # soft low_light aims below the predicate's 0.25, for the shadows it ignores
SPOT_CUTOFF, SPOT_EXPONENT = math.radians(45.0), 10.0  # MuJoCo's light defaults, which world uses


def disc_radius(asset, pose: int) -> float:
    """sqrt(a b) (m) for the half extents a, b of the asset's footprint box in resting pose ``pose``."""
    return float(np.sqrt(np.prod(footprint_half_extents(asset, pose))))


class SceneCost:
    """Callable (objects (B, slots, W), scene (B, S)) -> cost (B,) for one request."""

    def __init__(
        self,
        encoding: SceneEncoding,
        required: tuple[str, ...] = (),
        weights: dict[str, float] | None = None,
        shoulder: tuple[float, float, float] | None = None,
    ):
        self.encoding = encoding
        # per asset a and pose column c: the disc radius, whether the pose is upright, and whether
        # the asset lacks a pose in that column (decoding never picks it)
        shape = (len(encoding.assets), encoding.max_poses)
        radii, upright, lacks = torch.zeros(shape), torch.zeros(shape), torch.ones(shape, dtype=torch.bool)
        for a, name in enumerate(encoding.assets):
            asset = encoding.catalog.get(name)
            for c, p in enumerate(encoding.pose_order[name]):
                radii[a, c] = disc_radius(asset, p)
                upright[a, c] = float(asset.resting_poses[p].upright)
                lacks[a, c] = False
        self.radii, self.upright, self.lacks = radii, upright, lacks
        self.required = tuple(required)
        self.shoulder = None if shoulder is None else torch.tensor(shoulder, dtype=torch.float32)
        self.weights = {
            "penetration": 1.0,
            "table_bounds": 1.0,
            "robot_clearance": 1.0,
            "reach": 1.0,
            **(weights or {}),
        }

    def terms(self, objects: torch.Tensor, scene: torch.Tensor) -> dict[str, torch.Tensor]:
        e = self.encoding
        present = torch.sigmoid(SHARPNESS * objects[..., 0])  # (B, K)
        asset_p = torch.softmax(SHARPNESS * objects[..., e.asset_cols], dim=-1)
        logits = (SHARPNESS * objects[..., e.pose_cols])[:, :, None]  # (B, K, 1, P)
        pose_p = torch.softmax(logits.masked_fill(self.lacks, -torch.inf), dim=-1)  # (B, K, A, P)
        radius = torch.einsum("bka,ap,bkap->bk", asset_p, self.radii, pose_p)  # expected disc radius
        support_p = torch.softmax(SHARPNESS * objects[..., e.support_cols], dim=-1)
        on_table = support_p[..., SUPPORTS.index("table")]
        xyz = objects[..., e.xyz_cols] * XY_SCALE
        xy, z = xyz[..., :2], xyz[..., 2]
        target_p = torch.softmax(SHARPNESS * objects[..., e.target_col], dim=-1)  # which slot is the target

        diff = xy[:, :, None] - xy[:, None]
        dist = (diff.pow(2).sum(-1) + 1e-9).sqrt()
        same_level = torch.exp(-((z[:, :, None] - z[:, None]) / 0.05).pow(2))
        # a stacked object overlaps its base's footprint by design: pairs with one are left out
        loose = present * (1 - support_p[..., SUPPORTS.index("stacked")])
        pair = loose[:, :, None] * loose[:, None] * same_level
        pair = pair * (1 - torch.eye(e.slots))  # no self pairs
        overlap = torch.relu(radius[:, :, None] + radius[:, None] - dist)
        terms = {"penetration": 0.5 * (pair * overlap).sum((1, 2))}

        half = torch.tensor(layout.TABLE_SIZE[:2]) / 2
        outside = torch.relu(xy.abs() + radius[..., None] - half).sum(-1)
        terms["table_bounds"] = (present * on_table * outside).sum(1)

        base = torch.tensor(ROBOT_BASE_XY)
        to_base = ((xy - base).pow(2).sum(-1) + 1e-9).sqrt()
        terms["robot_clearance"] = (present * torch.relu(ROBOT_KEEP_OUT + radius - to_base)).sum(1)

        if self.shoulder is not None:
            point = torch.cat([xy, (z + layout.TABLE_TOP_Z)[..., None]], -1)
            r = ((point - self.shoulder).pow(2).sum(-1) + 1e-9).sqrt()
            outside = torch.relu(r - (REACH[1] - REACH_MARGIN)) + torch.relu(REACH[0] + REACH_MARGIN - r)
            not_floor = 1 - support_p[..., SUPPORTS.index("floor")]
            terms["reach"] = (target_p * not_floor * outside).sum(1)

        if "near_edge" in self.required:
            edge = torch.minimum(half[1] - xy[..., 1].abs(), half[0] - xy[..., 0].abs()) - radius
            terms["near_edge"] = (target_p * torch.relu(edge - 0.03)).sum(1)
        if "clutter" in self.required:
            near = torch.sigmoid((0.2 - dist) / 0.02) * present[:, None] * (1 - torch.eye(e.slots))
            neighbours = (near * target_p[:, :, None]).sum((1, 2))
            terms["clutter"] = torch.relu(3.0 - neighbours) * 0.1
        if "on_floor" in self.required:
            off_floor = 1 - support_p[..., SUPPORTS.index("floor")]
            terms["on_floor"] = (target_p * off_floor).sum(1) * 0.1
        if "stacked" in self.required:
            not_stacked = 1 - support_p[..., SUPPORTS.index("stacked")]
            terms["stacked"] = (target_p * not_stacked).sum(1) * 0.1
        if "toppled" in self.required:
            upright = torch.einsum("bka,ap,bkap->bk", asset_p, self.upright, pose_p)
            terms["toppled"] = (target_p * upright).sum(1) * 0.1
        if "under_overhang" in self.required:
            terms["under_overhang"] = self._under_overhang(scene, xy, radius, support_p, target_p) * 0.1
        if "low_light" in self.required:
            terms["low_light"] = torch.relu(self._light_bound(scene, xy, z, target_p) - LOW_LIGHT_BOUND)
        return terms

    def _under_overhang(self, scene, xy, radius, support_p, target_p) -> torch.Tensor:
        """1 - P(shelf present) x P(target centre under its board, a disc radius inside its legs)
        x P(target not on the shelf), for the flagged target."""
        i = FURNITURE_KINDS.index("shelf")
        present = torch.sigmoid(SHARPNESS * scene[:, 3 * i])
        home = torch.tensor(FURNITURE_HOME["shelf"])
        centre = home + scene[:, 3 * i + 1 : 3 * i + 3] * FURNITURE_SCALE  # (B, 2)
        half = torch.tensor(layout.FURNITURE["shelf"].surface_half) - torch.tensor([0.0, 0.02])
        inside = (half - radius[..., None] * torch.tensor([0.0, 1.0]) - (xy - centre[:, None]).abs()) / 0.01
        under = torch.sigmoid(inside).prod(-1)  # (B, K)
        below = 1 - support_p[..., SUPPORTS.index("shelf")]
        return 1 - present * (target_p * under * below).sum(1)

    def _light_bound(self, scene, xy, z, target_p) -> torch.Tensor:
        """Ambient + sum of unshadowed direct light on an upward surface at the flagged target (the
        predicate's formula without its shadow rays: an upper bound of what it measures)."""
        base = 3 * len(FURNITURE_KINDS)
        irradiance = scene[:, base] * AMBIENT_SCALE + AMBIENT_CENTRE
        point = torch.cat([(target_p[..., None] * xy).sum(1), (target_p * z).sum(1, keepdim=True)], -1)
        point = point + torch.tensor([0.0, 0.0, layout.TABLE_TOP_Z])
        for i in range(self.encoding.light_slots):
            v = scene[:, base + 1 + LIGHT_WIDTH * i : base + 1 + LIGHT_WIDTH * (i + 1)]
            present = torch.sigmoid(SHARPNESS * v[:, 0])
            pos = torch.stack([v[:, 1] * LIGHT_SCALE, v[:, 2] * LIGHT_SCALE, v[:, 3] * LIGHT_SCALE], -1)
            pos = pos + torch.tensor([0.0, 0.0, layout.TABLE_TOP_Z])
            aim = torch.stack(
                [v[:, 4] * XY_SCALE, v[:, 5] * XY_SCALE, torch.full_like(v[:, 4], layout.TABLE_TOP_Z)], -1
            )
            axis = torch.nn.functional.normalize(aim - pos, dim=-1)
            to_light = torch.nn.functional.normalize(pos - point, dim=-1)
            cos_spot = (-to_light * axis).sum(-1)
            inside = torch.sigmoid((cos_spot - math.cos(SPOT_CUTOFF)) / 0.01)
            falloff = torch.relu(cos_spot) ** SPOT_EXPONENT
            tint = v[:, 6] * TINT_SCALE
            colour = ((1 + tint).clamp(0, 1) + 1 + (1 - tint).clamp(0, 1)) / 3
            intensity = (v[:, 7] * INTENSITY_SCALE + INTENSITY_CENTRE).clamp(0, 3)
            incidence = torch.relu(to_light[:, 2])
            irradiance = irradiance + present * colour * intensity * inside * falloff * incidence
        return irradiance

    def __call__(self, objects: torch.Tensor, scene: torch.Tensor) -> torch.Tensor:
        terms = self.terms(objects, scene)
        return sum(self.weights.get(name, 1.0) * value for name, value in terms.items())
