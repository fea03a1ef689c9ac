"""The rendered reference scenes behind the image-statistics check: the first N layouts of the
reference set, rendered exactly as the reference recipe makes them, reduced to their image statistics
(scenegen/analysis/image_stats.py) in ``assets/reference/image_stats.json`` (committed: nothing is downloaded
at run time).

Rebuild the committed file (46 s on 2 cores)::

    scenegen reference-images --n 60 --workers 2
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

from scenegen.analysis.image_stats import (
    IMAGE_STAT_NAMES,
    REFERENCE_IMAGE_STATS,
    REFERENCE_PARQUET,
    REFERENCE_RECIPE,
    _decode_rgb,
    image_statistics,
)
from scenegen.paths import PROJECT_ROOT


def _shown(path: Path) -> str:
    """A path as written into the reference file: relative to the project when inside it."""
    path = Path(path).resolve()
    return path.relative_to(PROJECT_ROOT).as_posix() if path.is_relative_to(PROJECT_ROOT) else str(path)


def _command(n: int, out: Path, recipe: Path, reference: Path) -> str:
    """The command that rebuilds a reference file (workers do not change it: renders are bit-identical)."""
    command = f"scenegen reference-images --n {n} --out {_shown(out)}"
    if recipe.resolve() != REFERENCE_RECIPE.resolve():
        command += f" --recipe {_shown(recipe)}"
    if reference.resolve() != REFERENCE_PARQUET.resolve():
        command += f" --reference {_shown(reference)}"
    return command


def _reference_outcomes(config, n: int, workers: int) -> Iterator:
    """The first ``n`` accepted outcomes of the reference proposals, rendered."""
    from scenegen.data.reference import _proposals  # the reference set's own proposals, unchanged
    from scenegen.runner.executors import ordered_outcomes

    rendered = config.model_copy(update={"render": True})
    outcomes = ordered_outcomes(_proposals(config), rendered, workers, export=False)
    accepted = 0
    try:
        for outcome in outcomes:
            if outcome.record is None:
                continue
            yield outcome
            accepted += 1
            if accepted == n:
                return
    finally:
        outcomes.close()


def build_reference_image_stats(
    n: int,
    out: Path = REFERENCE_IMAGE_STATS,
    workers: int = 1,
    recipe: Path = REFERENCE_RECIPE,
    reference: Path = REFERENCE_PARQUET,
    images: Path | None = None,
) -> dict:
    """Render the first ``n`` accepted layouts of the reference set and write their image statistics
    to ``out`` (JSON, atomically); returns what was written, plus ``seconds``. ``images``: also write
    each RGB image there as ``<proposal index>_<camera>_rgb.png`` (to look at, or to test with).

    The layouts are made exactly as ``scenegen reference`` makes them (its proposals, the recipe's
    check, settle and tag) with rendering switched on; their proposal indices must equal the first
    ``n`` ``index`` values of the reference Parquet file, else ValueError (the recipe or the code
    changed since the Parquet file was built). Needs off-screen GL (MUJOCO_GL=egl).
    """
    import pyarrow.parquet as pq

    from scenegen.render.offscreen import RENDER_SETTINGS
    from scenegen.runner.config import load_pipeline
    from scenegen.store.batch import atomic_write, sha256_file

    if n < 1:
        raise ValueError(f"n={n}: render at least one reference layout")
    recipe, reference, out = Path(recipe), Path(reference), Path(out)
    config = load_pipeline(recipe)
    expected = pq.read_table(reference, columns=["index"]).column("index").to_pylist()[:n]
    if len(expected) < n:
        raise ValueError(f"n={n}: {reference} holds only {len(expected)} layouts")
    if images is not None:
        images = Path(images)
        images.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows, indices, cameras = [], [], []
    for outcome in _reference_outcomes(config, n, workers):
        record = outcome.record
        for camera in record.cameras:
            name = camera["images"]["rgb"]
            rgb = _decode_rgb(outcome.images[name], f"scene_{record.proposal_index:06d}/{name}")
            if images is not None:
                atomic_write(images / f"{record.proposal_index:06d}_{name}", outcome.images[name])
            rows.append([round(float(v), 6) for v in image_statistics(rgb)])
            indices.append(record.proposal_index)
            cameras.append(camera["name"])
    got = list(dict.fromkeys(indices))
    if got != expected:
        raise ValueError(
            f"the rendered reference layouts are proposals {got[:10]}..., but the first {n} rows of "
            f"{reference} are {expected[:10]}...; {recipe} or the pipeline changed since the Parquet "
            "file was built: rebuild it (scenegen reference) or restore the recipe"
        )
    result = {
        # The committed file's words (its sha256 is recorded by every image check); the function is
        # scenegen.analysis.image_stats.image_statistics since issue 17 moved it.
        "description": (
            "image statistics (scenegen.image_stats.image_statistics) of the rendered RGB images of the "
            f"first {n} accepted reference layouts, every camera"
        ),
        "stat_names": list(IMAGE_STAT_NAMES),
        "n": n,
        "scene_index": indices,
        "camera": cameras,
        "reference": _shown(reference),
        "reference_sha256": sha256_file(reference),
        "recipe": _shown(recipe),
        "recipe_sha256": config.digest(),
        "rendered_with": {"render": True},
        "render_settings": RENDER_SETTINGS,
        "command": _command(n, out, recipe, reference),
        "rows": rows,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, json.dumps(result, indent=1) + "\n")
    result["seconds"] = round(time.perf_counter() - start, 1)
    return result
