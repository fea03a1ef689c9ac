"""Image statistics: exposure and colour of a batch's rendered RGB images against rendered reference
scenes.

Each RGB image becomes a short vector of statistics (:func:`image_statistics`, all in 0-1 units);
a batch's rows (:func:`batch_image_statistics`) are compared with the rows of rendered reference
layouts (``assets/reference/image_stats.json``, built by scenegen/data/reference_images.py) by the
largest standardized mean difference over the statistics (:func:`image_stats_check`). It catches
batches that are too dark, too bright, too flat or tinted; it says nothing about the layout (that is
:mod:`scenegen.analysis.realism`). No download at run time: the reference rows are a committed file.

Pure numpy and OpenCV: no simulation, no renderer.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.paths import PIPELINES_DIR, PROJECT_ROOT

IMAGE_STAT_NAMES: tuple[str, ...] = (
    "luminance_mean",
    "luminance_std",
    "luminance_p05",
    "luminance_p95",
    "underexposed",
    "overexposed",
    "chroma_r",
    "chroma_g",
    "saturation_mean",
)
UNDEREXPOSED = 0.04  # luminance below this is crushed black (about 10 of 255)
OVEREXPOSED = 0.96  # luminance above this is blown white (about 245 of 255)
REC709 = (0.2126, 0.7152, 0.0722)

REFERENCE_IMAGE_STATS = PROJECT_ROOT / "assets" / "reference" / "image_stats.json"
REFERENCE_PARQUET = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"
REFERENCE_RECIPE = PIPELINES_DIR / "reference.yaml"

# Standard deviations below this (0-1 units) count as this much: a statistic that is constant over the
# reference (in practice `overexposed`, 0 in nearly every reference image) would otherwise turn a
# difference of one blown pixel into an infinite standardized difference. 0.01 = 1 % of the range.
STD_FLOOR = 0.01
# Largest |standardized mean difference| that passes. Measured on the committed file (60 reference
# scenes, 120 images; docs/realism.md, "Image statistics"): two disjoint halves of the reference
# 0.23 (first vs second) and 0.32 median, 0.90 max over 200 random scene-level splits; random 6-scene
# batches 0.49 median, 1.19 99th percentile, 1.46 max of 1,000. The same 120 images darkened x0.5
# give 2.41, tinted (R x1.15, B x0.85) 11.0, green x0.9 2.53, contrast x0.7 2.06.
IMAGE_STATS_THRESHOLD = 1.5


# ---------------------------------------------------------------- statistics of one image


def image_statistics(rgb: np.ndarray) -> np.ndarray:
    """Exposure and colour statistics (S,) float64 of one RGB image (H, W, 3) uint8, in the order of
    ``IMAGE_STAT_NAMES``. Luminance is the Rec. 709 weighted sum of the stored (gamma-encoded) R, G, B
    scaled to 0-1, i.e. luma as an image viewer shows it, not linear light.

    - ``luminance_mean``: mean luminance (0-1).
    - ``luminance_std``: standard deviation of luminance over pixels, the global contrast (0-1).
    - ``luminance_p05``, ``luminance_p95``: 5th and 95th percentiles of luminance (0-1; linear
      interpolation between pixels, numpy's default).
    - ``underexposed``: share of pixels with luminance < 0.04 (0-1).
    - ``overexposed``: share of pixels with luminance > 0.96 (0-1).
    - ``chroma_r``, ``chroma_g``: mean over pixels of r/(r+g+b) and g/(r+g+b) (0-1; 1/3 each for
      grey; a black pixel counts as grey).
    - ``saturation_mean``: mean HSV saturation (max - min) / max over pixels (0-1; 0 for black).
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.size == 0:
        raise ValueError(f"image_statistics takes an (H, W, 3) uint8 RGB image; got {rgb.shape} {rgb.dtype}")
    x = rgb.reshape(-1, 3).astype(np.float64) / 255.0
    luminance = x @ np.asarray(REC709)
    # per pixel over the three channels, written out: the same values as x.sum / x.max / x.min along
    # axis 1 ((r + g) + b; max and min are exact), at half the cost of numpy's reductions over an
    # axis of 3 (the image check of a 48-scene batch, 96 images: 6.7 -> 3.6 CPU-s)
    r, g, b = x[:, 0], x[:, 1], x[:, 2]
    total = r + g
    total += b
    grey = total <= 0.0
    safe = np.where(grey, 1.0, total)
    chroma_r = np.where(grey, 1.0 / 3.0, r / safe)
    chroma_g = np.where(grey, 1.0 / 3.0, g / safe)
    high, low = np.maximum(np.maximum(r, g), b), np.minimum(np.minimum(r, g), b)
    saturation = np.where(high > 0.0, (high - low) / np.where(high > 0.0, high, 1.0), 0.0)
    p05, p95 = np.percentile(luminance, [5.0, 95.0])
    return np.array(
        [
            luminance.mean(),
            luminance.std(),
            p05,
            p95,
            np.mean(luminance < UNDEREXPOSED),
            np.mean(luminance > OVEREXPOSED),
            chroma_r.mean(),
            chroma_g.mean(),
            saturation.mean(),
        ],
        dtype=np.float64,
    )


def _decode_rgb(data: bytes, name: str) -> np.ndarray:
    """An RGB uint8 image from PNG bytes; ``name`` is what an error calls it."""
    import cv2

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None:
        raise ValueError(f"{name}: not a readable image")
    return image[..., ::-1]  # OpenCV decodes to BGR


def read_rgb(path: Path) -> np.ndarray:
    """The RGB uint8 image (H, W, 3) of a PNG file; ValueError naming the file if it is missing or
    unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such image file")
    return _decode_rgb(path.read_bytes(), str(path))


# ---------------------------------------------------------------- a stored batch


def batch_image_statistics(batch: Path) -> tuple[np.ndarray, list[str], list[str]]:
    """Statistics of every RGB image of a stored batch: rows (N, S), and the scene id and camera
    name of each row.

    Scenes are taken in the order of the batch's ``index.jsonl``; within a scene, cameras in the
    order of scene.json ``cameras``, each one's ``images.rgb`` file, decoded and measured. A missing
    index or scene.json, a camera without an RGB image (a ``--no-render`` batch) or an unreadable PNG
    raises ValueError naming the file.
    """
    from scenegen.store.batch import INDEX, scene_dirs

    batch = Path(batch)
    index = batch / INDEX
    rows, scene_ids, cameras = [], [], []
    for entry, scene_dir in scene_dirs(batch):  # StoreError (a ValueError) for a broken index
        scene_json = scene_dir / "scene.json"
        if not scene_json.is_file():
            raise ValueError(f"{scene_json}: no such file, though {index} lists the scene")
        try:
            scene = json.loads(scene_json.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{scene_json}: not valid JSON ({exc})") from None
        names, measured = scene_statistics(scene, scene_dir, batch)
        rows += list(measured)
        scene_ids += [entry["scene_id"]] * len(names)
        cameras += names
    stats = np.stack(rows) if rows else np.zeros((0, len(IMAGE_STAT_NAMES)))
    return stats, scene_ids, cameras


def scene_statistics(scene: dict, scene_dir: Path, batch: Path) -> tuple[list[str], np.ndarray]:
    """The camera names and statistic rows (cameras, S) of one stored scene's RGB images (``scene``:
    its scene.json), each image confined to ``batch``; ValueError naming the file as above."""
    from scenegen.core.files import confined

    names, rows = [], []
    for camera in scene["cameras"]:
        name = (camera.get("images") or {}).get("rgb")
        if name is None:
            raise ValueError(
                f"{scene_dir / 'scene.json'}: camera {camera['name']!r} has no RGB image (was the batch "
                "generated with --no-render?); image statistics need rendered images"
            )
        rows.append(image_statistics(read_rgb(confined(scene_dir / str(name), batch, "an image"))))
        names.append(camera["name"])
    return names, (np.stack(rows) if rows else np.zeros((0, len(IMAGE_STAT_NAMES))))


def sampled_smd(
    scene_rows: Sequence[np.ndarray], population: int, reference: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each statistic's standardized mean difference (as :func:`image_stats_check` computes it over
    all of a batch's images) estimated from a simple random sample of the batch's scenes, and its
    standard error. ``scene_rows``: each sampled scene's rows (its cameras, S); ``population``: the
    scenes of the batch. The batch's image mean is a ratio (image sums over image counts), so the
    estimate is the sample's ratio and its standard error the ratio estimator's: the spread of each
    scene's residual sum (its rows' sum less the estimate times its image count) over sqrt(n), divided
    by the mean image count, times the finite-population correction sqrt(1 - n / population); both in
    the reference's scale (its standard deviation, floored at STD_FLOOR)."""
    reference = np.asarray(reference, np.float64)
    sums = np.stack([np.asarray(r, np.float64).sum(axis=0) for r in scene_rows])
    counts = np.array([len(r) for r in scene_rows], np.float64)
    n = len(scene_rows)
    if n < 2 or counts.sum() < 2:
        raise ValueError(f"a sample of {n} scene(s) and {int(counts.sum())} image(s): it needs 2 of each")
    mean = sums.sum(axis=0) / counts.sum()
    residual = sums - counts[:, None] * mean
    correction = np.sqrt(max(0.0, 1.0 - n / max(population, n)))
    error = residual.std(axis=0, ddof=1) / np.sqrt(n) / counts.mean() * correction
    scale = np.maximum(reference.std(axis=0, ddof=1), STD_FLOOR)
    return (mean - reference.mean(axis=0)) / scale, error / scale


