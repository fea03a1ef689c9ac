"""The realism checks a batch carries in its manifest, each against the committed reference set.

- ``layout_c2st``: classifier two-sample test of the batch's settled layouts against reference layouts
  of the same request (scenegen.analysis.realism.c2st); passes at accuracy <= ``C2ST_THRESHOLD``.
- ``layout_mmd``: kernel MMD^2 of the same two samples (scenegen.analysis.realism.mmd); passes at
  MMD^2 <= ``MMD_THRESHOLD``.
- ``image_stats``: exposure and colour statistics of the batch's RGB renders against rendered
  reference scenes (scenegen.analysis.image_stats; assets/reference/image_stats.json, committed: nothing is
  downloaded).

Each check records the checksum root of the batch it was computed on, the reference file's sha256 and
the subset used, the sample counts and its settings. A batch with fewer than ``MIN_SAMPLES`` scenes
gets its checks recorded with status ``insufficient``: the tests have no power there.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path

from scenegen.manifest.schema import RealismCheck, RealismReference
from scenegen.paths import PROJECT_ROOT
from scenegen.store.batch import scene_dirs, sha256_file

REFERENCE_TABLE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"
# The feature set's name in recorded manifests: the function's path when checks were first recorded
# (it now lives in scenegen.analysis.realism); kept so that recorded checks still audit equal.
FEATURES = "scenegen.realism.layout_features"
REFERENCE_IMAGES = PROJECT_ROOT / "assets" / "reference" / "image_stats.json"
MIN_SAMPLES = 20
MIN_REFERENCE = 50  # the narrowest reference subset used; wider subsets are taken below it
# Thresholds chosen by measurement (docs/realism.md, "Batch realism checks"): 15 random draws of 24
# reference layouts (spoon targets) against the held-out spoon layouts gave C2ST accuracy <= 0.60 and
# MMD^2 <= 0.0064 (0.0020 at 50 layouts); layouts spread 1.5x or lights halved gave MMD^2 0.035-0.066.
C2ST_THRESHOLD = 0.70
MMD_THRESHOLD = 0.02


def reference_subset(rows: list[dict], condition, unconditional: bool = False) -> tuple[list[dict], str]:
    """Reference rows comparable with a batch of ``condition``: same target category and required /
    forbidden tags, held-out split first; widened (all splits, then any target) while fewer than
    ``MIN_REFERENCE`` rows match. Returns the rows and a description of the subset."""
    if unconditional:
        held = [r for r in rows if r["split"] == "heldout"]
        return held, "split=heldout"
    required = sorted(t for t, s in condition.tags.items() if s == "required")
    forbidden = sorted(t for t, s in condition.tags.items() if s == "forbidden")

    def matches(row, by_target):
        return (
            (not by_target or row["target_category"] == condition.target)
            and all(row[f"tag_{t}"] for t in required)
            and not any(row[f"tag_{t}"] for t in forbidden)
        )

    tags = ",".join([*(f"+{t}" for t in required), *(f"-{t}" for t in forbidden)]) or "any"
    for split, by_target in (("heldout", True), (None, True), (None, False)):
        subset = [r for r in rows if (split is None or r["split"] == split) and matches(r, by_target)]
        if len(subset) >= MIN_REFERENCE or (split is None and not by_target):
            target = condition.target if by_target else "any"
            return subset, f"split={split or 'all'} target={target} tags={tags}"
    raise AssertionError("unreachable")


def batch_layout_rows(batch: Path) -> list[dict]:
    """The settled layouts of a batch's scenes, in index order, as reference-table rows."""
    from scenegen.analysis.realism import record_row
    from scenegen.schema.scene import SceneRecord

    rows = []
    for _, scene_dir in scene_dirs(Path(batch)):
        text = (scene_dir / "scene.json").read_text()
        rows.append(record_row(SceneRecord.model_validate_json(text)))
    return rows


