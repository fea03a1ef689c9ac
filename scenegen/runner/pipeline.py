"""A batch run: propose -> check -> build -> settle -> render -> store, committed in proposal-index order.

:func:`process_proposal` is a pure function of a proposal and the recipe: it returns either an
accepted scene (record, MJCF, images) or a rejection. It runs in this process (``workers=1``) or in
a spawn-based pool whose workers each own one GL context. :func:`run_batch` is the only writer of the
store and commits outcomes strictly in proposal-index order, so the accepted set is the N
lowest-index accepted proposals whatever the number of workers, and a killed batch resumes exactly.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
from collections import Counter, deque
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import yaml

from scenegen import __version__
from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.check.geometry import run_checks
from scenegen.manifest.derive import SCENE_PACKAGES, package_versions
from scenegen.propose.base import PROPOSERS, Proposer
from scenegen.render.offscreen import RENDER_SETTINGS  # settings only: no GL is touched at import
from scenegen.runner.config import PipelineConfig, RealismFilter
from scenegen.schema.scene import CheckResult, Rejection, SceneProposal, SceneRecord, SettledObject
from scenegen.settle.physics import contact_configuration, free_bodies, rotation_angle, settle
from scenegen.sim import world
from scenegen.store.batch import BatchStore, atomic_write, scene_xml
from scenegen.tags.predicates import PREDICATE_VERSION, condition_check, scene_tags

STAGES = ("propose", "check", "build", "settle", "tag", "render", "store")
PROPOSAL_CHUNK = 8  # proposals drawn at a time (each is independent of the chunking)


@dataclass
class Outcome:
    """Result of processing one proposal: a record + MJCF + images, or a rejection."""

    proposal_index: int
    record: SceneRecord | None = None
    xml: str = ""
    needed: dict[str, str] = field(default_factory=dict)
    images: dict[str, bytes] = field(default_factory=dict)
    rejection: Rejection | None = None
    seconds: dict[str, float] = field(default_factory=dict)


def process_proposal(
    proposal: SceneProposal, config: PipelineConfig, catalog: Catalog, export: bool = True
) -> Outcome:
    """Check, build, settle, tag and render one proposal; on success, the scene record, MJCF and images.

    ``export=False`` skips the MJCF (layout-only datasets such as the reference set do not store it).
    """
    out = Outcome(proposal.index)
    t0 = time.perf_counter()
    checks, ok = run_checks(proposal, catalog, config.checks)
    out.seconds["check"] = time.perf_counter() - t0
    if not ok:
        out.rejection = Rejection.from_check(proposal.index, checks[-1])
        return out

    t0 = time.perf_counter()
    spec = world.build_world(
        catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras
    )
    model = spec.compile()
    qpos0, ctrl = world.initial_state(model, proposal.condition.robot_pose, proposal.objects)
    out.seconds["build"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    settled = settle(model, proposal, qpos0, ctrl, config.settle, catalog)
    out.seconds["settle"] = time.perf_counter() - t0
    checks += settled.checks
    if not settled.passed:
        failed = next(c for c in settled.checks if not c.passed)
        out.rejection = Rejection.from_check(proposal.index, failed)
        return out

    t0 = time.perf_counter()
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = settled.qpos, settled.ctrl
    mujoco.mj_forward(model, data)
    contacts = contact_configuration(model, settled.qpos, [o.name for o in proposal.objects])
    tags = scene_tags(model, data, catalog, proposal, contacts, config.tags)
    checks.append(condition_check(tags, proposal.condition))
    if checks[-1].passed:  # settled poses and the realism score only for scenes that meet the request
        objects = settled_objects(model, proposal, settled.qpos)
        if config.realism is not None:
            checks.append(realism_check(proposal, objects, config.realism))
    out.seconds["tag"] = time.perf_counter() - t0
    if not checks[-1].passed:
        out.rejection = Rejection.from_check(proposal.index, checks[-1])
        return out

    segmentation: dict[str, int] = {}
    if config.render:
        t0 = time.perf_counter()
        rendered = _render(model, data, proposal)
        if isinstance(rendered, Rejection):
            out.rejection = rendered
            return out
        out.images, segmentation = rendered
        out.seconds["render"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if export:
        out.xml, out.needed = scene_xml(spec, settled.qpos, settled.ctrl, dict(free_bodies(model)))
    out.record = SceneRecord(
        scene_id=f"scene_{proposal.index:06d}",
        proposal_index=proposal.index,
        seed=proposal.seed,
        condition=proposal.condition,
        generator={"kind": config.proposer.kind, "settings": config.proposer.model_dump(mode="json")},
        target=proposal.target,
        objects=tuple(objects),
        furniture=proposal.furniture,
        lighting=proposal.lighting,
        cameras=tuple(_camera_entry(cam, config.render) for cam in proposal.cameras),
        tags=tags,
        predicate_version=PREDICATE_VERSION,
        segmentation=segmentation,
        render=RENDER_SETTINGS if config.render else None,
        contacts=tuple(contacts),
        contact_options=world.CONTACT_OPTIONS,
        checks=tuple(checks),
        settle=settled.stats,
        provenance={
            "scenegen": __version__,
            "packages": package_versions(SCENE_PACKAGES),
            "pipeline": config.name,
            "pipeline_sha256": config.digest(),
            "catalog_sha256": catalog.sha256,
        },
    )
    out.seconds["store"] = time.perf_counter() - t0  # record + MJCF export; file writes are added later
    return out


def _render(model, data, proposal: SceneProposal) -> tuple[dict[str, bytes], dict[str, int]] | Rejection:
    """PNG files of every camera (rgb, depth, seg) and the segmentation ids; a ``render_failed``
    rejection when the renderer fails on this scene."""
    from scenegen.render.offscreen import frames_to_files, process_renderer, segmentation_ids

    segmentation = segmentation_ids(
        model, [o.name for o in proposal.objects], [f.name for f in proposal.furniture]
    )
    try:
        frames = process_renderer().render(
            model,
            data,
            [c.name for c in proposal.cameras],
            segmentation,
            [(c.width, c.height) for c in proposal.cameras],
        )
    except Exception as exc:  # noqa: BLE001 - a scene that cannot be rendered is rejected, not fatal
        result = CheckResult(
            stage="render", check="render", passed=False, label="render_failed", detail=str(exc)[:200]
        )
        return Rejection.from_check(proposal.index, result)
    images: dict[str, bytes] = {}
    for cam, frame in zip(proposal.cameras, frames, strict=True):
        images.update(frames_to_files(cam.name, frame))
    return images, segmentation


def settled_objects(model: mujoco.MjModel, proposal: SceneProposal, qpos) -> list[SettledObject]:
    """The proposal's objects at their settled poses (``qpos``), with how far each moved and turned."""
    bodies = dict(free_bodies(model))
    objects = []
    for obj in proposal.objects:
        adr = bodies[obj.name]
        pos, quat = qpos[adr : adr + 3], qpos[adr + 3 : adr + 7]
        moved = sum((a - b) ** 2 for a, b in zip(pos, obj.position, strict=True)) ** 0.5
        objects.append(
            SettledObject(
                **obj.model_dump(exclude={"position", "quat"}),
                position=tuple(round(float(v), 6) for v in pos),
                quat=tuple(round(float(v), 6) for v in quat),
                moved=round(float(moved), 6),
                rotated=round(rotation_angle(quat, obj.quat), 6),
            )
        )
    return objects


