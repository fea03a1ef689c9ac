"""One proposal through check -> build -> settle -> tag -> render: a pure function of (proposal, recipe).

:func:`process_proposal` returns either an accepted scene (record, MJCF, images) or a rejection; it
never writes. :func:`init_worker` / :func:`work` run it in a worker process (a local pool or a Ray
actor: scenegen/runner/executors.py), which loads the recipe and catalog once and owns one GL context.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import mujoco

from scenegen import __version__
from scenegen.assets.catalog import Catalog
from scenegen.check.geometry import run_checks
from scenegen.manifest.derive import SCENE_PACKAGES, package_versions, sensor_entry
from scenegen.render.offscreen import RENDER_SETTINGS  # settings only: no GL is touched at import
from scenegen.runner.config import PipelineConfig, RealismFilter, validate_config
from scenegen.schema.condition import RARE_TAGS
from scenegen.schema.scene import CheckResult, Rejection, SceneProposal, SceneRecord, SettledObject
from scenegen.settle.physics import contact_configuration, free_bodies, rotation_angle, settle
from scenegen.sim import world
from scenegen.store.batch import scene_xml
from scenegen.tags.predicates import PREDICATE_VERSION, condition_check, scene_tags


@dataclass
class Outcome:
    """Result of processing one proposal: a record + MJCF + images, or a rejection."""

    proposal_index: int
    attempt: int = 0  # the proposal's try (0: first pass; k: its k-th repair)
    record: SceneRecord | None = None
    xml: str = ""
    needed: dict[str, str] = field(default_factory=dict)
    images: dict[str, bytes] = field(default_factory=dict)
    rejection: Rejection | None = None
    seconds: dict[str, float] = field(default_factory=dict)  # wall seconds per stage
    cpu: dict[str, float] = field(default_factory=dict)  # this worker's CPU seconds per stage


class _Stopwatch:
    """Wall and CPU seconds of one stage at a time, into an outcome's ``seconds`` and ``cpu``."""

    def __init__(self, outcome: Outcome):
        self.outcome, self.wall, self.cpu = outcome, 0.0, 0.0

    def start(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def stop(self, stage: str) -> None:
        self.outcome.seconds[stage] = time.perf_counter() - self.wall
        self.outcome.cpu[stage] = time.process_time() - self.cpu


def process_proposal(
    proposal: SceneProposal, config: PipelineConfig, catalog: Catalog, export: bool = True
) -> Outcome:
    """Check, build, settle, tag and render one proposal; on success, the scene record, MJCF and images.

    ``export=False`` skips the MJCF (layout-only datasets such as the reference set do not store it).
    """
    out = Outcome(proposal.index, proposal.attempt)
    clock = _Stopwatch(out)
    clock.start()
    checks, ok = run_checks(proposal, catalog, config.checks)
    clock.stop("check")
    if not ok:
        out.rejection = Rejection.from_check(proposal.index, checks[-1], proposal.attempt)
        return out

    clock.start()
    spec = world.build_world(
        catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras, **config.supports
    )
    model = spec.compile()
    qpos0, ctrl = world.initial_state(model, proposal.condition.robot_pose, proposal.objects)
    clock.stop("build")

    clock.start()
    settled = settle(model, proposal, qpos0, ctrl, config.settle, catalog)
    clock.stop("settle")
    checks += settled.checks
    if not settled.passed:
        failed = next(c for c in settled.checks if not c.passed)
        out.rejection = Rejection.from_check(proposal.index, failed, proposal.attempt)
        return out

    clock.start()
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = settled.qpos, settled.ctrl
    mujoco.mj_forward(model, data)
    contacts = contact_configuration(model, settled.qpos, [o.name for o in proposal.objects])
    tags = scene_tags(model, data, catalog, proposal, contacts, config.tags)
    checks.append(condition_check(tags, proposal.condition))
    if checks[-1].passed:  # settled poses and the realism score only for scenes that meet the request
        objects = settled_objects(model, proposal, settled.qpos)
        if config.realism is not None:
            checks.append(realism_check(proposal, objects, config.realism, tags))
    clock.stop("tag")
    if not checks[-1].passed:
        out.rejection = Rejection.from_check(proposal.index, checks[-1], proposal.attempt)
        return out

    segmentation: dict[str, int] = {}
    if config.render:
        clock.start()
        rendered = _render(model, data, proposal, config.robot_mesh_detail or 1.0, config.sensor)
        if isinstance(rendered, Rejection):
            out.rejection = rendered
            return out
        out.images, segmentation = rendered
        clock.stop("render")

    clock.start()
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
        cameras=tuple(_camera_entry(cam, config.render, config.sensor) for cam in proposal.cameras),
        tags=tags,
        predicate_version=PREDICATE_VERSION,
        segmentation=segmentation,
        render=render_settings(config),
        contacts=tuple(contacts),
        contact_options=world.contact_options(**config.supports),
        checks=tuple(checks),
        settle=settled.stats,
        provenance={
            "scenegen": __version__,
            "packages": package_versions(SCENE_PACKAGES),
            "pipeline": config.name,
            "pipeline_sha256": config.digest(),
            "catalog_sha256": catalog.sha256,
            **({"catalogs": [f.model_dump() for f in catalog.files]} if config.catalogs else {}),
            **(
                {"repairs": [r.model_dump(mode="json") for r in proposal.repairs]} if proposal.repairs else {}
            ),
        },
    )
    clock.stop("store")  # record + MJCF export; file writes are added later
    return out