def reference_layouts(path: Path, condition, unconditional: bool = False) -> tuple[list[dict], str]:
    """:func:`reference_subset` of the reference table at ``path``, decided on its flat columns
    (split, target category, tags) and only the chosen rows turned into dicts: the same rows in the
    same order as on the whole table, without building 10,000 nested rows (0.9 s) a batch's
    manifest then throws away. The table is read once per process for each version of the file (an
    audit of a project manifest judges every source against it)."""
    stat = Path(path).stat()
    table = _reference_table(str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    keys = [c for c in table.column_names if c in ("split", "target_category") or c.startswith("tag_")]
    flat = table.select(keys).to_pylist()
    for i, row in enumerate(flat):
        row["_row"] = i
    subset, description = reference_subset(flat, condition, unconditional)
    import pyarrow as pa

    rows = pa.array([row["_row"] for row in subset], type=pa.int64())  # typed: a request may match none
    return table.take(rows).to_pylist(), description


@functools.lru_cache(maxsize=2)
def _reference_table(path: str, size: int, mtime_ns: int):
    import pyarrow.parquet as pq

    return pq.read_table(path)


def check_status(n: int, value: float, threshold: float, reference: int = MIN_SAMPLES) -> str:
    """A check's status: ``insufficient`` below MIN_SAMPLES scenes or without reference rows, else
    passed or failed at ``threshold``."""
    if n < MIN_SAMPLES or reference == 0:
        return "insufficient"
    return "passed" if value <= threshold else "failed"


def layout_checks(
    rows: list[dict],
    batch_sha: str,
    condition,
    unconditional: bool = False,
    seed: int = 0,
    reference: Path = REFERENCE_TABLE,
) -> list[RealismCheck]:
    """``layout_c2st`` and ``layout_mmd`` of layout ``rows`` against the reference subset of the
    request. Fewer than 5 rows (the C2ST's folds) give ``insufficient`` checks with value 0."""
    from scenegen.analysis.realism import c2st, feature_matrix, mmd

    subset, description = reference_layouts(reference, condition, unconditional)
    unknown = unknown_categories(rows)
    if unknown:  # objects of a user catalog: the reference set has no layouts to compare them with
        subset, description = [], f"none: categories {', '.join(unknown)} are not in the reference set"
    ref = RealismReference(source=_relative(reference), sha256=sha256_file(reference), subset=description)
    samples = {"batch": len(rows), "reference": len(subset)}
    if len(rows) >= 5 and len(subset) >= 5:
        a, b = feature_matrix(rows), feature_matrix(subset)
        test = c2st(a, b, seed=seed)
        kernel = mmd(a, b, seed=seed)
        c2st_details = {"ci": [round(v, 6) for v in test.ci], "n": test.n}
        mmd_details = {"p_value": round(kernel.p_value, 6), "bandwidth": round(kernel.bandwidth, 6)}
        c2st_value, mmd_value = round(test.accuracy, 6), round(kernel.mmd2, 6)
    else:
        note = description if unknown else "fewer than 5 samples: not computed"
        c2st_details = mmd_details = {"note": note}
        c2st_value = mmd_value = 0.0
    common = {"batch_sha256": batch_sha, "reference": ref, "samples": samples, "min_samples": MIN_SAMPLES}
    return [
        RealismCheck(
            metric="layout_c2st",
            value=c2st_value,
            threshold=C2ST_THRESHOLD,
            status=check_status(len(rows), c2st_value, C2ST_THRESHOLD, len(subset)),
            settings={"seed": seed, "folds": 5, "features": FEATURES},
            details=c2st_details,
            **common,
        ),
        RealismCheck(
            metric="layout_mmd",
            value=mmd_value,
            threshold=MMD_THRESHOLD,
            status=check_status(len(rows), mmd_value, MMD_THRESHOLD, len(subset)),
            settings={"seed": seed, "kernel": "gaussian, median heuristic", "estimate": "unbiased MMD^2"},
            details=mmd_details,
            **common,
        ),
    ]


def unknown_categories(rows: list[dict]) -> list[str]:
    """Categories of the layout ``rows`` that the reference set does not hold (a user catalog's)."""
    from scenegen.analysis.realism import feature_categories

    return sorted({o["category"] for row in rows for o in row["objects"]} - set(feature_categories()))


def image_check(
    batch: Path,
    batch_sha: str,
    reference: Path = REFERENCE_IMAGES,
    unknown: Sequence[str] = (),
    measured: tuple | None = None,
) -> RealismCheck:
    """``image_stats`` of a rendered batch's RGB images against the committed reference renders;
    ``unknown``: categories of the batch that no reference render shows (then not judged);
    ``measured``: the batch's (rows, scene ids) already measured elsewhere (the audit's workers),
    else its images are decoded here."""
    from scenegen.analysis.image_stats import (
        IMAGE_STATS_THRESHOLD,
        batch_image_statistics,
        image_stats_check,
        load_reference_image_stats,
    )

    rows, scene_ids = measured if measured is not None else batch_image_statistics(batch)[:2]
    ref_rows, meta = load_reference_image_stats(reference)
    n = len(set(scene_ids))
    if unknown:  # objects of a user catalog, whose colours no reference render holds
        ref_rows, value = [], 0.0
        details = {"note": f"categories {', '.join(unknown)} are not in the reference renders: not computed"}
    elif len(rows) >= 2:
        result = image_stats_check(rows, ref_rows)
        value, details = (
            round(result.value, 6),
            {"per_stat": {k: round(v, 6) for k, v in result.per_stat.items()}},
        )
    else:
        value, details = 0.0, {"note": "fewer than 2 images: not computed"}
    return RealismCheck(
        metric="image_stats",
        value=value,
        threshold=IMAGE_STATS_THRESHOLD,
        status=check_status(n, value, IMAGE_STATS_THRESHOLD, len(ref_rows)),
        batch_sha256=batch_sha,
        reference=RealismReference(
            source=_relative(reference), sha256=sha256_file(reference), subset=f"{len(ref_rows)} renders"
        ),
        samples={"batch": n, "images": len(rows), "reference": len(ref_rows)},
        min_samples=MIN_SAMPLES,
        settings={"statistic": "largest |standardized mean difference| over the image statistics"},
        details=details,
    )


def batch_realism(batch: Path, config, batch_sha: str, images: tuple | None = None) -> list[RealismCheck]:
    """Every realism check of a batch written by ``run_batch`` with recipe ``config``; ``images``:
    its images' (rows, scene ids), when measured already (see :func:`image_check`)."""
    unconditional = bool(getattr(config.proposer, "unconditional", False))
    rows = batch_layout_rows(batch)
    checks = layout_checks(rows, batch_sha, config.condition, unconditional, config.seed)
    if config.render:
        checks.append(image_check(batch, batch_sha, unknown=unknown_categories(rows), measured=images))
    return checks


def _relative(path: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(PROJECT_ROOT))
    except ValueError:
        return str(path)