# ---------------------------------------------------------------- the check


@dataclass(frozen=True)
class ImageStatsResult:
    """Image-statistics check: ``value`` = the largest |standardized mean difference| over the
    statistics, ``passed`` = value <= ``threshold``; ``per_stat`` maps each statistic's name to its
    signed standardized mean difference (batch minus reference, in reference standard deviations)."""

    value: float
    threshold: float
    passed: bool
    per_stat: dict[str, float]
    n_batch: int
    n_reference: int


def image_stats_check(
    batch: np.ndarray, reference: np.ndarray, threshold: float = IMAGE_STATS_THRESHOLD
) -> ImageStatsResult:
    """Compare a batch's statistic rows (N_b, S) with reference rows (N_r, S).

    Per statistic: (mean_batch - mean_ref) / max(std_ref, STD_FLOOR), std_ref with ddof=1; the value
    is the largest absolute one. The rows are images, not scenes: cameras of one scene are not
    independent, so a handful of scenes gives a noisy mean (the default threshold allows for 6).
    Raises ValueError for misuse: a sample with fewer than 2 rows, a width other than
    ``len(IMAGE_STAT_NAMES)``, or NaN.
    """
    batch, reference = np.asarray(batch, np.float64), np.asarray(reference, np.float64)
    width = len(IMAGE_STAT_NAMES)
    for label, rows in (("batch", batch), ("reference", reference)):
        if rows.ndim != 2 or rows.shape[1] != width:
            raise ValueError(f"{label} rows must be (N, {width}) (IMAGE_STAT_NAMES); got {rows.shape}")
        if len(rows) < 2:
            raise ValueError(
                f"{label} has {len(rows)} image row(s); the check needs at least 2 (one scene with two "
                "cameras will do)"
            )
        if not np.isfinite(rows).all():
            raise ValueError(f"{label} rows contain NaN or infinite statistics")
    scale = np.maximum(reference.std(axis=0, ddof=1), STD_FLOOR)
    smd = (batch.mean(axis=0) - reference.mean(axis=0)) / scale
    value = float(np.abs(smd).max())
    return ImageStatsResult(
        value=value,
        threshold=float(threshold),
        passed=value <= threshold,
        per_stat={name: float(v) for name, v in zip(IMAGE_STAT_NAMES, smd, strict=True)},
        n_batch=len(batch),
        n_reference=len(reference),
    )