def render_settings(config: PipelineConfig) -> dict | None:
    """What scene.json records of how its images were drawn (None: not rendered)."""
    if not config.render:
        return None
    settings = dict(RENDER_SETTINGS)  # as before a setting existed when it is left at its default
    if config.robot_mesh_detail is not None:
        settings["robot_mesh_detail"] = config.robot_mesh_detail
    if (sensor := sensor_entry(config)) is not None:
        settings["sensor"] = sensor  # the sensor and what decides its frames
    return settings


def _render(
    model, data, proposal: SceneProposal, robot_detail: float = 1.0, sensor: str = "exact"
) -> tuple[dict[str, bytes], dict[str, int]] | Rejection:
    """PNG files of every camera (rgb, depth, seg, and the ``sensor``'s depth unless it is exact) and
    the segmentation ids; a ``render_failed`` rejection when the renderer fails on this scene."""
    from scenegen.render.offscreen import depth_png, frames_to_files, process_renderer, segmentation_ids

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
            robot_detail,
        )
    except Exception as exc:  # noqa: BLE001 - a scene that cannot be rendered is rejected, not fatal
        result = CheckResult(
            stage="render", check="render", passed=False, label="render_failed", detail=str(exc)[:200]
        )
        return Rejection.from_check(proposal.index, result, proposal.attempt)
    images: dict[str, bytes] = {}
    for cam, frame in zip(proposal.cameras, frames, strict=True):
        images.update(frames_to_files(cam.name, frame))
    if sensor != "exact":
        from scenegen.render.sensor import SENSORS, Sight

        for cam, frame in zip(proposal.cameras, frames, strict=True):
            sight = Sight(process_renderer(), model, data, cam.name, (cam.width, cam.height), segmentation,
                          frame.depth, frame.rgb)  # fmt: skip
            # seeded by the scene (its proposal index and seed) and the camera: the same bytes in any
            # worker, on a resumed run too
            point = f"scene_{proposal.index:06d}|{proposal.seed}|settled"
            images[sensor_depth_file(cam.name, sensor)] = depth_png(SENSORS[sensor].measure(sight, point))
    return images, segmentation


