"""Contact sheets: a batch at a glance, for a person to look at (``scenegen show``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from scenegen.core.files import OutsideRootError, confined
from scenegen.store.batch import INDEX, StoreError, scene_dirs

CONTACT_SHEET = "contact_sheet.png"  # the sheet's name inside the batch when no --out is given
THUMB = (320, 240)  # width, height of one thumbnail
LABEL_HEIGHT = 34


class SheetError(ValueError):
    """The batch cannot be shown; the message names the path and what to do."""


def _label(image: np.ndarray, lines: list[str]) -> np.ndarray:
    band = np.full((LABEL_HEIGHT, image.shape[1], 3), 255, np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(
            band, text[:48], (4, 13 + 15 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA
        )
    return np.vstack([image, band])


def depth_view(depth_mm: np.ndarray) -> np.ndarray:
    """Millimetre depth as a colour image (near bright, far dark; missing pixels black): a uint16
    PNG shows black in a browser and in most viewers."""
    valid = depth_mm > 0
    view = np.zeros(depth_mm.shape, np.uint8)
    if valid.any():
        lo, hi = np.percentile(depth_mm[valid], [1, 99])
        view[valid] = np.clip(255 * (1 - (depth_mm[valid] - lo) / max(hi - lo, 1)), 0, 255).astype(np.uint8)
    out = cv2.applyColorMap(view, cv2.COLORMAP_VIRIDIS)
    out[~valid] = 0
    return out


def seg_view(seg: np.ndarray) -> np.ndarray:
    """Instance ids as distinct colours (background black)."""
    ids = seg.astype(np.int64)
    colours = np.stack([(ids * 67) % 256, (ids * 151) % 256, (ids * 199) % 256], axis=-1).astype(np.uint8)
    colours[ids == 0] = 0
    return colours


def _read(path: Path, flags: int) -> np.ndarray:
    try:
        confined(path, path.parent.parent, "an image")  # batch/scene_NNNNNN/IMAGE
    except OutsideRootError as exc:
        raise SheetError(str(exc)) from None
    image = cv2.imread(str(path), flags) if path.is_file() else None
    if image is None:
        raise SheetError(f"{path}: missing or unreadable image; was the batch generated with --no-render?")
    return image


def _record(path: Path) -> dict:
    """A stored scene.json, validated (SheetError naming it otherwise)."""
    from pydantic import ValidationError

    from scenegen.schema.scene import SceneRecord

    try:
        return SceneRecord.model_validate_json(path.read_bytes()).model_dump(mode="json")
    except FileNotFoundError:
        raise SheetError(f"{path}: missing; is the batch complete?") from None
    except (ValidationError, OSError, ValueError) as exc:
        raise SheetError(f"{path}: not a scene record ({str(exc).splitlines()[0][:100]})") from None


def contact_sheet(
    batch: Path,
    out: Path | None = None,
    camera: str | None = None,
    depth: bool = False,
    seg: bool = False,
    limit: int = 24,
    columns: int = 4,
) -> Path:
    """Write a PNG grid of the batch's scenes (in index order) and return its path."""
    batch = Path(batch)
    try:
        scenes = scene_dirs(batch)
    except StoreError as exc:
        raise SheetError(str(exc)) from None
    if not scenes:
        raise SheetError(f"{batch}: no {INDEX} with stored scenes; run `scenegen generate` first")
    tiles = []
    for row, scene_dir in scenes[: max(limit, 1)]:
        record = _record(scene_dir / "scene.json")
        cam = camera or record["cameras"][0]["name"]
        if cam not in {c["name"] for c in record["cameras"]}:
            valid = ", ".join(c["name"] for c in record["cameras"])
            raise SheetError(f"--camera {cam}: not a camera of {row['scene_id']}; valid cameras: {valid}")
        views = [
            cv2.resize(
                _read(scene_dir / f"{cam}_rgb.png", cv2.IMREAD_COLOR), THUMB, interpolation=cv2.INTER_AREA
            )
        ]
        if depth:
            d = _read(scene_dir / f"{cam}_depth.png", cv2.IMREAD_UNCHANGED)
            views.append(cv2.resize(depth_view(d), THUMB, interpolation=cv2.INTER_NEAREST))
            images = next(c for c in record["cameras"] if c["name"] == cam).get("images") or {}
            if "sensor_depth" in images:  # the depth sensor's frame beside the exact one (docs/sensor.md)
                d = _read(scene_dir / images["sensor_depth"], cv2.IMREAD_UNCHANGED)
                views.append(cv2.resize(depth_view(d), THUMB, interpolation=cv2.INTER_NEAREST))
        if seg:
            s = _read(scene_dir / f"{cam}_seg.png", cv2.IMREAD_UNCHANGED)
            views.append(cv2.resize(seg_view(s), THUMB, interpolation=cv2.INTER_NEAREST))
        target = next(o for o in record["objects"] if o["name"] == record["target"])
        tags = record.get("tags") or {}
        held = [t for t, v in tags.items() if (v.get("holds") if isinstance(v, dict) else v)]
        lines = [
            f"{row['scene_id']}  target {target['asset']} on {target['support']}",
            "tags: " + (", ".join(held) or "-"),
        ]
        tiles.append(_label(np.hstack(views), lines))
    blank = np.full_like(tiles[0], 255)
    columns = max(1, min(columns, len(tiles)))
    while len(tiles) % columns:
        tiles.append(blank)
    grid = np.vstack([np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)])
    out = Path(out) if out else batch / CONTACT_SHEET
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), grid):
        raise SheetError(f"{out}: cannot write the PNG")
    return out
