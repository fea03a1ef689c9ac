"""Scene <-> tensor: the fixed-size representation the diffusion model denoises.

A scene is ``SLOTS`` object tokens plus one scene token, every entry scaled to about [-1, 1]:

object token (``object_width``; an empty slot is all -1 with ``present`` -1):
    present (+1/-1), asset one-hot (catalog order, +1/-1), resting-pose one-hot (``max_poses``; the
    asset's upright poses first, see :attr:`SceneEncoding.pose_order`), support one-hot
    (``SUPPORTS``), x, y and height above the table top, each / 0.5 m, cos and sin of the yaw about
    the resting pose, target flag (+1 for the target, -1 otherwise)
scene token (``scene_width``):
    per furniture kind: present, dx / 0.05 m and dy / 0.05 m from its home position;
    ambient ((a - 0.15) / 0.15); per light slot (``LIGHT_SLOTS``): present, position / 2.5 m
    (x, y, and z above the table top), aim point on the table / 0.5 m (x, y), tint / 0.2,
    (intensity - 0.6) / 0.6, casts shadow; the number of objects (one-hot over 1..``SLOTS``)

Decoding keeps the ``count`` slots with the highest presence, ``count`` the argmax of the scene
token's object-count one-hot, but no slot whose presence is <= 0 (an empty slot decodes to garbage:
all -1, at x = y = -0.5 m) unless none is present, then the most present one. Training with the count
one-hot calibrated the presences themselves (six-object scenes 12.5 % of null samples, 7 % before;
data 15 %); see docs/generator.md.

Decoding snaps every object onto a stable resting pose of its asset at its support's height
(objects on the table, floor and furniture first, then stacked ones onto the inner half of the top
of the nearest base within ``STACK_SNAP``, as the procedural sampler stacks them; a table object
whose centre is inside the bin's walls goes into the bin, and an object in the bin or on the shelf
moves in until its footprint circle is inside, centred along an axis where it does not fit: the
procedural sampler's rule) and reports how far
that moved its centre (``projection_distance``): the decoded height against the height the support
and resting pose dictate, and the horizontal move onto a base or into the furniture. Encoding the
settled layout of a stored or reference scene takes each object's nearest resting pose to its settled
orientation.
Pure numpy; no MuJoCo, no torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from scenegen.assets.catalog import Asset, Catalog
from scenegen.core import layout
from scenegen.core.layout import FURNITURE_HOME, footprint_radius, is_stack_base
from scenegen.core.placement import placed_at_rest, quat_mul, snap_to_rest, yaw_quat
from scenegen.schema.condition import Condition
from scenegen.schema.scene import (
    Camera,
    FurniturePlacement,
    Light,
    Lighting,
    ObjectPlacement,
    SceneProposal,
)

ENCODING_VERSION = 2  # 2: object-count one-hot in the scene token, upright resting poses first
SLOTS = 8
LIGHT_SLOTS = 3
SUPPORTS = ("table", "floor", "shelf", "bin", "stacked")
FURNITURE_KINDS = tuple(sorted(FURNITURE_HOME))
UPRIGHT_SUPPORTS = ("floor", "shelf", "bin")  # where ``upright_off_table`` decodes upright poses
XY_SCALE = 0.5  # m
FURNITURE_SCALE = 0.05  # m of jitter around the home position
LIGHT_SCALE = 2.5  # m
AMBIENT_CENTRE, AMBIENT_SCALE = 0.15, 0.15
TINT_SCALE = 0.2
INTENSITY_CENTRE, INTENSITY_SCALE = 0.6, 0.6
LIGHT_WIDTH = 9
# m: an object decoded as stacked moves onto the nearest base's top within this. The model marks about
# as many targets stacked as the data (3.3 % against 2.3 %) but misplaces them: within 10 cm 0.7 % of
# null samples keep a stacked target, within 30 cm 1.9 % (median move 17 cm; data 2.4 %)
STACK_SNAP = 0.30


def _onto(surface: layout.Surface, xy: np.ndarray, half: Sequence[float]) -> np.ndarray:
    """``xy`` moved (in the surface's yaw frame) into the centred region of half extents ``half``;
    unchanged when already there."""
    local = np.clip(surface.local_xy(xy), -np.asarray(half), np.asarray(half))
    c, s = math.cos(surface.yaw), math.sin(surface.yaw)
    return np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]]) + surface.center


def _decoded_slot(name: str) -> int | None:
    """The slot an object name of :meth:`SceneEncoding.decode` (``obj<slot>_<asset>``) names, or None."""
    head, _, rest = name.partition("_")
    return int(head[3:]) if head.startswith("obj") and head[3:].isdigit() and rest else None


def _onehot(index: int, n: int) -> np.ndarray:
    v = -np.ones(n)
    v[index] = 1.0
    return v


def _yaw_of(quat: Sequence[float], rest: Sequence[float]) -> float:
    """Yaw (rad) of the world z rotation that best carries resting pose ``rest`` onto ``quat``."""
    rel = quat_mul(np.asarray(quat, float), np.asarray(rest, float) * np.array([1, -1, -1, -1]))
    return 2.0 * math.atan2(rel[3], rel[0])


Substitute = Callable[[Asset, int, int], "tuple[Asset, int] | None"]


def matched_pose(asset: Asset, pose: int, other: Asset) -> int:
    """The resting pose of ``other`` that matches ``asset``'s ``pose``: of those as upright as it (all
    when none is), the one whose height over the tallest pose's is nearest its own."""
    rel = asset.resting_poses[pose].height / max(p.height for p in asset.resting_poses)
    top = max(p.height for p in other.resting_poses)
    same = [i for i, p in enumerate(other.resting_poses) if p.upright == asset.resting_poses[pose].upright]
    return min(
        same or range(len(other.resting_poses)), key=lambda i: abs(other.resting_poses[i].height / top - rel)
    )