# ---------------------------------------------------------------- the committed reference file


def load_reference_image_stats(path: Path = REFERENCE_IMAGE_STATS) -> tuple[np.ndarray, dict]:
    """Rows (N, S) and metadata (every other key) of a reference image-statistics file; a one-line
    ValueError naming the file when it is missing, not JSON, or not of this module's statistics."""
    path = Path(path)
    rebuild = "rebuild it with: scenegen reference-images --n 60 --out " + str(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file; {rebuild}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({str(exc).splitlines()[0]}); {rebuild}") from None
    if not isinstance(data, dict) or "rows" not in data or "stat_names" not in data:
        raise ValueError(f"{path}: not an image-statistics file (needs 'stat_names' and 'rows'); {rebuild}")
    if list(data["stat_names"]) != list(IMAGE_STAT_NAMES):
        raise ValueError(
            f"{path}: statistics {data['stat_names']} differ from IMAGE_STAT_NAMES "
            f"{list(IMAGE_STAT_NAMES)}; {rebuild}"
        )
    try:
        rows = np.asarray(data["rows"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: 'rows' is not a rectangular table of numbers; {rebuild}") from None
    n = len(data["rows"])
    if rows.ndim != 2 or rows.shape[1] != len(IMAGE_STAT_NAMES) or n < 2:
        raise ValueError(
            f"{path}: 'rows' has shape {rows.shape}, expected (N >= 2, {len(IMAGE_STAT_NAMES)}); {rebuild}"
        )
    if not np.isfinite(rows).all():
        raise ValueError(f"{path}: 'rows' holds NaN or infinite values; {rebuild}")
    for key in ("scene_index", "camera"):
        if len(data.get(key, ())) != n:
            raise ValueError(f"{path}: '{key}' must have one entry per row ({n}); {rebuild}")
    meta = {k: v for k, v in data.items() if k != "rows"}
    return rows, meta
