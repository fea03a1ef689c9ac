"""A batch's scenes, checked for ``scenegen audit`` (files.py's :func:`~scenegen.audit.files.audit_batch`
calls :func:`check_scenes`): every file a scene.json lists against its checksum, inside the batch,
its repair path and predicate version; and, for a rendered batch, the RGB images of a seeded sample of
its scenes (all of them when the sample is the batch) decoded and measured for the image check
(:func:`compare_image_sample`). The scenes are checked in jobs of ``SCENES_PER_JOB`` on the audit's
workers and backend (runner/executors.py), each job's findings replayed in index order by the
coordinator, so the report does not depend on how many workers there are.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

from scenegen.core.files import SCENE_ID
from scenegen.manifest.schema import RealismCheck, Source
from scenegen.store.batch import ASSETS, INDEX

SCENES_PER_JOB = 50  # scenes a worker checks per job: large enough that a job's overhead is small
# A recorded image statistic agrees with a sample when it lies within the sample's estimate plus or
# minus t standard errors, t the Student quantile with n - 1 degrees of freedom (n sampled scenes) of
# this two-sided tail: 6e-5 per statistic, about 1 false alarm in 1,800 audits of a faithful batch
# over the 9 statistics (t = 4.1 at n = 200; wide at a handful of scenes, whose spread is unsure).
SAMPLE_TAIL = 6e-5
# The least standard error the rule grants, in reference standard deviations: a sample can miss the
# few scenes that move a statistic (all its scenes without an underexposed pixel, say), and then
# measures no spread at all. So a sampled audit verifies each difference to +-t x 0.05 at least.
SAMPLE_ERROR_FLOOR = 0.05


@dataclass
class ImageSample:
    """The RGB images of a batch that its scene checks measured: ``rows``, (scene id, statistic rows
    (cameras, S)) of each sampled scene in index order; ``scenes`` and ``images``, how many the batch's
    readable scene records list; ``seed``, the sample's."""

    scenes: int
    images: int
    rows: list
    seed: int

    @property
    def whole(self) -> bool:
        return len(self.rows) == self.scenes

    def measured(self) -> tuple:
        """(rows (N, S), scene ids) of every measured image, as ``image_check`` takes them."""
        import numpy as np

        if not self.rows:
            return np.zeros((0, 0)), []
        return np.concatenate([r for _, r in self.rows]), [i for i, r in self.rows for _ in range(len(r))]


class _Findings:
    """What a worker's job found: the audit's ``violation``/``file_sha256`` interface, recorded in
    order for the coordinator to replay; the shared ``_assets/`` files' hashes come from it."""

    def __init__(self, shared: dict[str, str | None]):
        self.shared, self.found = shared, []

    def violation(self, where: str, check: str, message: str) -> None:
        self.found.append((where, check, message))

    def file_sha256(self, path: Path) -> str | None:
        from scenegen.store.batch import sha256_file

        return self.shared[str(path)] if str(path) in self.shared else sha256_file(path)


def check_scenes(
    audit, where: str, source: Source, batch: Path, index: list[dict], repaired
) -> tuple[set[str], ImageSample | None]:
    """Every scene of the index checked (``_scene``), in jobs of ``SCENES_PER_JOB`` scenes on the
    audit's workers and backend (runner/executors.py), the findings reported in index order; for a
    rendered source, the images of ``audit.image_sample`` scenes drawn by ``audit.sample_seed`` (None:
    every scene) measured too. Returns the files the scene.json files list, and the images measured
    (None for a batch without rendering)."""
    from scenegen.runner.executors import ordered_map

    shared = {}
    assets = batch / ASSETS
    if assets.is_dir() and not assets.is_symlink():  # each shared file hashed once, here
        shared = {str(p): audit.file_sha256(p) for p in sorted(assets.iterdir()) if p.is_file()}
    sampled = _sample(index, audit.image_sample, audit.sample_seed) if source.rendered else frozenset()
    jobs = [
        (
            where,
            (source.predicate_version, source.sensor),
            batch,
            chunk,
            _repairs_of(chunk, repaired),
            shared,
            sampled,
        )  # fmt: skip
        for chunk in (index[i : i + SCENES_PER_JOB] for i in range(0, len(index), SCENES_PER_JOB))
    ]
    listed: set[str] = set()
    images = ImageSample(0, 0, [], audit.sample_seed)
    for found, files, cameras, rows in ordered_map(_scene_job, jobs, audit.workers, backend=audit.backend):
        for finding in found:
            audit.violation(*finding)
        listed |= files
        images.scenes += len(cameras)
        images.images += sum(cameras)
        images.rows += rows
    return listed, (images if source.rendered else None)


def _repairs_of(chunk: list[dict], repaired: set[tuple]) -> frozenset[tuple]:
    """The repaired tries of the chunk's proposals (what their repair paths may name)."""
    proposals = {row.get("proposal_index") for row in chunk}
    return frozenset(r for r in repaired if r[0] in proposals)


