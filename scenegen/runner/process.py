"""One proposal through check -> build -> settle -> tag -> render: a pure function of (proposal, recipe).

:func:`process_proposal` returns either an accepted scene (record, MJCF, images) or a rejection; it
never writes. :func:`init_worker` / :func:`work` run it in a worker process (a local pool or a Ray
actor: scenegen/runner/executors.py), which loads the recipe and catalog once and owns one GL context.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import mujoco

from scenegen import __version__
from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.check.geometry import run_checks
from scenegen.manifest.derive import SCENE_PACKAGES, package_versions
from scenegen.render.offscreen import RENDER_SETTINGS  # settings only: no GL is touched at import
from scenegen.runner.config import PipelineConfig, RealismFilter
from scenegen.schema.scene import CheckResult, Rejection, SceneProposal, SceneRecord, SettledObject
from scenegen.settle.physics import contact_configuration, free_bodies, rotation_angle, settle
from scenegen.sim import world
from scenegen.store.batch import scene_xml
from scenegen.tags.predicates import PREDICATE_VERSION, condition_check, scene_tags


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


def init_worker(config_json: str, pooled: bool = False, export: bool = True) -> None:
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


def work(proposal: SceneProposal) -> Outcome:
    """:func:`process_proposal` with the recipe and catalog :func:`init_worker` loaded."""
    config, catalog, export = _WORKER
    try:
        return process_proposal(proposal, config, catalog, export)
    except StopIteration as exc:  # inside map() it would end the batch silently, as if out of proposals
        raise RuntimeError(f"proposal {proposal.proposal_index}: StopIteration in a stage") from exc
