"""Procedural proposer: domain randomization from explicit distributions.

The baseline every learned-generator figure is compared with. Per proposal: furniture jittered
around its home position, a target of the requested category plus random other objects, each on a
support (table, shelf top, bin floor) drawn by weight, on a resting pose drawn by its probability,
with uniform yaw and position; lights and cameras jittered. Objects are placed one by one with a
cheap footprint test (bounding circles on the same support, ``placement_attempts`` tries) so that
most proposals are not obvious overlaps; the verifier downstream decides what is kept.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from scenegen.assets.catalog import Asset, Catalog
from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME, footprint_radius, is_stack_base
from scenegen.core.placement import placed_at_rest, yaw_quat
from scenegen.propose.base import AssetChoice, proposal_rng, register_proposer
from scenegen.schema.condition import Condition
from scenegen.schema.scene import (
    Camera,
    FurniturePlacement,
    Light,
    Lighting,
    ObjectPlacement,
    SceneProposal,
)

DEFAULT_CAMERAS = (
    # The main camera (first): tags such as `occluded` are measured from it.
    Camera(name="front", position=(1.25, 0.0, 1.45), lookat=(0.0, 0.0, 0.85)),
    Camera(name="side", position=(0.15, -1.25, 1.35), lookat=(0.0, 0.0, 0.85)),
)


class LightingSettings(BaseModel):
    """Distributions of the lighting: uniform ranges (lo, hi)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    n_lights: tuple[int, int] = (1, 3)
    intensity: tuple[float, float] = (0.3, 0.9)
    ambient: tuple[float, float] = (0.05, 0.3)
    elevation_deg: tuple[float, float] = (35.0, 80.0)
    distance: tuple[float, float] = (1.5, 2.5)  # m from the table centre
    colour_jitter: float = 0.15  # warm/cool tint amplitude
    shadows: int = 1  # how many lights cast shadows (each costs render time)


