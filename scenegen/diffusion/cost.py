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
  the predicate's irradiance, which also counts shadows), ``occluded`` (a line-of-sight proxy, below);
- ``arm_clearance`` (when the arm's geoms are given): overlap of an object's disc, where it stands as
  high as a geom's lowest point, with the geom's disc widened by the check's 3 cm clearance: the
  robot_clearance check's own geometry (check/geometry.py ``robot_geometry``), flattened to discs.

Soft occluded: the main camera sees the target's centre along one ray. Another object blocks part of
it where its centre lies between the two in the table plane, its top rises above the ray there and
its disc covers part of the target's width across the ray (the overlap of the two discs' intervals
across the line of sight, over the target's diameter); the shelf's board blocks it where the ray
crosses the board's plane inside the board. Hidden = 1 - prod(1 - blocked), and 0 for a target off
the table; the term, 0.3 x (0.7 - hidden) where positive, asks for at least 0.7 hidden (the
predicate: half of the visible side's sample points). Its edges are soft (5 cm along the line of
sight, 2 cm across it and in height) so that the gradient reaches objects not yet near the line; on
the reference layouts it is 0 for 39 % of those where the target is occluded and for 0.1 % of the
others (2,000 layouts). "retrieve the spoon occluded", 64 proposals: 9 accepted without the term,
14 with hard 1 cm edges, 20 with the soft ones.

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
from scenegen.core.layout import FURNITURE_HOME, footprint_half_extents, pose_top
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
REACH, REACH_MARGIN = layout.REACH, 0.03  # m: the arm's envelope (CheckSettings' defaults), a margin
LOW_LIGHT_BOUND = 0.22  # soft low_light aims below the predicate's 0.25, for the shadows it ignores
SPOT_CUTOFF, SPOT_EXPONENT = math.radians(45.0), 10.0  # MuJoCo's light defaults, which world uses
OCCLUDED_AIM = 0.7  # soft occluded asks for this share hidden (the predicate: 0.5 of sample points)
# The occluded term's weight within the request's: at 1 its gradient threw objects off the table
# (out_of_workspace 16 of 64 proposals of "retrieve the mug toppled occluded low_light"); accepted
# 5 / 11 / 14 / 13 / 10 of 64 at 0 / 0.1 / 0.3 / 0.5 / 1 (hard 1 cm edges; measured here)
OCCLUDED_SCALE = 0.3
SIGHT_SOFT = 0.05  # m: the soft edge of "between the target and the camera"
ARM_CLEARANCE = 0.03  # m: CheckSettings.robot_clearance


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
        camera: tuple[float, float, float] | None = None,
        arm: np.ndarray | None = None,
        aim_lights: bool = False,
    ):
        """``camera``: the main camera's position (m), for soft ``occluded``; ``arm`` (G, 4): the
        arm's collision geoms at the request's pose as discs (x, y, lowest z, radius; m), for
        ``arm_clearance``; ``aim_lights``: soft ``low_light`` moves where the lights point and stand,
        not how bright they and the ambient are (their gradient stopped), as the reference darkens a
        target (``proposer.light_projection: aim``)."""
        self.encoding = encoding
        self.aim_lights = aim_lights
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
        tops = torch.zeros(shape)  # top above the object's origin (m) in each pose
        for a, name in enumerate(encoding.assets):
            asset = encoding.catalog.get(name)
            for c, p in enumerate(encoding.pose_order[name]):
                tops[a, c] = pose_top(asset, p)
        self.radii, self.upright, self.lacks, self.tops = radii, upright, lacks, tops
        self.camera = None if camera is None else torch.tensor(camera, dtype=torch.float32)
        self.arm = None if arm is None else torch.tensor(np.asarray(arm), dtype=torch.float32)
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
        occluded = "occluded" in self.required and self.camera is not None
        if occluded or self.arm is not None:  # the expected top above each object's origin
            top = torch.einsum("bka,ap,bkap->bk", asset_p, self.tops, pose_p)
        if occluded:
            hidden = self._hidden(scene, present, xy, z, radius, top)  # (B, K): as if slot k were the target
            terms["occluded"] = (target_p * torch.relu(OCCLUDED_AIM - hidden)).sum(1) * OCCLUDED_SCALE
        if self.arm is not None:
            terms["arm_clearance"] = self._arm_overlap(present, xy, z, radius, top)
        return terms

    def _hidden(self, scene, present, xy, z, radius, top) -> torch.Tensor:
        """Soft share (B, K) of slot k's width hidden from the main camera by the other slots' objects
        and the shelf's board (module docstring)."""
        k = self.encoding.slots
        cam_xy, cam_z = self.camera[:2], self.camera[2] - layout.TABLE_TOP_Z  # heights above the table
        xy_t, z_t = xy, z
        sight = cam_xy - xy_t  # (B, K, 2) from each candidate target to the camera
        reach = (sight.pow(2).sum(-1) + 1e-9).sqrt()
        d = sight / reach[..., None]
        rel = xy[:, None] - xy_t[:, :, None]  # (B, K target, K other, 2)
        along = (rel * d[:, :, None]).sum(-1)
        across = (rel[..., 0] * d[:, :, None, 1] - rel[..., 1] * d[:, :, None, 0]).abs()
        # Wide soft edges (5 cm, 2 cm): the gradient must reach an object that is not yet near the line
        # of sight (with 1 cm edges, guided samples ended with nothing near it, the term at its top)
        between = torch.sigmoid(along / SIGHT_SOFT) * torch.sigmoid((reach[:, :, None] - along) / SIGHT_SOFT)
        # only an occluder on the table counts: otherwise the gradient finds the line of sight beyond
        # the table's front edge, towards the camera (out_of_workspace)
        front = layout.TABLE_SIZE[0] / 2 - radius - xy[..., 0]
        between = between * torch.sigmoid(front / 0.01)[:, None]
        ray = z_t[:, :, None] + (cam_z - z_t[:, :, None]) * along / reach[:, :, None]
        tall = torch.sigmoid((z[:, None] + top[:, None] - ray) / 0.02)
        r_t, r_o = radius[:, :, None], radius[:, None]
        overlap = torch.minimum(across + r_o, r_t) - torch.maximum(across - r_o, -r_t)
        cover = torch.nn.functional.softplus(overlap / 0.02) * 0.02 / (2 * r_t)
        blocked = present[:, None] * between * tall * cover.clamp(max=1.0) * (1 - torch.eye(k))
        visible = (1 - blocked).prod(-1)
        i = FURNITURE_KINDS.index("shelf")
        shelf = layout.FURNITURE["shelf"]
        board = shelf.surface_height - 0.02  # the board's underside above the table
        centre = torch.tensor(FURNITURE_HOME["shelf"]) + scene[:, 3 * i + 1 : 3 * i + 3] * FURNITURE_SCALE
        level = ((board - z_t) / (cam_z - z_t).clamp(min=1e-3)).clamp(0.0, 1.0)  # where the ray meets it
        crossing = xy_t + level[..., None] * sight - centre[:, None]
        inside = torch.sigmoid((torch.tensor(shelf.surface_half) - crossing.abs()) / 0.01).prod(-1)
        under = torch.sigmoid((board - z_t) / 0.01) * torch.sigmoid(SHARPNESS * scene[:, 3 * i])[:, None]
        # A target off the table is not hidden: otherwise the gradient found it a long line of sight
        # off the table (x = -1.1 m or 1.45 m: out_of_workspace, measured) instead of occluders.
        half = torch.tensor(layout.TABLE_SIZE[:2]) / 2
        on_table = torch.sigmoid((half - xy.abs() - radius[..., None]) / 0.05).prod(-1)
        return on_table * (1 - visible * (1 - under * inside))

    def _arm_overlap(self, present, xy, z, radius, top) -> torch.Tensor:
        """Sum over objects and arm geoms of how far (m) an object's disc reaches into a geom's disc
        widened by the clearance, where the object rises above the geom's lowest point."""
        gx, gy, low, r = self.arm.T
        dist = ((xy[..., None, :] - torch.stack([gx, gy], -1)).pow(2).sum(-1) + 1e-9).sqrt()  # (B, K, G)
        rises = torch.sigmoid((z[..., None] + top[..., None] + layout.TABLE_TOP_Z - low) / 0.01)
        overlap = torch.relu(radius[..., None] + r + ARM_CLEARANCE - dist)
        return (present[..., None] * rises * overlap).sum((1, 2))

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
        strength = scene.detach() if self.aim_lights else scene  # brightness held, aim and place free
        irradiance = strength[:, base] * AMBIENT_SCALE + AMBIENT_CENTRE
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
            held = strength[:, base + 1 + LIGHT_WIDTH * i : base + 1 + LIGHT_WIDTH * (i + 1)]
            intensity = (held[:, 7] * INTENSITY_SCALE + INTENSITY_CENTRE).clamp(0, 3)
            incidence = torch.relu(to_light[:, 2])
            irradiance = irradiance + present * colour * intensity * inside * falloff * incidence
        return irradiance

    def __call__(self, objects: torch.Tensor, scene: torch.Tensor) -> torch.Tensor:
        terms = self.terms(objects, scene)
        return sum(self.weights.get(name, 1.0) * value for name, value in terms.items())
