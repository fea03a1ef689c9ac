"""Differentiable scene costs for cost guidance, computed on (predicted clean) token tensors.

Soft versions of what the checks and predicates decide, in metres, so that their gradient can bend a
sample toward a valid scene that holds the request. Discrete fields enter as probabilities (presence
by a sigmoid, asset and support by a softmax), objects as bounding circles of their footprint.

- ``penetration``: sum over pairs of present objects at about the same height of the overlap of
  their footprint circles;
- ``table_bounds``: how far the footprint of an object on the table leaves the table top;
- ``robot_clearance``: overlap of footprints with a keep-out disc around the robot's base column;
- soft required predicates: ``near_edge`` (target footprint beyond 3 cm from the nearest side edge),
  ``clutter`` (missing neighbours within 0.2 m), ``on_floor`` (probability mass of the target's
  support not on the floor).

Every term is >= 0 and 0 on scenes that satisfy it; :meth:`SceneCost.__call__` returns their
weighted sum per sample.
"""

from __future__ import annotations

import torch

from scenegen import world
from scenegen.diffusion.encoding import SUPPORTS, XY_SCALE, SceneEncoding
from scenegen.propose.procedural import footprint_radius

ROBOT_BASE_XY = (-0.56, 0.0)
ROBOT_KEEP_OUT = 0.2  # m around the base column
SHARPNESS = 8.0  # presence logits are +-1; sigmoid(8 x) is ~0 or ~1 away from 0


class SceneCost:
    """Callable (objects (B, slots, W), scene (B, S)) -> cost (B,) for one request."""

    def __init__(
        self,
        encoding: SceneEncoding,
        required: tuple[str, ...] = (),
        weights: dict[str, float] | None = None,
    ):
        self.encoding = encoding
        radii = []
        for name in encoding.assets:
            asset = encoding.catalog.get(name)
            radii.append(max(footprint_radius(asset, p) for p in range(len(asset.resting_poses))))
        self.radii = torch.tensor(radii, dtype=torch.float32)
        self.required = tuple(required)
        self.weights = {"penetration": 1.0, "table_bounds": 1.0, "robot_clearance": 1.0, **(weights or {})}

    def terms(self, objects: torch.Tensor, scene: torch.Tensor) -> dict[str, torch.Tensor]:
        e = self.encoding
        present = torch.sigmoid(SHARPNESS * objects[..., 0])  # (B, K)
        asset_p = torch.softmax(SHARPNESS * objects[..., e.asset_cols], dim=-1)
        radius = asset_p @ self.radii  # (B, K) expected footprint radius
        support_p = torch.softmax(SHARPNESS * objects[..., e.support_cols], dim=-1)
        on_table = support_p[..., SUPPORTS.index("table")]
        xyz = objects[..., e.xyz_cols] * XY_SCALE
        xy, z = xyz[..., :2], xyz[..., 2]
        target_p = torch.softmax(SHARPNESS * objects[..., e.target_col], dim=-1)  # which slot is the target

        diff = xy[:, :, None] - xy[:, None]
        dist = (diff.pow(2).sum(-1) + 1e-9).sqrt()
        same_level = torch.exp(-((z[:, :, None] - z[:, None]) / 0.05).pow(2))
        pair = present[:, :, None] * present[:, None] * same_level
        pair = pair * (1 - torch.eye(e.slots))  # no self pairs
        overlap = torch.relu(radius[:, :, None] + radius[:, None] - dist)
        terms = {"penetration": 0.5 * (pair * overlap).sum((1, 2))}

        half = torch.tensor(world.TABLE_SIZE[:2]) / 2
        outside = torch.relu(xy.abs() + radius[..., None] - half).sum(-1)
        terms["table_bounds"] = (present * on_table * outside).sum(1)

        base = torch.tensor(ROBOT_BASE_XY)
        to_base = ((xy - base).pow(2).sum(-1) + 1e-9).sqrt()
        terms["robot_clearance"] = (present * torch.relu(ROBOT_KEEP_OUT + radius - to_base)).sum(1)

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
        return terms

    def __call__(self, objects: torch.Tensor, scene: torch.Tensor) -> torch.Tensor:
        terms = self.terms(objects, scene)
        return sum(self.weights.get(name, 1.0) * value for name, value in terms.items())
