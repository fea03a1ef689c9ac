"""A batch's scenes, checked for ``scenegen audit`` (files.py's :func:`~scenegen.audit.files.audit_batch`
calls :func:`check_scenes`): every file a scene.json lists against its checksum, inside the batch,
its repair path and predicate version; and a seeded sample of scenes whose images' stored statistics
are re-measured from the pixels. The scenes are checked in jobs of ``SCENES_PER_JOB`` on the audit's
workers and backend (runner/executors.py), each job's findings replayed in index order by the
coordinator, so the report does not depend on how many workers there are.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from scenegen.core.files import SCENE_ID
from scenegen.manifest.schema import Source
from scenegen.store.batch import ASSETS, INDEX

SCENES_PER_JOB = 50  # scenes a worker checks per job: large enough that a job's overhead is small


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


def check_scenes(audit, where: str, source: Source, batch: Path, index: list[dict], repaired) -> set[str]:
    """Every scene of the index checked (``_scene``), in jobs of ``SCENES_PER_JOB`` scenes on the
    audit's workers and backend (runner/executors.py), a seeded sample of them with their images'
    statistics re-measured from the pixels (``_image_sample``); the findings reported in index order.
    Returns the files the scene.json files list."""
    from scenegen.runner.executors import ordered_map

    shared = {}
    assets = batch / ASSETS
    if assets.is_dir() and not assets.is_symlink():  # each shared file hashed once, here
        shared = {str(p): audit.file_sha256(p) for p in sorted(assets.iterdir()) if p.is_file()}
    sampled = _sample(index, audit.image_sample, audit.sample_seed)
    jobs = [
        (where, source.predicate_version, batch, chunk, _repairs_of(chunk, repaired), shared, sampled)
        for chunk in (index[i : i + SCENES_PER_JOB] for i in range(0, len(index), SCENES_PER_JOB))
    ]
    listed: set[str] = set()
    measured = 0
    for found, files, images in ordered_map(_scene_job, jobs, audit.workers, backend=audit.backend):
        for finding in found:
            audit.violation(*finding)
        listed |= files
        measured += images
    if measured:
        audit.report.verified.append(
            f"{where}: image statistics of a seeded sample of {len(sampled)} of {len(index)} scenes "
            f"(seed {audit.sample_seed}; {measured} images) re-measured from their pixels, each equal to "
            "the statistics its scene.json stores (within 1e-9); the batch's image check recomputed "
            "from the stored statistics of every image"
        )
    return listed


def _repairs_of(chunk: list[dict], repaired: set[tuple]) -> frozenset[tuple]:
    """The repaired tries of the chunk's proposals (what their repair paths may name)."""
    proposals = {row.get("proposal_index") for row in chunk}
    return frozenset(r for r in repaired if r[0] in proposals)


def _sample(index: list[dict], size: int, seed: int) -> frozenset[str]:
    """The scene ids whose images are re-measured: ``size`` of the index's drawn without replacement
    by ``seed`` (all when ``size`` is at least the batch; none when 0)."""
    import numpy as np

    ids = sorted({str(r.get("scene_id")) for r in index})
    if size >= len(ids):
        return frozenset(ids)
    return frozenset(np.random.default_rng(seed).choice(ids, size=size, replace=False).tolist())


def _scene_job(job: tuple) -> tuple[list[tuple], set[str], int]:
    """One worker job: the scenes of ``chunk`` checked, the sampled ones' images re-measured."""
    where, predicate_version, batch, chunk, repaired, shared, sampled = job
    findings = _Findings(shared)
    listed: set[str] = set()
    measured = 0
    for row in chunk:
        files = _scene(findings, where, predicate_version, batch, row, repaired)
        listed |= files
        if files and row.get("scene_id") in sampled:
            measured += _image_sample(findings, where, batch, row["scene_id"])
    return findings.found, listed, measured


def _image_sample(findings, where: str, batch: Path, scene_id: str) -> int:
    """Re-measure the RGB images of one scene whose scene.json stores their statistics; a camera
    whose stored statistics differ from its pixels' is a violation. Returns the images measured."""
    import numpy as np

    from scenegen.analysis.image_stats import image_statistics, read_rgb

    scene_dir = batch / scene_id
    try:
        cameras = json.loads((scene_dir / "scene.json").read_bytes())["cameras"]
    except (OSError, ValueError, KeyError, TypeError):
        return 0  # already reported by the checksum check
    measured = 0
    for camera in cameras:
        stored, name = camera.get("image_stats"), (camera.get("images") or {}).get("rgb")
        if stored is None or name is None or "/" in str(name):
            continue  # a batch from before the statistics were stored: the image check measures it all
        try:
            pixels = image_statistics(read_rgb(scene_dir / str(name)))
        except ValueError as exc:
            findings.violation(f"{where}: {scene_id}/{name}", "realism", str(exc)[:200])
            continue
        measured += 1
        if len(stored) != len(pixels) or not np.allclose(pixels, stored, rtol=0.0, atol=1e-9):
            findings.violation(
                f"{where}: {scene_id}/scene.json",
                "realism",
                f"camera {camera.get('name')!r}: the stored image statistics differ from its pixels'",
            )
    return measured


def _scene(audit, where: str, predicate_version, batch: Path, row: dict, repaired=frozenset()) -> set[str]:
    """Check one scene of the index; returns the paths its scene.json lists (``batch`` resolved, no
    link followed). ``repaired``: the (proposal index, attempt) of every rejection row a repair
    followed: each step of the scene's repair path must have its failed parent there."""
    scene_id = row.get("scene_id")
    if not isinstance(scene_id, str) or not SCENE_ID.match(scene_id):
        audit.violation(f"{where}: {INDEX}", "count", f"an index row names scene {scene_id!r}")
        return set()
    scene_dir, at = batch / scene_id, f"{where}: {scene_id}"
    scene_json = scene_dir / "scene.json"
    if not scene_json.is_file():
        audit.violation(at, "missing_scene", f"listed in {INDEX} but its directory or scene.json is missing")
        return set()
    if scene_dir.is_symlink() or scene_json.is_symlink():  # a batch's writer makes no link
        audit.violation(f"{at}/scene.json", "location", "a link out of the batch")
        return set()
    text = scene_json.read_bytes()
    if hashlib.sha256(text).hexdigest() != row.get("scene_json_sha256"):
        audit.violation(f"{at}/scene.json", "checksum", f"sha256 differs from its {INDEX} row")
    try:
        record = json.loads(text)
        files = record["files"]
        assert isinstance(files, dict) and all(isinstance(v, str) for v in files.values())
    except (ValueError, KeyError, TypeError, AssertionError):
        audit.violation(f"{at}/scene.json", "checksum", "not a scene record with a files mapping")
        return set()
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
    return listed
