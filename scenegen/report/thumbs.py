"""Thumbnails beside a report: per scene and camera a small RGB (JPEG), the depth colourized and the
segmentation in distinct colours (PNG), so a browser shows a thousand scenes without decoding a
thousand full-size frames. Made from the scene's own image files; a scene without images (a batch
generated with --no-render) gets none."""

from __future__ import annotations

from pathlib import Path

import cv2

from scenegen.analysis.contact_sheet import depth_view, seg_view
from scenegen.core.files import OutsideRootError, confined
from scenegen.store.batch import atomic_write

SIZE = (224, 168)  # width, height
KINDS = {  # kind -> (the scene's file, read flags, view, interpolation, thumbnail suffix)
    "rgb": ("{camera}_rgb.png", cv2.IMREAD_COLOR, None, cv2.INTER_AREA, ".jpg"),
    "depth": ("{camera}_depth.png", cv2.IMREAD_UNCHANGED, depth_view, cv2.INTER_NEAREST, ".png"),
    "seg": ("{camera}_seg.png", cv2.IMREAD_UNCHANGED, seg_view, cv2.INTER_NEAREST, ".png"),
}


def thumbnail_name(scene_id: str, camera: str, kind: str) -> str:
    return f"{scene_id}_{camera}_{kind}{KINDS[kind][4]}"


def write_thumbnails(batch: Path, scene: dict, out: Path) -> dict[str, dict[str, str]]:
    """The thumbnails of one scene (``facts.batch_facts``'s entry) written into ``out``; camera ->
    kind -> file name. Each file is written whole (``atomic_write``)."""
    made: dict[str, dict[str, str]] = {}
    if not scene["rendered"]:
        return made
    folder = batch / scene["folder"]
    for camera in scene["cameras"]:
        for kind, (pattern, flags, view, interpolation, suffix) in KINDS.items():
            source = folder / pattern.format(camera=camera)
            try:
                confined(source, batch, "an image")
            except OutsideRootError:
                continue
            image = cv2.imread(str(source), flags) if source.is_file() else None
            if image is None:
                continue
            image = cv2.resize(view(image) if view else image, SIZE, interpolation=interpolation)
            params = [cv2.IMWRITE_JPEG_QUALITY, 85] if suffix == ".jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 3]
            ok, data = cv2.imencode(suffix, image, params)
            if not ok:
                continue
            name = thumbnail_name(scene["id"], camera, kind)
            atomic_write(out / name, data.tobytes())
            made.setdefault(camera, {})[kind] = name
    return made