class ProceduralSettings(AssetChoice):
    """Settings of the procedural proposer (``proposer.kind: procedural`` in a pipeline); ``assets``
    (:class:`~scenegen.propose.base.AssetChoice`): the only assets drawn, the target's included."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["procedural"] = "procedural"
    n_objects: tuple[int, int] = Field((3, 6), description="inclusive range of free objects, target included")
    furniture: tuple[Literal["shelf", "bin"], ...] = ("shelf", "bin")
    furniture_jitter: float = Field(0.02, ge=0.0, le=0.1)  # m
    categories: tuple[str, ...] | None = None  # categories of the other objects; None = all
    furniture_probability: dict[str, float] = Field(default_factory=dict)  # kind -> P(present); default 1
    # Where objects go: table, floor (the strip beside the table), a furniture piece by name (its
    # top or inside), under_shelf (on the table beneath the shelf board), or stack (on the flat top
    # of an object placed before it). target_support_weights replaces support_weights for the target.
    support_weights: dict[str, float] = Field(
        default_factory=lambda: {"table": 0.8, "shelf": 0.1, "bin": 0.1}
    )
    target_support_weights: dict[str, float] | None = None
    # Chance that an object stands on an upright resting pose of its asset (objects on real tables
    # mostly stand upright); None draws poses by their quasi-static drop probabilities instead.
    upright_probability: float | None = Field(None, ge=0.0, le=1.0)
    # Chance that the objects on the table are gathered around one point (a cluttered spot, normal
    # N(point, cluster_spread) per axis) instead of spread uniformly.
    cluster_probability: float = Field(0.0, ge=0.0, le=1.0)
    cluster_spread: float = Field(0.07, gt=0.0)
    edge_margin: float = Field(0.03, ge=0.0)  # min distance (m) from an object's centre to its surface's edge
    placement_attempts: int = Field(20, ge=1)
    lighting: LightingSettings = LightingSettings()
    camera_jitter: float = Field(0.03, ge=0.0, le=0.2)  # m, on position and look-at point
    cameras: tuple[Camera, ...] = DEFAULT_CAMERAS

    @field_validator("n_objects")
    @classmethod
    def _range(cls, v: tuple[int, int]) -> tuple[int, int]:
        if not 1 <= v[0] <= v[1] <= 12:
            raise ValueError(f"n_objects must be [min, max] with 1 <= min <= max <= 12, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _supports(self):
        valid = {
            "table",
            "floor",
            "stack",
            *self.furniture,
            *(["under_shelf"] if "shelf" in self.furniture else []),
        }
        for field_name in ("support_weights", "target_support_weights"):
            weights = getattr(self, field_name)
            if weights is None:
                continue
            for name, w in weights.items():
                if name not in valid:
                    raise ValueError(
                        f"{field_name}: unknown support {name!r}; valid: {', '.join(sorted(valid))}"
                    )
                if w < 0:
                    raise ValueError(f"{field_name}: weight of {name!r} must be >= 0")
            if weights.get("table", 0) <= 0:
                raise ValueError(f"{field_name}: 'table' needs a positive weight")
        for kind, p in self.furniture_probability.items():
            if kind not in self.furniture or not 0 <= p <= 1:
                raise ValueError(f"furniture_probability: {kind!r} must be one of furniture with 0 <= p <= 1")
        return self

    @field_validator("categories")
    @classmethod
    def _known_categories(cls, categories: tuple[str, ...] | None) -> tuple[str, ...] | None:
        from scenegen.assets.catalog import active_catalog

        valid = active_catalog().categories
        for c in categories or ():
            if c not in valid:
                raise ValueError(f"unknown category {c!r}; valid categories: {', '.join(valid)}")
        return categories


def sample_lighting(rng: np.random.Generator, s: LightingSettings) -> Lighting:
    lights = []
    for i in range(int(rng.integers(s.n_lights[0], s.n_lights[1] + 1))):
        elevation = math.radians(rng.uniform(*s.elevation_deg))
        azimuth = rng.uniform(-math.pi, math.pi)
        r = rng.uniform(*s.distance)
        pos = np.array(
            [
                r * math.cos(elevation) * math.cos(azimuth),
                r * math.cos(elevation) * math.sin(azimuth),
                layout.TABLE_TOP_Z + r * math.sin(elevation),
            ]
        )
        aim = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), layout.TABLE_TOP_Z])
        direction = (aim - pos) / np.linalg.norm(aim - pos)
        tint = rng.uniform(-s.colour_jitter, s.colour_jitter)  # > 0 warm, < 0 cool
        colour = np.clip([1.0 + tint, 1.0, 1.0 - tint], 0.0, 1.0)
        lights.append(
            Light(
                position=_r(pos),
                direction=_r(direction),
                colour=_r(colour),
                intensity=round(float(rng.uniform(*s.intensity)), 4),
                cast_shadow=i < s.shadows,
            )
        )
    ambient = round(float(rng.uniform(*s.ambient)), 4)
    return Lighting(lights=tuple(lights), ambient=(ambient, ambient, ambient))


def jitter_cameras(rng: np.random.Generator, cameras: Sequence[Camera], amount: float) -> tuple[Camera, ...]:
    return tuple(
        cam.model_copy(
            update={
                "position": _r(np.add(cam.position, rng.uniform(-amount, amount, 3))),
                "lookat": _r(np.add(cam.lookat, rng.uniform(-amount, amount, 3))),
            }
        )
        for cam in cameras
    )


def _r(v) -> tuple[float, ...]:
    return tuple(round(float(x), 6) for x in v)


@register_proposer("procedural")
class ProceduralProposer:
    """Domain randomization behind the proposer interface."""

    def __init__(self, settings: ProceduralSettings, catalog: Catalog):
        self.settings = settings
        self.catalog = catalog
        pool = settings.categories or catalog.categories
        self.allowed = tuple(
            a for a in catalog.assets if settings.assets is None or a.name in settings.assets
        )
        self.others = tuple(a for a in self.allowed if a.category in pool)

    def describe(self) -> dict:
        return {"kind": self.kind, "settings": self.settings.model_dump(mode="json")}

    def propose(self, condition: Condition, indices: Sequence[int], seed: int) -> list[SceneProposal]:
        return [self._one(condition, i, seed) for i in indices]

    def _one(self, condition: Condition, index: int, seed: int) -> SceneProposal:
        s = self.settings
        rng = proposal_rng(seed, index)
        furniture = []
        for kind in s.furniture:
            present = rng.uniform() < s.furniture_probability.get(kind, 1.0)
            jitter = rng.uniform(-s.furniture_jitter, s.furniture_jitter, 2)
            if present:
                position = (*_r(np.add(FURNITURE_HOME[kind], jitter)), 0.0)
                furniture.append(FurniturePlacement(name=kind, kind=kind, position=position))
        furniture = tuple(furniture)
        surfaces = layout.support_surfaces(furniture)
        keep_out = [
            box
            for piece in furniture
            for box in layout.furniture_boxes(piece)
            if box[0][2] - box[2][2] < layout.TABLE_TOP_Z + 1e-3
        ]
        n = int(rng.integers(s.n_objects[0], s.n_objects[1] + 1))
        target_slot = int(rng.integers(n))
        table = surfaces["table"]
        cluster = rng.uniform(-0.6, 0.6, 2) * table.half if rng.uniform() < s.cluster_probability else None
        target_kinds = tuple(a for a in self.allowed if a.category == condition.target)
        placed: list[ObjectPlacement] = []
        footprints: list[tuple[str, np.ndarray, float]] = []
        for slot in range(n):
            is_target = slot == target_slot
            pool = target_kinds if is_target else self.others
            asset = pool[int(rng.integers(len(pool)))]
            pose = _draw_pose(rng, asset, s.upright_probability)
            radius = footprint_radius(asset, pose)
            weights = (s.target_support_weights if is_target else None) or s.support_weights
            support = _draw_support(rng, weights, surfaces)
            if support == "stack":
                bases = [
                    o for o in placed if is_stack_base(self.catalog.get(o.asset)) and o.support != "floor"
                ]
                base = bases[int(rng.integers(len(bases)))] if bases else None
                support = base.name if base else "table"
                if base is not None:
                    surfaces[base.name] = layout.object_top_surface(self.catalog, base)
            under_shelf = support == "under_shelf"
            if under_shelf:
                # On the table, within the shelf's footprint: the table region under its board.
                shelf = surfaces["shelf"]
                surface = layout.Surface("table", layout.TABLE_TOP_Z, shelf.center, shelf.half, shelf.yaw)
                support = "table"
            else:
                surface = surfaces[support]
            # On the table an object may overhang the edge (near-edge cases); on furniture its whole
            # footprint stays inside (bin walls, shelf board); on another object its centre stays on
            # the inner half of the top.
            if support == "table":
                margin = np.full(2, s.edge_margin)
            elif support in {o.name for o in placed}:
                margin = np.asarray(surface.half) / 2
            else:
                margin = np.full(2, max(s.edge_margin, radius))
            for _ in range(s.placement_attempts):
                if support == "table" and cluster is not None and not under_shelf:
                    limit = np.maximum(np.asarray(surface.half) - margin, 0.0)
                    local = np.clip(rng.normal(cluster, s.cluster_spread), -limit, limit)
                else:
                    local = rng.uniform(-1, 1, 2) * np.maximum(np.asarray(surface.half) - margin, 0.0)
                c, sn = math.cos(surface.yaw), math.sin(surface.yaw)
                xy = np.asarray(surface.center) + [
                    c * local[0] - sn * local[1],
                    sn * local[0] + c * local[1],
                ]
                free = all(
                    sup != support or np.linalg.norm(xy - other) >= radius + r for sup, other, r in footprints
                ) and (support != "table" or not any(_inside(xy, box, radius) for box in keep_out))
                if free:
                    break
            yaw = rng.uniform(-math.pi, math.pi)
            raw_quat = _quat_mul_yaw(yaw, asset.resting_poses[pose].quat)
            raw_position = (*xy, surface.z + asset.resting_poses[pose].height)
            footprints.append((support, xy, radius))
            placed.append(
                placed_at_rest(f"obj{slot}_{asset.name}", asset, raw_position, raw_quat, surface, support)
            )
        return SceneProposal(
            index=index,
            seed=seed,
            condition=condition,
            target=placed[target_slot].name,
            objects=tuple(placed),
            furniture=furniture,
            lighting=sample_lighting(rng, s.lighting),
            cameras=jitter_cameras(rng, s.cameras, s.camera_jitter),
        )


def _draw_pose(rng: np.random.Generator, asset: Asset, upright_probability: float | None) -> int:
    """A resting pose index: by drop probability, or upright with ``upright_probability``."""
    probs = np.array([p.probability for p in asset.resting_poses])
    if upright_probability is not None:
        upright = np.array([p.upright for p in asset.resting_poses])
        if upright.any() and (~upright).any():
            upright_draw = rng.uniform() < upright_probability
            probs = np.where(upright == upright_draw, probs, 0.0)
    return int(rng.choice(len(probs), p=probs / probs.sum()))


def _draw_support(rng: np.random.Generator, weights: dict[str, float], surfaces: dict) -> str:
    """A support name drawn by weight among those present in this scene (plus ``stack`` and, with a
    shelf, ``under_shelf``)."""
    present = {*surfaces, "stack", *(["under_shelf"] if "shelf" in surfaces else [])}
    names = [n for n in sorted(weights) if weights[n] > 0 and n in present]
    p = np.array([weights[n] for n in names])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _inside(xy: np.ndarray, box: tuple[np.ndarray, np.ndarray, np.ndarray], radius: float) -> bool:
    """Whether a circle at ``xy`` overlaps the footprint of a world box (centre, rotation, half sizes)."""
    center, rot, half = box
    local = rot[:2, :2].T @ (xy - center[:2])
    return bool(np.all(np.abs(local) < half[:2] + radius))


def _quat_mul_yaw(yaw: float, quat: Sequence[float]) -> np.ndarray:
    from scenegen.core.placement import quat_mul

    return quat_mul(yaw_quat(yaw), np.asarray(quat, float))