def _sample(index: list[dict], size: int | None, seed: int) -> frozenset[str] | None:
    """The scene ids whose images are measured: ``size`` of the index's drawn without replacement by
    ``seed``; None (every scene) when ``size`` is None or at least the batch."""
    import numpy as np

    ids = sorted({str(r.get("scene_id")) for r in index})
    if size is None or size >= len(ids):
        return None
    return frozenset(np.random.default_rng(seed).choice(ids, size=size, replace=False).tolist())


def _scene_job(job: tuple) -> tuple[list[tuple], set[str], list[int], list[tuple]]:
    """One worker job: the scenes of ``chunk`` checked; the RGB camera count of each readable scene
    record, and the sampled scenes' image statistic rows (empty ``sampled``: none measured)."""
    where, (predicate_version, sensor), batch, chunk, repaired, shared, sampled = job
    findings = _Findings(shared)
    listed: set[str] = set()
    cameras, rows = [], []
    for row in chunk:
        files, record = _scene(findings, where, predicate_version, batch, row, repaired)
        if record is not None:
            _sensor(findings, f"{where}: {row['scene_id']}/scene.json", record, sensor)
        listed |= files
        if record is None or sampled == frozenset():
            continue
        listed_cameras = record.get("cameras")
        cameras.append(len(listed_cameras) if isinstance(listed_cameras, list) else 0)
        if sampled is None or row["scene_id"] in sampled:
            measured = _measure(findings, where, batch, row["scene_id"], record)
            if measured is not None:
                rows.append((row["scene_id"], measured))
    return findings.found, listed, cameras, rows


def _measure(findings, where: str, batch: Path, scene_id: str, record: dict):
    """The statistic rows of one scene's RGB images, or None (a violation) when one cannot be read."""
    from scenegen.analysis.image_stats import scene_statistics

    try:
        return scene_statistics(record, batch / scene_id, batch)[1]
    except (ValueError, KeyError, TypeError, AttributeError) as exc:  # a damaged camera list
        findings.violation(f"{where}: {scene_id}", "realism", f"its images: {exc}"[:300])
        return None


def compare_image_sample(audit, where: str, recorded: RealismCheck, sample: RealismCheck, images) -> None:
    """The recorded ``image_stats`` check against a seeded sample of the batch's scenes (``sample``:
    the check recomputed on the sample alone, ``images``: the :class:`ImageSample`). Exact: the
    reference, threshold and comparison; the counts (the batch's scenes and images, from their
    records); the value, the largest |per-statistic difference| recorded; the status that value
    gives. Statistical: each recorded statistic within t standard errors of the sample's estimate
    (analysis/image_stats.sampled_smd), by the rule of ``SAMPLE_TAIL`` and ``SAMPLE_ERROR_FLOOR``.
    The rule and the sample are stated in the report."""
    import numpy as np
    from scipy import stats

    from scenegen.analysis.image_stats import load_reference_image_stats, sampled_smd
    from scenegen.manifest.realism_checks import REFERENCE_IMAGES, check_status

    at = f"{where}.realism image_stats"
    counts = {"batch": images.scenes, "images": images.images, "reference": sample.samples.get("reference")}
    judged = "per_stat" in (sample.details or {})  # else not computed (user categories, too few images)
    exact = ("threshold", "comparison", "reference", "min_samples")
    for name in exact if judged else (*exact, "value", "status", "details"):
        if getattr(recorded, name) != getattr(sample, name):
            audit.violation(at, "realism", f"recomputed from the files, {name} differs")
    if recorded.samples != counts:
        audit.violation(at, "realism", f"samples {recorded.samples}; the batch's records give {counts}")
    if not judged:
        return None
    per_stat = (recorded.details or {}).get("per_stat")
    if not isinstance(per_stat, dict) or not per_stat:
        return audit.violation(at, "realism", "no per-statistic differences recorded to compare with")
    largest = max(abs(float(v)) for v in per_stat.values())
    if not math.isclose(recorded.value, largest, abs_tol=1e-6):
        audit.violation(at, "realism", f"value {recorded.value} is not its largest |per_stat| ({largest})")
    status = check_status(images.scenes, recorded.value, recorded.threshold, counts["reference"] or 0)
    if recorded.status != status:
        audit.violation(at, "realism", f"status {recorded.status}, its value gives {status}")
    reference, _ = load_reference_image_stats(REFERENCE_IMAGES)
    try:
        estimate, error = sampled_smd([r for _, r in images.rows], images.scenes, reference)
    except ValueError as exc:  # too few of the sampled scenes' images could be read
        return audit.violation(at, "realism", f"the sample cannot judge the check: {exc}")
    t = float(stats.t.ppf(1 - SAMPLE_TAIL / 2, len(images.rows) - 1))
    error = np.maximum(error, SAMPLE_ERROR_FLOOR)
    names = list(sample.details["per_stat"])
    far = [
        f"{name} {float(per_stat.get(name, math.nan)):+.4f} (sample {e:+.4f} +- {t * s:.4f})"
        for name, e, s in zip(names, estimate, error, strict=True)
        if not abs(float(per_stat.get(name, math.nan)) - e) <= t * s + 1e-6
    ]
    rule = (
        f"image_stats checked on a seeded sample of {len(images.rows)} of {images.scenes} scenes (seed "
        f"{images.seed}; {sum(len(r) for _, r in images.rows)} of {images.images} images decoded): each "
        f"recorded per-statistic difference within {t:.2f} standard errors of the sample's estimate "
        f"(ratio estimator over scenes, finite-population corrected, at least {SAMPLE_ERROR_FLOOR:g} "
        f"reference SDs; Student t, {len(images.rows) - 1} degrees of freedom, two-sided tail "
        f"{SAMPLE_TAIL:g} per statistic); value, status, counts and "
        "reference exact"
    )
    if far:
        audit.violation(at, "realism", f"{rule}; outside: {'; '.join(far[:3])}"[:500])
    else:
        audit.report.verified.append(f"{where}: {rule}")