@dataclass(frozen=True)
class Decoded:
    """A decoded scene: the proposal, and the projection distance (m) of each object."""

    proposal: SceneProposal
    projection: tuple[float, ...]


class SceneEncoding:
    """The map between layouts and (object tokens (SLOTS, object_width), scene token (scene_width))."""

    def __init__(
        self,
        catalog: Catalog,
        slots: int = SLOTS,
        light_slots: int = LIGHT_SLOTS,
        assets: Sequence[str] | None = None,
    ):
        """``assets``: the assets of the asset one-hot, in order (a checkpoint's; default every asset
        of ``catalog``, which may hold more: decoding can place those through ``substitute``)."""
        self.catalog = catalog
        self.slots = slots
        self.light_slots = light_slots
        self.assets = tuple(assets) if assets is not None else tuple(a.name for a in catalog.assets)
        known = [catalog.get(name) for name in self.assets]
        self.max_poses = max(len(a.resting_poses) for a in known)
        # pose_order[asset][column] = resting-pose index: upright poses first, so that a column means
        # "upright" for most assets (a sample whose asset changes late in denoising stays upright)
        self.pose_order = {
            a.name: tuple(
                sorted(range(len(a.resting_poses)), key=lambda p: (not a.resting_poses[p].upright, p))
            )
            for a in known
        }
        n_assets = len(self.assets)
        # Column offsets of an object token.
        self.asset_cols = slice(1, 1 + n_assets)
        self.pose_cols = slice(self.asset_cols.stop, self.asset_cols.stop + self.max_poses)
        self.support_cols = slice(self.pose_cols.stop, self.pose_cols.stop + len(SUPPORTS))
        self.xyz_cols = slice(self.support_cols.stop, self.support_cols.stop + 3)
        self.yaw_cols = slice(self.xyz_cols.stop, self.xyz_cols.stop + 2)
        self.target_col = self.yaw_cols.stop
        self.object_width = self.target_col + 1
        start = 3 * len(FURNITURE_KINDS) + 1 + LIGHT_WIDTH * light_slots
        self.light_cols = slice(3 * len(FURNITURE_KINDS), start)  # the ambient level and the light slots
        self.count_cols = slice(start, start + slots)
        self.scene_width = self.count_cols.stop

    # ------------------------------------------------------------------------------ encode

    def encode_row(self, row: dict) -> tuple[np.ndarray, np.ndarray]:
        """Tokens of one layout in the shape of a reference Parquet row (``reference.layout_row``)."""
        objects = row["objects"]
        if len(objects) > self.slots:
            raise ValueError(
                f"layout {row.get('index')}: {len(objects)} objects, more than {self.slots} slots"
            )
        tokens = -np.ones((self.slots, self.object_width))
        names = [o["name"] for o in objects]
        for slot, o in enumerate(objects):
            asset = self.catalog.get(o["asset"])
            surface_kind = o["support"] if o["support"] not in names else "stacked"
            table = layout.support_surfaces(())["table"]
            pose = snap_to_rest(asset, o["position"], o["quat"], table)[2]
            yaw = _yaw_of(o["quat"], asset.resting_poses[pose].quat)
            token = tokens[slot]
            token[0] = 1.0
            token[self.asset_cols] = _onehot(self.assets.index(asset.name), len(self.assets))
            token[self.pose_cols] = _onehot(self.pose_order[asset.name].index(pose), self.max_poses)
            token[self.support_cols] = _onehot(SUPPORTS.index(surface_kind), len(SUPPORTS))
            x, y, z = o["position"]
            token[self.xyz_cols] = (x / XY_SCALE, y / XY_SCALE, (z - layout.TABLE_TOP_Z) / XY_SCALE)
            token[self.yaw_cols] = (math.cos(yaw), math.sin(yaw))
            token[self.target_col] = 1.0 if o["name"] == row["target"] else -1.0
        return tokens, self._scene_token(row)

    def encode_proposal(self, proposal: SceneProposal) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
        """Tokens of a proposal's layout, and the slot of each object by name: an object named as
        decoding names it (``obj<slot>_<asset>``) keeps that slot, so a repaired scene's objects keep
        their names; others fill the free slots in order. Layouts the encoding cannot hold (more
        objects than slots, an asset the checkpoint does not know) raise ValueError."""
        wanted = [_decoded_slot(o.name) for o in proposal.objects]
        taken = {s for s in wanted if s is not None and s < self.slots}
        free = iter(s for s in range(self.slots) if s not in taken)
        slot_of, seen = {}, set()
        for obj, slot in zip(proposal.objects, wanted, strict=True):
            if slot is None or slot >= self.slots or slot in seen:
                slot = next(free, None)
                if slot is None:
                    raise ValueError(f"proposal {proposal.index}: more objects than {self.slots} slots")
            seen.add(slot)
            slot_of[obj.name] = slot
        for obj in proposal.objects:
            if obj.asset not in self.assets:
                raise ValueError(f"proposal {proposal.index}: {obj.asset} is not an asset of this encoding")
        row = {
            "index": proposal.index,
            "target": proposal.target,
            "objects": [
                {
                    "name": o.name,
                    "asset": o.asset,
                    "support": o.support,
                    "position": o.position,
                    "quat": o.quat,
                }
                for o in sorted(proposal.objects, key=lambda o: slot_of[o.name])
            ],
            "furniture": [
                {"kind": f.kind, "x": f.position[0], "y": f.position[1]} for f in proposal.furniture
            ],
            "ambient": float(np.mean(proposal.lighting.ambient)),
            "lights": [light.model_dump() for light in proposal.lighting.lights],
        }
        tokens, scene = self.encode_row(row)
        placed = -np.ones_like(tokens)
        for k, obj in enumerate(row["objects"]):
            placed[slot_of[obj["name"]]] = tokens[k]
        return placed, scene, slot_of

    def regenerate_masks(
        self, slot_of: dict[str, int], parts: Sequence[str]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Boolean masks (slots, object_width), (scene_width): True where a repair re-samples
        ``parts`` (object names of ``slot_of``, ``furniture``, ``lights``). An object keeps its
        presence and target flag (the scene keeps its objects and its target), everything else of
        its token is re-sampled; ``furniture``: the furniture's presence and offsets; ``lights``:
        the ambient level and the light slots."""
        objects = np.zeros((self.slots, self.object_width), bool)
        scene = np.zeros(self.scene_width, bool)
        for part in parts:
            if part == "furniture":
                scene[: self.light_cols.start] = True
            elif part == "lights":
                scene[self.light_cols] = True
            else:
                objects[slot_of[part], 1 : self.target_col] = True
        return objects, scene

    def _scene_token(self, row: dict) -> np.ndarray:
        out = []
        present = {f["kind"]: f for f in row["furniture"]}
        for kind in FURNITURE_KINDS:
            f = present.get(kind)
            if f is None:
                out += [-1.0, 0.0, 0.0]
            else:
                home = FURNITURE_HOME[kind]
                out += [1.0, (f["x"] - home[0]) / FURNITURE_SCALE, (f["y"] - home[1]) / FURNITURE_SCALE]
        out.append((row["ambient"] - AMBIENT_CENTRE) / AMBIENT_SCALE)
        lights = row["lights"][: self.light_slots]
        for i in range(self.light_slots):
            if i >= len(lights):
                out += [-1.0] + [0.0] * (LIGHT_WIDTH - 1)
                continue
            light = lights[i]
            pos = np.asarray(light["position"], float)
            direction = np.asarray(light["direction"], float)
            # Where the spot's axis meets the table top: the aim point.
            t = (layout.TABLE_TOP_Z - pos[2]) / direction[2] if direction[2] < -1e-6 else 0.0
            aim = pos + t * direction
            colour = light["colour"]
            out += [
                1.0,
                pos[0] / LIGHT_SCALE,
                pos[1] / LIGHT_SCALE,
                (pos[2] - layout.TABLE_TOP_Z) / LIGHT_SCALE,
                aim[0] / XY_SCALE,
                aim[1] / XY_SCALE,
                (colour[0] - colour[2]) / TINT_SCALE,  # colour = clip([1 + tint, 1, 1 - tint], 0, 1)
                (light["intensity"] - INTENSITY_CENTRE) / INTENSITY_SCALE,
                1.0 if light["cast_shadow"] else -1.0,
            ]
        if not row["objects"]:
            raise ValueError(f"layout {row.get('index')}: no objects; a scene holds at least one")
        out += list(_onehot(len(row["objects"]) - 1, self.slots))
        return np.asarray(out, float)

    # ------------------------------------------------------------------------------ decode

    def decode(
        self,
        tokens: np.ndarray,
        scene: np.ndarray,
        condition: Condition,
        cameras: Sequence[Camera],
        index: int = 0,
        seed: int = 0,
        own_target: bool = False,
        substitute: Substitute | None = None,
        upright_off_table: bool = False,
    ) -> Decoded:
        """A proposal from (possibly noisy) tokens: discrete fields by argmax, objects snapped onto a
        resting pose at their support's height, the target an object of ``condition.target``'s
        category (see :meth:`_target`). The scene has the most present slots' objects (module docstring).

        ``own_target``: the target is the slot the sample flags most, whatever its category, and the
        proposal's condition names that category (for samples of the null condition).

        ``substitute(asset, pose, slot)``: the asset and resting pose to place for a slot decoded as
        ``asset`` in ``pose`` (a user asset of the same category, say), or None to leave the slot out
        (never the target's); called in placement order, before snapping.

        ``upright_off_table``: an object on the floor, the shelf or in the bin (a table object inside
        its walls too) takes its best-scoring upright resting pose, as the procedural sampler places
        the reference layouts (none of their shelf or bin objects and 2 % of their floor objects rest
        otherwise, the shipped model's 26 %, 13 % and 29 %); a target whose request requires it
        toppled keeps its pose."""
        tokens, scene = np.asarray(tokens, float), np.asarray(scene, float)
        furniture = self._furniture(scene)
        surfaces = layout.support_surfaces(furniture)
        count = int(np.argmax(scene[self.count_cols])) + 1
        count = min(count, max(1, int(np.sum(tokens[:, 0] > 0))))  # never an empty slot's -1 token
        present = sorted(np.argsort(-tokens[:, 0], kind="stable")[:count].tolist())
        support_of = {s: SUPPORTS[int(np.argmax(tokens[s, self.support_cols]))] for s in present}
        for s, kind in support_of.items():
            if kind in FURNITURE_KINDS and kind not in surfaces:
                support_of[s] = "table"  # furniture that is absent cannot hold anything
        order = sorted(present, key=lambda s: (support_of[s] == "stacked", s))
        target, asset_of = self._target(tokens, present, None if own_target else condition.target)
        toppled = condition.tags.get("toppled") == "required"
        placed: dict[int, ObjectPlacement] = {}
        projection: dict[int, float] = {}
        for s in order:
            token = tokens[s]
            asset = self.catalog.get(asset_of[s])
            columns = self.pose_order[asset.name]
            xyz = token[self.xyz_cols] * XY_SCALE + [0.0, 0.0, layout.TABLE_TOP_Z]
            xy = xyz[:2]
            support = support_of[s]
            in_bin = support == "table" and "bin" in surfaces and surfaces["bin"].margin(xy) > 0
            scores = token[self.pose_cols][: len(columns)]
            pose = columns[int(np.argmax(scores))]
            off_table = support in UPRIGHT_SUPPORTS or in_bin
            if upright_off_table and off_table and not (s == target and toppled):
                upright = [k for k, c in enumerate(columns) if asset.resting_poses[c].upright]
                pose = columns[max(upright, key=lambda k: scores[k])] if upright else pose
            if substitute is not None:
                swapped = substitute(asset, pose, s)
                if swapped is None and s != target:
                    continue
                asset, pose = swapped or (asset, pose)
            yaw = math.atan2(token[self.yaw_cols][1], token[self.yaw_cols][0])
            surface = surfaces.get(support, surfaces["table"])
            xy_on = xy
            if support == "stacked":
                base = self._base_under(xy, placed.values())
                if base is None:
                    support, surface = "table", surfaces["table"]
                else:  # onto the inner half of the base's top, as the procedural sampler stacks
                    support, surface = base[0].name, base[1]
                    xy_on = _onto(surface, xy, np.asarray(surface.half) / 2)
            if support == "table" and "bin" in surfaces and surfaces["bin"].margin(xy) > 0:
                support, surface = "bin", surfaces["bin"]  # inside the bin's walls: in the bin
            if support in FURNITURE_KINDS:  # footprint inside the bin's walls or on the shelf's board
                radius = footprint_radius(asset, pose)
                xy_on = _onto(surface, xy, np.maximum(np.asarray(surface.half) - radius, 0.0))
            moved = float(np.hypot(*(xy_on - xy)))
            xyz = np.array([xy_on[0], xy_on[1], xyz[2]])
            quat = quat_mul(yaw_quat(yaw), np.asarray(asset.resting_poses[pose].quat))
            placed[s] = placed_at_rest(f"obj{s}_{asset.name}", asset, xyz, quat, surface, support)
            if moved:  # the snap is vertical, the move onto a base or into the furniture horizontal
                total = round(math.hypot(placed[s].projection_distance, moved), 6)
                placed[s] = placed[s].model_copy(update={"projection_distance": total})
            projection[s] = placed[s].projection_distance
        if own_target:
            category = self.catalog.get(asset_of[target]).category
            condition = condition.model_copy(update={"target": category, "text": None})
        proposal = SceneProposal(
            index=index,
            seed=seed,
            condition=condition,
            target=placed[target].name,
            objects=tuple(placed[s] for s in sorted(placed)),
            furniture=furniture,
            lighting=self._lighting(scene),
            cameras=tuple(cameras),
        )
        return Decoded(proposal, tuple(projection[s] for s in sorted(placed)))

    def _target(
        self, tokens: np.ndarray, present: list[int], category: str | None
    ) -> tuple[int, dict[int, str]]:
        """The target slot and every present slot's asset (argmax). The target is the slot with the
        highest target flag among those holding an asset of the requested category; if none does, the
        highest-flag slot becomes the best-scoring asset of that category. ``category`` None: the
        highest-flag slot, as it is."""
        asset_of = {s: self.assets[int(np.argmax(tokens[s, self.asset_cols]))] for s in present}
        if category is None:
            return max(present, key=lambda s: tokens[s, self.target_col]), asset_of
        in_category = [s for s in present if self.catalog.get(asset_of[s]).category == category]
        target = max(in_category or present, key=lambda s: tokens[s, self.target_col])
        if not in_category:
            allowed = [i for i, name in enumerate(self.assets) if self.catalog.get(name).category == category]
            scores = tokens[target, self.asset_cols]
            asset_of[target] = self.assets[max(allowed, key=lambda i: scores[i])]
        return target, asset_of

    def _base_under(self, xy: np.ndarray, placed) -> tuple[ObjectPlacement, layout.Surface] | None:
        """The base for an object decoded as stacked at ``xy``, among the placed objects that may
        carry another (``layout.is_stack_base``, not on the floor, as the procedural sampler stacks): of those
        whose top holds ``xy`` (2 cm tolerance), the one whose top centre is nearest; else the one
        whose top is nearest, if within ``STACK_SNAP``; else None. Returns the base and its top."""
        bases = [o for o in placed if is_stack_base(self.catalog.get(o.asset)) and o.support != "floor"]
        tops = [layout.object_top_surface(self.catalog, o) for o in bases]
        holding = [
            (np.hypot(*(np.asarray(t.center) - xy)), k) for k, t in enumerate(tops) if t.margin(xy) >= -0.02
        ]
        near = [(-t.margin(xy), k) for k, t in enumerate(tops) if t.margin(xy) >= -STACK_SNAP]
        k = min(holding or near, default=(None, None))[1]
        return None if k is None else (bases[k], tops[k])

    def _furniture(self, scene: np.ndarray) -> tuple[FurniturePlacement, ...]:
        out = []
        for i, kind in enumerate(FURNITURE_KINDS):
            present, dx, dy = scene[3 * i : 3 * i + 3]
            if present > 0:
                home = FURNITURE_HOME[kind]
                position = (
                    round(home[0] + float(dx) * FURNITURE_SCALE, 6),
                    round(home[1] + float(dy) * FURNITURE_SCALE, 6),
                    0.0,
                )
                out.append(FurniturePlacement(name=kind, kind=kind, position=position))
        return tuple(out)

    def _lighting(self, scene: np.ndarray) -> Lighting:
        base = 3 * len(FURNITURE_KINDS)
        ambient = round(float(np.clip(scene[base] * AMBIENT_SCALE + AMBIENT_CENTRE, 0.0, 1.0)), 6)
        lights = []
        for i in range(self.light_slots):
            v = scene[base + 1 + LIGHT_WIDTH * i : base + 1 + LIGHT_WIDTH * (i + 1)]
            if v[0] <= 0:
                continue
            pos = np.array([v[1] * LIGHT_SCALE, v[2] * LIGHT_SCALE, layout.TABLE_TOP_Z + v[3] * LIGHT_SCALE])
            aim = np.array([v[4] * XY_SCALE, v[5] * XY_SCALE, layout.TABLE_TOP_Z])
            direction = aim - pos
            norm = np.linalg.norm(direction)
            direction = direction / norm if norm > 1e-9 else np.array([0.0, 0.0, -1.0])
            tint = float(v[6]) * TINT_SCALE
            lights.append(
                Light(
                    position=tuple(round(float(x), 6) for x in pos),
                    direction=tuple(round(float(x), 6) for x in direction),
                    colour=tuple(round(float(x), 6) for x in np.clip([1 + tint, 1.0, 1 - tint], 0.0, 1.0)),
                    intensity=round(float(np.clip(v[7] * INTENSITY_SCALE + INTENSITY_CENTRE, 0.0, 3.0)), 6),
                    cast_shadow=bool(v[8] > 0),
                )
            )
        return Lighting(lights=tuple(lights), ambient=(ambient, ambient, ambient))
