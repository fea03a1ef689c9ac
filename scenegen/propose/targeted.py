"""Hand-targeted proposer: procedural scenes with the target moved to where a requested tag is likely.

The second baseline of the rare-case work: what a researcher would write by hand to get, say, a mug
at the table edge. Each proposal starts as a procedural scene (same settings, same randomness) and
then, for every tag the request requires, one hand-written rule edits it:

============== ==================================================================================
near_edge      target on the table, its footprint ``edge_distance`` from a side edge, within reach
under_overhang a shelf is present; the target stands on the table under the near half of its board
toppled        the target lies on a non-upright resting pose of its asset
occluded       a tall occluder stands between the target and the main camera
clutter        ``clutter_count`` other objects are moved (or added) within ``clutter_radius``
stacked        the target rests on top of a flat-topped base object
low_light      the lights are redrawn from ``dim_lighting``
on_floor       the target lies on the floor strip beside the table
============== ==================================================================================

Objects whose footprints the edits run into are dropped. Nothing here guarantees the tag: the
pipeline's checks, settling and predicates decide, exactly as for every other proposer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from scenegen.assets.catalog import Asset, Catalog
from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME, footprint_radius
from scenegen.core.placement import placed_at_rest, quat_mul, yaw_quat
from scenegen.core.rotations import quat_to_matrix
from scenegen.propose.base import non_upright, register_proposer
from scenegen.propose.procedural import (
    LightingSettings,
    ProceduralProposer,
    ProceduralSettings,
    sample_lighting,
)
from scenegen.schema.condition import Condition
from scenegen.schema.scene import FurniturePlacement, ObjectPlacement, SceneProposal

# Order in which the rules are applied when a request requires several tags: first where the target
# goes, then how it lies, then what surrounds it.
RULE_ORDER = (
    "on_floor",
    "under_overhang",
    "stacked",
    "near_edge",
    "toppled",
    "clutter",
    "occluded",
    "low_light",
)
# Edges the target may be pushed to (the back edge, -x, is the robot's side).
EDGE_NORMALS = {"front": (1.0, 0.0), "left": (0.0, 1.0), "right": (0.0, -1.0)}


class TargetedSettings(ProceduralSettings):
    """Settings of the hand-targeted proposer (``proposer.kind: targeted``): every procedural setting
    (for the scene it starts from) plus the parameters of the rules."""

    kind: Literal["targeted"] = "targeted"  # type: ignore[assignment]
    edge_distance: tuple[float, float] = (-0.01, 0.02)  # m, target footprint to the edge (< 0 overhangs)
    # Which edges, and where along them (m, x for a side edge, y for the front edge): by default the
    # side edges within the arm's reach (the front edge, x = 0.4, is beyond it).
    edges: tuple[Literal["front", "left", "right"], ...] = ("left", "right")
    edge_along: tuple[float, float] = (-0.3, 0.1)
    occluders: tuple[str, ...] = ("cereal_box",)  # assets stood upright between target and camera
    occluder_gap: tuple[float, float] = (0.005, 0.03)  # m between target and occluder footprints
    clutter_count: int = Field(4, ge=1)  # objects gathered around the target
    clutter_radius: float = Field(0.16, gt=0.0)  # m, their centres within this of the target's
    stack_bases: tuple[str, ...] = ("small_box", "soup_can", "cereal_box", "plate")
    dim_lighting: LightingSettings = LightingSettings(
        n_lights=(1, 2), intensity=(0.03, 0.12), ambient=(0.02, 0.08)
    )

    @field_validator("occluders", "stack_bases")
    @classmethod
    def _known_assets(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        from scenegen.assets.catalog import active_catalog

        valid = [a.name for a in active_catalog().assets]
        for name in names:
            if name not in valid:
                raise ValueError(f"unknown asset {name!r}; valid assets: {', '.join(valid)}")
        if not names:
            raise ValueError("needs at least one asset")
        return names


class _Scene:
    """A proposal being edited: its objects by name, furniture and lighting."""

    def __init__(self, proposal: SceneProposal):
        self.objects = {o.name: o for o in proposal.objects}
        self.furniture = list(proposal.furniture)
        self.lighting = proposal.lighting
        self.target = proposal.target
        self.protected = {proposal.target}  # objects a rule placed; others make way for them

    def new_name(self, asset: str) -> str:
        return f"obj{len(self.objects)}_{asset}"


@register_proposer("targeted")
class TargetedProposer:
    """Procedural scenes, edited by one hand-written rule per required tag."""

    def __init__(self, settings: TargetedSettings, catalog: Catalog):
        self.settings = settings
        self.catalog = catalog
        self.procedural = ProceduralProposer(settings, catalog)

    def describe(self) -> dict:
        return {"kind": self.kind, "settings": self.settings.model_dump(mode="json")}

    def propose(self, condition: Condition, indices: Sequence[int], seed: int) -> list[SceneProposal]:
        return [self._one(condition, i, seed) for i in indices]

    def _one(self, condition: Condition, index: int, seed: int) -> SceneProposal:
        base = self.procedural.propose(condition, [index], seed)[0]
        if not condition.required():
            return base
        rng = np.random.default_rng(np.random.SeedSequence([seed, index, 2]))  # the rules' own stream
        scene = _Scene(base)
        required = set(condition.required())
        for tag in RULE_ORDER:
            if tag in required:
                getattr(self, f"_{tag}")(scene, rng)
        self._make_way(scene)
        return base.model_copy(
            update={
                "objects": tuple(scene.objects.values()),
                "furniture": tuple(scene.furniture),
                "lighting": scene.lighting,
            }
        )

    # ------------------------------------------------------------------------------- the rules

    def _on_floor(self, scene: _Scene, rng: np.random.Generator) -> None:
        self._place(scene, scene.target, layout.FLOOR, rng)

    def _under_overhang(self, scene: _Scene, rng: np.random.Generator) -> None:
        shelf = next((f for f in scene.furniture if f.kind == "shelf"), None)
        if shelf is None:
            shelf = FurniturePlacement(name="shelf", kind="shelf", position=(*FURNITURE_HOME["shelf"], 0.0))
            scene.furniture.append(shelf)
        # The half of the region under the board nearer the robot (the far half is mostly out of reach).
        board = layout.support_surfaces([shelf])["shelf"]
        wall = layout.FURNITURE["shelf"].boxes[0].half[1] * 2
        c, s = math.cos(board.yaw), math.sin(board.yaw)
        back = np.asarray(board.center) - board.half[0] / 2 * np.array([c, s])
        under = layout.Surface(
            "table", layout.TABLE_TOP_Z, tuple(back), (board.half[0] / 2, board.half[1] - wall), board.yaw
        )
        self._place(scene, scene.target, under, rng, margin="radius")

    def _stacked(self, scene: _Scene, rng: np.random.Generator) -> None:
        name = self.settings.stack_bases[int(rng.integers(len(self.settings.stack_bases)))]
        asset = self.catalog.get(name)
        upright = [i for i, p in enumerate(asset.resting_poses) if p.upright]
        # A box lies flat (its widest top); other bases stand upright.
        pose = max(range(len(asset.resting_poses)), key=lambda i: asset.resting_poses[i].probability)
        pose = pose if layout.is_box_like(asset) or not upright else upright[0]
        base = self._add(scene, asset, pose, self._table(), rng, margin="radius")
        top = layout.object_top_surface(self.catalog, base)
        inner = layout.Surface(base.name, top.z, top.center, tuple(h / 2 for h in top.half), top.yaw)
        self._place(scene, scene.target, inner, rng, support=base.name)

    def _near_edge(self, scene: _Scene, rng: np.random.Generator) -> None:
        edge = self.settings.edges[int(rng.integers(len(self.settings.edges)))]
        normal = np.array(EDGE_NORMALS[edge])
        target = scene.objects[scene.target]
        asset = self.catalog.get(target.asset)
        yaw = rng.uniform(-math.pi, math.pi)
        quat = quat_mul(yaw_quat(yaw), np.asarray(asset.resting_poses[target.resting_pose].quat))
        reach = _extent_along(asset, quat, normal)  # centre to footprint boundary along the normal
        half = np.array(layout.TABLE_SIZE[:2]) / 2
        depth = float(np.abs(normal) @ half) - reach - rng.uniform(*self.settings.edge_distance)
        along = np.abs([normal[1], normal[0]])
        xy = normal * depth + along * rng.uniform(*self.settings.edge_along)
        self._set(scene, scene.target, asset, target.resting_pose, xy, quat, self._table(), "table")

    def _toppled(self, scene: _Scene, rng: np.random.Generator) -> None:
        target = scene.objects[scene.target]
        asset = self.catalog.get(target.asset)
        if not non_upright(asset):
            allowed = [a for a in self.procedural.allowed if a.category == target.category and non_upright(a)]
            options = allowed or [a for a in self.catalog.of_category(target.category) if non_upright(a)]
            asset = options[int(rng.integers(len(options)))]
        poses = non_upright(asset)
        pose = poses[int(rng.integers(len(poses)))]
        quat = quat_mul(yaw_quat(rng.uniform(-math.pi, math.pi)), np.asarray(asset.resting_poses[pose].quat))
        surface = self._surface_of(scene, target)
        self._set(scene, scene.target, asset, pose, target.position[:2], quat, surface, target.support)

    def _clutter(self, scene: _Scene, rng: np.random.Generator) -> None:
        s = self.settings
        target = scene.objects[scene.target]
        centre = np.asarray(target.position[:2])
        surface = self._surface_of(scene, target)
        if target.support != "table":
            surface = self._table()
        others = [o for o in scene.objects.values() if o.name not in scene.protected and o.support == "table"]
        while len(others) < s.clutter_count:
            pool = self.procedural.others
            asset = pool[int(rng.integers(len(pool)))]
            pose = _upright_or_likeliest(asset)
            others.append(self._add(scene, asset, pose, surface, rng, near=(centre, s.clutter_radius)))
            scene.protected.discard(others[-1].name)
        for obj in others[: s.clutter_count]:
            asset = self.catalog.get(obj.asset)
            scene.objects[obj.name] = self._placement(
                scene, asset, obj.resting_pose, surface, rng, near=(centre, s.clutter_radius), name=obj.name
            )
            scene.protected.add(obj.name)

    def _occluded(self, scene: _Scene, rng: np.random.Generator) -> None:
        s = self.settings
        target = scene.objects[scene.target]
        camera = np.asarray(self.procedural.settings.cameras[0].position[:2])
        t_xy = np.asarray(target.position[:2])
        toward = (camera - t_xy) / np.linalg.norm(camera - t_xy)
        asset = self.catalog.get(s.occluders[int(rng.integers(len(s.occluders)))])
        pose = _upright_or_likeliest(asset)
        # Broad side to the camera: the asset's long footprint axis across the line of sight.
        yaw = math.atan2(toward[1], toward[0]) + math.pi / 2
        quat = quat_mul(yaw_quat(yaw), np.asarray(asset.resting_poses[pose].quat))
        t_asset = self.catalog.get(target.asset)
        gap = _extent_along(t_asset, target.quat, toward) + _extent_along(asset, quat, -toward)
        xy = t_xy + toward * (gap + rng.uniform(*s.occluder_gap))
        name = scene.new_name(asset.name)
        self._set(scene, name, asset, pose, xy, quat, self._surface_of(scene, target), target.support)
        scene.protected.add(name)

    def _low_light(self, scene: _Scene, rng: np.random.Generator) -> None:
        scene.lighting = sample_lighting(rng, self.settings.dim_lighting)

    # ----------------------------------------------------------------------------- placement

    def _table(self) -> layout.Surface:
        return layout.support_surfaces(())["table"]

    def _surface_of(self, scene: _Scene, obj: ObjectPlacement) -> layout.Surface:
        if obj.support in scene.objects:
            return layout.object_top_surface(self.catalog, scene.objects[obj.support])
        return layout.support_surfaces(scene.furniture)[obj.support]

    def _place(
        self,
        scene: _Scene,
        name: str,
        surface: layout.Surface,
        rng: np.random.Generator,
        margin: str = "fixed",
        support: str | None = None,
    ) -> None:
        """Move object ``name`` (same asset and pose, new yaw) to a free spot of ``surface``."""
        obj = scene.objects[name]
        asset = self.catalog.get(obj.asset)
        scene.objects[name] = self._placement(
            scene, asset, obj.resting_pose, surface, rng, margin=margin, name=name, support=support
        )

    def _add(self, scene: _Scene, asset: Asset, pose: int, surface, rng, **kwargs) -> ObjectPlacement:
        name = scene.new_name(asset.name)
        scene.objects[name] = self._placement(scene, asset, pose, surface, rng, name=name, **kwargs)
        scene.protected.add(name)
        return scene.objects[name]

    def _placement(
        self,
        scene: _Scene,
        asset: Asset,
        pose: int,
        surface: layout.Surface,
        rng: np.random.Generator,
        *,
        name: str,
        margin: str = "fixed",
        near: tuple[np.ndarray, float] | None = None,
        support: str | None = None,
    ) -> ObjectPlacement:
        """A placement of ``asset`` on ``surface`` clear of the protected objects' footprints (best of
        ``placement_attempts`` random spots), inside ``near`` = (centre, radius) when given."""
        radius = footprint_radius(asset, pose)
        pad = radius if margin == "radius" else min(radius, self.settings.edge_margin)
        limit = np.maximum(np.asarray(surface.half) - pad, 0.0)
        keep = [
            (np.asarray(o.position[:2]), footprint_radius(self.catalog.get(o.asset), o.resting_pose))
            for n, o in scene.objects.items()
            if n in scene.protected and n != name
        ]
        best, best_gap = None, -math.inf
        for _ in range(self.settings.placement_attempts):
            if near is not None:
                angle, r = rng.uniform(-math.pi, math.pi), near[1] * math.sqrt(rng.uniform(0.15, 1.0))
                xy = near[0] + r * np.array([math.cos(angle), math.sin(angle)])
                local = np.clip(surface.local_xy(xy), -limit, limit)
            else:
                local = rng.uniform(-1, 1, 2) * limit
            c, s = math.cos(surface.yaw), math.sin(surface.yaw)
            xy = np.asarray(surface.center) + [c * local[0] - s * local[1], s * local[0] + c * local[1]]
            gap = min((np.linalg.norm(xy - p) - radius - r for p, r in keep), default=math.inf)
            if gap > best_gap:
                best, best_gap = xy, gap
            if gap >= 0:
                break
        quat = quat_mul(yaw_quat(rng.uniform(-math.pi, math.pi)), np.asarray(asset.resting_poses[pose].quat))
        return self._make(name, asset, pose, best, quat, surface, support or surface.name)

    def _set(self, scene, name, asset, pose, xy, quat, surface, support) -> None:
        scene.objects[name] = self._make(name, asset, pose, xy, quat, surface, support)

    def _make(self, name, asset, pose, xy, quat, surface, support) -> ObjectPlacement:
        raw = (float(xy[0]), float(xy[1]), surface.z + asset.resting_poses[pose].height)
        return placed_at_rest(name, asset, raw, quat, surface, support)

    def _make_way(self, scene: _Scene) -> None:
        """Drop unprotected objects whose footprint overlaps a protected (placed by a rule) one at about
        the same height; then, repeatedly, objects whose support is gone or was moved by a rule."""
        protected = [scene.objects[n] for n in scene.protected]
        holding = set()  # what a protected object stands on, all the way down: it stays too
        below = [o.support for o in protected]
        while below:
            support = below.pop()
            if support in scene.objects and support not in holding:
                holding.add(support)
                below.append(scene.objects[support].support)
        for name, obj in list(scene.objects.items()):
            if name in scene.protected or name in holding:
                continue
            radius = footprint_radius(self.catalog.get(obj.asset), obj.resting_pose)
            for other in protected:
                r = footprint_radius(self.catalog.get(other.asset), other.resting_pose)
                close = np.linalg.norm(np.subtract(obj.position[:2], other.position[:2])) < radius + r
                if close and abs(obj.position[2] - other.position[2]) < 0.15:
                    del scene.objects[name]
                    break
        changed = True
        while changed:
            known = {*scene.objects, *layout.support_surfaces(scene.furniture)}
            gone = [
                n
                for n, o in scene.objects.items()
                if o.support not in known or (n not in scene.protected and o.support in scene.protected)
            ]
            changed = bool(gone)
            for n in gone:
                del scene.objects[n]


def _extent_along(asset: Asset, quat: Sequence[float], direction: np.ndarray) -> float:
    """How far (m) the asset's bounding box reaches from its centre along a horizontal direction."""
    half = np.asarray(asset.extents) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    rotated = corners @ quat_to_matrix(quat).T
    return float((rotated[:, :2] @ np.asarray(direction, float)).max())


def _upright_or_likeliest(asset: Asset) -> int:
    upright = [i for i, p in enumerate(asset.resting_poses) if p.upright]
    if upright:
        return upright[0]
    return int(np.argmax([p.probability for p in asset.resting_poses]))