def _sensor(audit, at: str, record: dict, sensor: dict | None) -> None:
    """A scene made with the manifest's depth sensor (name and version, or none) and, for one, each
    camera's sensor depth listed among its files (whose checksums :func:`_scene` verifies)."""
    recorded = (record.get("render") or {}).get("sensor")
    if recorded != sensor:
        made = recorded.get("name") if isinstance(recorded, dict) else recorded
        said = (sensor or {}).get("name")
        audit.violation(at, "sensor", f"render.sensor: {made} (or another version); the manifest: {said}")
        return
    if sensor is None:
        return
    files = record.get("files") or {}
    for cam in record.get("cameras") or []:
        listed = (cam.get("images") or {}).get("sensor_depth")
        if listed is None or listed not in files:
            audit.violation(at, "missing_file", f"camera {cam.get('name')}: its sensor depth is not listed")


def _scene(
    audit, where: str, predicate_version, batch: Path, row: dict, repaired=frozenset()
) -> tuple[set[str], dict | None]:
    """Check one scene of the index; returns the paths its scene.json lists (``batch`` resolved, no
    link followed) and its record (None when unreadable). ``repaired``: the (proposal index,
    attempt) of every rejection row a repair followed: each step of the scene's repair path must have
    its failed parent there."""
    scene_id = row.get("scene_id")
    if not isinstance(scene_id, str) or not SCENE_ID.match(scene_id):
        audit.violation(f"{where}: {INDEX}", "count", f"an index row names scene {scene_id!r}")
        return set(), None
    scene_dir, at = batch / scene_id, f"{where}: {scene_id}"
    scene_json = scene_dir / "scene.json"
    if not scene_json.is_file():
        audit.violation(at, "missing_scene", f"listed in {INDEX} but its directory or scene.json is missing")
        return set(), None
    if scene_dir.is_symlink() or scene_json.is_symlink():  # a batch's writer makes no link
        audit.violation(f"{at}/scene.json", "location", "a link out of the batch")
        return set(), None
    text = scene_json.read_bytes()
    if hashlib.sha256(text).hexdigest() != row.get("scene_json_sha256"):
        audit.violation(f"{at}/scene.json", "checksum", f"sha256 differs from its {INDEX} row")
    try:
        record = json.loads(text)
        files = record["files"]
        assert isinstance(files, dict) and all(isinstance(v, str) for v in files.values())
    except (ValueError, KeyError, TypeError, AssertionError):
        audit.violation(f"{at}/scene.json", "checksum", "not a scene record with a files mapping")
        return set(), None
    path = (record.get("provenance") or {}).get("repairs") or []
    missing = [
        step.get("parent") for step in path if (row.get("proposal_index"), step.get("parent")) not in repaired
    ]
    if missing:
        audit.violation(
            f"{at}/scene.json", "rejections", f"repair path names tries {missing[:3]} the rejection log lacks"
        )
    if record.get("predicate_version") != predicate_version:
        audit.violation(
            f"{at}/scene.json",
            "predicate_version",
            f"tagged by predicates {record.get('predicate_version')}, the manifest says {predicate_version}",
        )
    listed = set()
    for name, sha in sorted(files.items()):
        own = "/" not in name and name not in ("", ".", "..", "scene.json")
        shared = name.startswith(f"../{ASSETS}/") and "/" not in name[len(ASSETS) + 4 :]
        shared = shared and name[len(ASSETS) + 4 :] not in ("", ".", "..")
        # a name of its own folder or of _assets/ lies inside the batch unless a link leads out
        path = scene_dir / name if own else batch / ASSETS / name[len(ASSETS) + 4 :]
        if not (own or shared) or path.is_symlink():
            audit.violation(f"{at}/{name}", "location", "scene.json may list only its own files and _assets/")
        elif not path.is_file():
            audit.violation(f"{at}/{name}", "missing_file", "listed in scene.json but missing")
        elif audit.file_sha256(path) != sha:
            audit.violation(f"{at}/{name}", "checksum", "sha256 differs from scene.json's")
        else:
            listed.add(str(path))
    return listed, record
