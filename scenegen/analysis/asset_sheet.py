"""Asset contact sheets (``scenegen assets show``): each asset in every resting pose, built by the
scene builder (sim/world.py) and lit by a lamp above each view and a soft ambient light, and its
convex parts beside it, one colour per part, so a person can check an import (scale, up axis,
texture, poses, collision model).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import mujoco
import numpy as np

from scenegen.assets.catalog import Asset, Catalog
from scenegen.schema.scene import Camera, ObjectPlacement
from scenegen.sim import world

PANEL = 240  # pixels per side of one view
LABEL_HEIGHT = 30
AMBIENT = 0.3
LAMP = (0.25, -0.35, 1.0)  # a lamp above each view, relative to the asset (metres), aimed at it
PART_COLOURS = np.array(
    [[0.9, 0.3, 0.3], [0.3, 0.7, 0.3], [0.3, 0.4, 0.9], [0.9, 0.7, 0.2], [0.7, 0.3, 0.8], [0.2, 0.8, 0.8]]
)


def asset_sheet(catalog: Catalog, names: Sequence[str], out: Path) -> Path:
    """Write a PNG with one row per asset in ``names`` (its resting poses, then its convex parts) and
    return its path."""
    rows = [_asset_row(catalog.get(name)) for name in names]
    width = max(row.shape[1] for row in rows)
    sheet = np.vstack(
        [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    )
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".tmp_{out.name}")
    if not cv2.imwrite(str(tmp), sheet[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise OSError(f"{out}: cannot write the contact sheet")
    tmp.replace(out)
    return out


def _asset_row(asset: Asset) -> np.ndarray:
    """Views of one asset (H, W, 3) uint8: one per resting pose, then its parts, each labelled."""
    spacing = 3.0 * max(asset.extents)
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = PANEL, PANEL
    spec.worldbody.add_geom(
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0, 0, 0.05],
        rgba=[0.62, 0.6, 0.57, 1],
        group=world.VISUAL_GROUP,
    )
    spec.visual.headlight.ambient = [AMBIENT] * 3
    spec.visual.headlight.diffuse = [0.0] * 3
    catalog = Catalog(version=1, assets=(asset,))
    world._add_asset_meshes(spec, catalog, asset, {1.0})
    views, labels = [], []
    for i, pose in enumerate(asset.resting_poses):
        centre = (i * spacing, 0.0, pose.height)
        obj = ObjectPlacement(
            name=f"pose{i}", asset=asset.name, category=asset.category, position=centre, quat=pose.quat
        )
        world._add_object(spec, asset, obj)
        views.append(_view(spec, f"view{i}", centre, asset))
        kind = "upright" if pose.upright else "lying"
        labels.append([f"{asset.name} ({asset.category})", f"pose {i}: {kind}, p={pose.probability:.2f}"])
    first = asset.resting_poses[0]
    centre = (len(asset.resting_poses) * spacing, 0.0, first.height)
    body = spec.worldbody.add_body(name="parts", pos=centre, quat=first.quat)
    _, part_meshes = world._mesh_names(asset, 1.0)
    for j, mesh in enumerate(part_meshes):
        colour = PART_COLOURS[j % len(PART_COLOURS)]
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh, rgba=[*colour, 1.0], group=world.VISUAL_GROUP
        )
    views.append(_view(spec, "view_parts", centre, asset))
    labels.append(
        [f"{len(part_meshes)} convex part(s): {asset.collision}", f"{asset.hull_to_visual_mm} mm off"]
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0
    option.geomgroup[world.VISUAL_GROUP] = 1
    with mujoco.Renderer(model, PANEL, PANEL) as renderer:
        images = []
        for view, label in zip(views, labels, strict=True):
            renderer.update_scene(data, camera=view, scene_option=option)
            images.append(_labelled(renderer.render(), label))
    return np.hstack(images)


def _view(spec: mujoco.MjSpec, name: str, centre: tuple[float, float, float], asset: Asset) -> str:
    """A camera 30 degrees above the horizon, in front and to the side, framing the asset."""
    lookat = np.asarray(centre, float)
    spec.worldbody.add_light(
        pos=lookat + LAMP,
        dir=-np.asarray(LAMP),
        diffuse=[0.5] * 3,
        specular=[0.1] * 3,
        castshadow=True,
        cutoff=20,
    )
    distance = 1.6 * max(asset.extents) / math.tan(math.radians(22.5))
    azimuth, elevation = math.radians(-60), math.radians(30)
    offset = distance * np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    world.add_camera(
        spec, Camera(name=name, position=tuple(lookat + offset), lookat=tuple(lookat), fovy=45.0)
    )
    return name


def _labelled(image: np.ndarray, lines: list[str]) -> np.ndarray:
    band = np.full((LABEL_HEIGHT, image.shape[1], 3), 255, np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(
            band, text[:40], (4, 12 + 13 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.36, (20, 20, 20), 1, cv2.LINE_AA
        )
    return np.vstack([image, band])