def sensor_depth_file(camera: str, sensor: str) -> str:
    """The file a camera's depth as ``sensor`` returns it is stored in (beside ``<cam>_depth.png``,
    the exact depth; the same uint16 millimetres, 0 = no return)."""
    return f"{camera}_depth_{sensor}.png"


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
    proposal: SceneProposal, objects: list[SettledObject], settings: RealismFilter, tags: dict | None = None
) -> CheckResult:
    """The per-scene realism score of a settled scene against the reference set (``unrealistic`` below
    ``settings.min_score``; scenegen.analysis.scene_score.SceneScorer). With ``compositions:
    per_tag``, a scene whose rare ``tags`` the reference holds together in fewer than k layouts is
    judged per tag (``composition_scores``), and the detail says so."""
    from scenegen.analysis.scene_score import (  # torch: only when the filter is on
        composition_scores,
        placement_row,
        reference_scorer,
    )

    row = placement_row(proposal.target, objects, proposal.furniture, proposal.lighting)
    held = [t for t in RARE_TAGS if tags and t in tags and tags[t].holds]
    judged = None
    if settings.compositions == "per_tag":
        judged = composition_scores(settings.reference, settings.k, held, row)
    if judged is None:
        score = round(reference_scorer(settings.reference, settings.k).score(row), 6)
        detail = f"share of reference layouts at least as far from their {settings.k} nearest neighbours"
    else:
        score, detail = judged.score, judged.detail()
    passed = score >= settings.min_score
    return CheckResult(
        stage="tag",
        check="realism_score",
        passed=passed,
        label=None if passed else "unrealistic",
        value=score,
        threshold=settings.min_score,
        detail=detail,
    )


def _camera_entry(cam, rendered: bool = True, sensor: str = "exact") -> dict:
    rot = world.camera_rotation(cam)
    return {
        **cam.model_dump(mode="json"),
        "intrinsics": {k: round(v, 6) for k, v in cam.intrinsics().items()},
        "extrinsics": {
            "convention": "camera-to-world; camera axes x right, y up, looking along -z (MuJoCo/OpenGL)",
            "position": list(cam.position),
            "rotation": [[round(float(v), 7) for v in row] for row in rot],
        },
        **({"images": _images(cam.name, sensor)} if rendered else {}),
    }


def _images(camera: str, sensor: str) -> dict[str, str]:
    images = {k: f"{camera}_{k}.png" for k in ("rgb", "depth", "seg")}
    if sensor != "exact":
        images["sensor_depth"] = sensor_depth_file(camera, sensor)
    return images


# ------------------------------------------------------------------------------------- workers

_WORKER: tuple[PipelineConfig, Catalog, bool] | None = None


def init_worker(config_json: str, pooled: bool = False, export: bool = True, scorer=None) -> None:
    """Pool initializer: load the recipe and catalog once, and open this worker's GL context.

    ``scorer``: the recipe's realism scorer (:func:`shared_state`), built once by the coordinator."""
    global _WORKER
    if pooled:
        # Mesa's llvmpipe rasterizes on every core by default; with one worker per core that thrashes.
        os.environ.setdefault("LP_NUM_THREADS", "1")
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")  # one worker per core (executors.one_blas_thread)
    config = validate_config(json.loads(config_json))
    if scorer is not None:
        from scenegen.analysis.scene_score import install_scorer

        install_scorer(config.realism.reference, config.realism.k, scorer)
    _WORKER = (config, config.catalog(), export)
    _warm_up(config, _WORKER[1])


def _warm_up(config: PipelineConfig, catalog: Catalog) -> None:
    """Pay a worker's first-scene costs at its start, while the coordinator draws the first proposals:
    MuJoCo's mesh cache (the robot's meshes decoded, ~0.7 s) and, with rendering, the GL context with
    every catalog mesh and texture uploaded and the robot's meshes decimated (~0.8 s). Scenes share
    that mesh table (sim/world.py: build_world), so the first scene finds them ready; nothing of a
    scene's output depends on this (its own model sets what it draws)."""
    model = world.build_world(catalog, []).compile()
    if config.render:
        from scenegen.render.offscreen import process_renderer

        process_renderer().prepare(model, config.robot_mesh_detail or 1.0)


def shared_state(config: PipelineConfig):
    """What the coordinator builds once and hands to every worker: the realism scorer (~3 s to
    build from the reference set, ~2.5 MB to send), or None without the filter."""
    if config.realism is None:
        return None
    from scenegen.analysis.scene_score import reference_scorer

    return reference_scorer(config.realism.reference, config.realism.k)


def work(proposal: SceneProposal) -> Outcome:
    """:func:`process_proposal` with the recipe and catalog :func:`init_worker` loaded."""
    config, catalog, export = _WORKER
    try:
        return process_proposal(proposal, config, catalog, export)
    except StopIteration as exc:  # inside map() it would end the batch silently, as if out of proposals
        raise RuntimeError(f"proposal {proposal.index}: StopIteration in a stage") from exc