def realism_check(
    proposal: SceneProposal, objects: list[SettledObject], settings: RealismFilter
) -> CheckResult:
    """The per-scene realism score of a settled scene against the reference set (``unrealistic`` below
    ``settings.min_score``; scenegen.analysis.scene_score.SceneScorer)."""
    from scenegen.analysis.scene_score import (  # torch: only when the filter is on
        placement_row,
        reference_scorer,
    )

    row = placement_row(proposal.target, objects, proposal.furniture, proposal.lighting)
    score = round(reference_scorer(settings.reference, settings.k).score(row), 6)
    passed = score >= settings.min_score
    return CheckResult(
        stage="tag",
        check="realism_score",
        passed=passed,
        label=None if passed else "unrealistic",
        value=score,
        threshold=settings.min_score,
        detail=f"share of reference layouts at least as far from their {settings.k} nearest neighbours",
    )


def _camera_entry(cam, rendered: bool = True) -> dict:
    rot = world.camera_rotation(cam)
    return {
        **cam.model_dump(mode="json"),
        "intrinsics": {k: round(v, 6) for k, v in cam.intrinsics().items()},
        "extrinsics": {
            "convention": "camera-to-world; camera axes x right, y up, looking along -z (MuJoCo/OpenGL)",
            "position": list(cam.position),
            "rotation": [[round(float(v), 7) for v in row] for row in rot],
        },
        **({"images": {k: f"{cam.name}_{k}.png" for k in ("rgb", "depth", "seg")}} if rendered else {}),
    }


# ------------------------------------------------------------------------------------- workers

_WORKER: tuple[PipelineConfig, Catalog, bool] | None = None


def _init_worker(config_json: str, pooled: bool = False, export: bool = True) -> None:
    """Pool initializer: load the recipe and catalog once, and open this worker's GL context."""
    global _WORKER
    if pooled:
        # Mesa's llvmpipe rasterizes on every core by default; with one worker per core that thrashes.
        os.environ.setdefault("LP_NUM_THREADS", "1")
    config = PipelineConfig.model_validate_json(config_json)
    _WORKER = (config, load_catalog(), export)
    if config.render:
        from scenegen.render.offscreen import process_renderer

        process_renderer()


def _work(proposal: SceneProposal) -> Outcome:
    config, catalog, export = _WORKER
    try:
        return process_proposal(proposal, config, catalog, export)
    except StopIteration as exc:  # inside map() it would end the batch silently, as if out of proposals
        raise RuntimeError(f"proposal {proposal.proposal_index}: StopIteration in a stage") from exc


def _proposals(proposer: Proposer, config: PipelineConfig, start: int) -> Iterator[SceneProposal]:
    for first in range(start, config.proposal_cap, PROPOSAL_CHUNK):
        yield from proposer.propose(
            config.condition, range(first, min(first + PROPOSAL_CHUNK, config.proposal_cap)), config.seed
        )


def ordered_outcomes(
    proposals: Iterator[SceneProposal], config: PipelineConfig, workers: int, export: bool = True
) -> Iterator[Outcome]:
    """Outcomes of ``proposals`` in their order, computed here or in a spawn pool of ``workers``.

    Closing the generator (or leaving the loop that consumes it) stops the pool.
    """
    if workers <= 1:
        _init_worker(config.model_dump_json(), False, export)
        yield from map(_work, proposals)
        return
    # concurrent.futures rather than multiprocessing.Pool: a worker that dies (or whose initializer
    # fails) breaks the pool with an error instead of being respawned forever.
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_worker,
        initargs=(config.model_dump_json(), True, export),
    )
    try:
        pending: deque = deque()
        for proposal in proposals:
            pending.append(pool.submit(_work, proposal))
            if len(pending) >= 4 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@dataclass
class BatchSummary:
    out: Path
    accepted: int
    proposals: int
    rejections: Counter
    seconds: dict[str, float]
    accepted_seconds: dict[str, float]
    wall: float


def run_batch(config: PipelineConfig, out: Path, workers: int = 1, progress: bool = True) -> BatchSummary:
    """Generate ``config.n`` accepted scenes into ``out``, resuming a killed batch of the same recipe."""
    from tqdm import tqdm

    catalog = load_catalog()
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    store = BatchStore(out)
    state = store.open(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    seconds = dict.fromkeys(STAGES, 0.0)  # all proposals, summed over workers
    accepted_seconds = dict.fromkeys(STAGES, 0.0)  # accepted scenes only
    rejections, accepted, index = Counter(state.rejections), state.accepted, state.next_index
    done_before = state.accepted + sum(state.rejections.values())
    start = time.perf_counter()
    bar = tqdm(
        total=config.n,
        initial=accepted,
        desc=config.name,
        unit="scene",
        disable=not progress,
        dynamic_ncols=True,
    )

    proposals = _timed(_proposals(proposer, config, index), seconds)
    outcomes = ordered_outcomes(proposals, config, workers)  # lazy: no pool until iterated
    try:
        for outcome in outcomes if accepted < config.n else ():
            index = outcome.proposal_index + 1
            for stage, s in outcome.seconds.items():
                seconds[stage] += s
            t0 = time.perf_counter()
            if outcome.record is not None:
                store.commit_scene(outcome.record, outcome.xml, outcome.needed, outcome.images)
                accepted += 1
                for stage, s in outcome.seconds.items():
                    accepted_seconds[stage] += s
                bar.update(1)
            else:
                store.log_rejection(outcome.rejection)
                rejections[outcome.rejection.label] += 1
            seconds["store"] += time.perf_counter() - t0
            bar.set_postfix_str(
                f"proposals={index} " + " ".join(f"{k}={v}" for k, v in sorted(rejections.items())),
                refresh=False,
            )
            if accepted == config.n:
                break
    finally:
        outcomes.close()  # stops the pool now, not at garbage collection
        bar.close()
    wall = time.perf_counter() - start
    write_batch_manifest(out, config, catalog.sha256)
    proposals_done = accepted + sum(rejections.values())
    timing = {
        "wall": round(wall, 3),
        "workers": workers,
        "stages": {k: round(v, 3) for k, v in seconds.items()},
        "proposals_this_run": proposals_done - done_before,
    }
    atomic_write(out / "timings.json", json.dumps(timing, indent=1) + "\n")
    return BatchSummary(out, accepted, proposals_done, rejections, seconds, accepted_seconds, wall)


def write_batch_manifest(out: Path, config: PipelineConfig, catalog_sha: str):
    """Derive the batch's source from its files, compute its realism checks, and write
    ``out/manifest.yaml`` atomically (a run killed here leaves the previous manifest or none)."""
    from scenegen.manifest import Manifest, write_manifest
    from scenegen.manifest.derive import batch_source
    from scenegen.manifest.realism_checks import batch_realism

    source = batch_source(out, config, catalog_sha, PREDICATE_VERSION)
    source = source.model_copy(update={"realism": batch_realism(out, config, source.checksums.root)})
    manifest = Manifest(kind="batch", sources=[source])
    write_manifest(out / "manifest.yaml", manifest)
    return manifest


def _timed(proposals: Iterator[SceneProposal], seconds: dict[str, float]) -> Iterator[SceneProposal]:
    """Pass proposals through, adding the time spent making them to ``seconds['propose']``."""
    while True:
        t0 = time.perf_counter()
        proposal = next(proposals, None)
        seconds["propose"] += time.perf_counter() - t0
        if proposal is None:
            return
        yield proposal
