"""A batch run: propose -> check -> build -> settle -> store, in proposal-index order.

:func:`process_proposal` is a pure function of a proposal (and the recipe): it returns either an
accepted scene (record and MJCF) or a rejection. :func:`run_batch` feeds it proposals in index order
until ``n`` scenes are accepted or the proposal cap is hit, and is the only writer of the store.
"""

from __future__ import annotations

import importlib.metadata
import json
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from scenegen import __version__, world
from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.check.geometry import run_checks
from scenegen.config import PipelineConfig
from scenegen.manifest import Manifest, batch_source, write_manifest
from scenegen.propose.base import PROPOSERS
from scenegen.schema.scene import Rejection, SceneProposal, SceneRecord, SettledObject
from scenegen.settle import contact_configuration, free_bodies, rotation_angle, settle
from scenegen.store import BatchStore, atomic_write, scene_xml

STAGES = ("propose", "check", "build", "settle", "store")
PROPOSAL_CHUNK = 8  # proposals drawn at a time (each is independent of the chunking)


@dataclass
class Outcome:
    """Result of processing one proposal: a record + MJCF, or a rejection."""

    proposal_index: int
    record: SceneRecord | None = None
    xml: str = ""
    needed: dict[str, str] = field(default_factory=dict)
    rejection: Rejection | None = None
    seconds: dict[str, float] = field(default_factory=dict)


def _versions() -> dict[str, str]:
    names = ("mujoco", "robosuite", "trimesh", "coacd", "python-fcl", "numpy", "pydantic")
    return {n: importlib.metadata.version(n) for n in names}


def process_proposal(proposal: SceneProposal, config: PipelineConfig, catalog: Catalog) -> Outcome:
    """Check, build, settle one proposal; on success, the scene record and its MJCF."""
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
    settled = settle(model, proposal, qpos0, ctrl, config.settle)
    out.seconds["settle"] = time.perf_counter() - t0
    checks += settled.checks
    if not settled.passed:
        failed = next(c for c in settled.checks if not c.passed)
        out.rejection = Rejection.from_check(proposal.index, failed)
        return out

    t0 = time.perf_counter()
    bodies = dict(free_bodies(model))
    objects = []
    for obj in proposal.objects:
        adr = bodies[obj.name]
        pos, quat = settled.qpos[adr : adr + 3], settled.qpos[adr + 3 : adr + 7]
        moved = sum((a - b) ** 2 for a, b in zip(pos, obj.position, strict=True)) ** 0.5
        rotated = rotation_angle(quat, obj.quat)
        objects.append(
            SettledObject(
                **obj.model_dump(exclude={"position", "quat"}),
                position=tuple(round(float(v), 6) for v in pos),
                quat=tuple(round(float(v), 6) for v in quat),
                moved=round(float(moved), 6),
                rotated=round(rotated, 6),
            )
        )
    contacts = contact_configuration(model, settled.qpos, [o.name for o in proposal.objects])
    out.xml, out.needed = scene_xml(spec, settled.qpos, settled.ctrl, bodies)
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
        cameras=tuple(_camera_entry(cam) for cam in proposal.cameras),
        contacts=tuple(contacts),
        contact_options=world.CONTACT_OPTIONS,
        checks=tuple(checks),
        settle=settled.stats,
        provenance={
            "scenegen": __version__,
            "packages": _versions(),
            "pipeline": config.name,
            "pipeline_sha256": config.digest(),
            "catalog_sha256": catalog.sha256,
        },
    )
    out.seconds["store"] = time.perf_counter() - t0  # record + MJCF export; file writes are added later
    return out


def _camera_entry(cam) -> dict:
    rot = world.camera_rotation(cam)
    return {
        **cam.model_dump(mode="json"),
        "intrinsics": {k: round(v, 6) for k, v in cam.intrinsics().items()},
        "extrinsics": {
            "convention": "camera-to-world; camera axes x right, y up, looking along -z (MuJoCo/OpenGL)",
            "position": list(cam.position),
            "rotation": [[round(float(v), 7) for v in row] for row in rot],
        },
    }


@dataclass
class BatchSummary:
    out: Path
    accepted: int
    proposals: int
    rejections: Counter
    seconds: dict[str, float]
    wall: float


def run_batch(config: PipelineConfig, out: Path, progress: bool = True) -> BatchSummary:
    """Generate ``config.n`` accepted scenes into ``out`` (which must be new or empty)."""
    from tqdm import tqdm

    catalog = load_catalog()
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    store = BatchStore(out)
    store.prepare(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    seconds = dict.fromkeys(STAGES, 0.0)
    rejections: Counter = Counter()
    accepted = index = 0
    start = time.perf_counter()
    bar = tqdm(total=config.n, desc=f"{config.name}", unit="scene", disable=not progress, dynamic_ncols=True)
    while accepted < config.n and index < config.proposal_cap:
        t0 = time.perf_counter()
        chunk = range(index, min(index + PROPOSAL_CHUNK, config.proposal_cap))
        proposals = proposer.propose(config.condition, chunk, config.seed)
        seconds["propose"] += time.perf_counter() - t0
        for proposal in proposals:
            index = proposal.index + 1
            outcome = process_proposal(proposal, config, catalog)
            for stage, s in outcome.seconds.items():
                seconds[stage] += s
            t0 = time.perf_counter()
            if outcome.record is not None:
                store.commit_scene(outcome.record, outcome.xml, outcome.needed)
                accepted += 1
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
    bar.close()
    wall = time.perf_counter() - start
    source = batch_source(
        out,
        name=config.name,
        pipeline={"name": config.name, "sha256": config.digest(), "file": "pipeline.yaml"},
        generator={"kind": config.proposer.kind},
        seed=config.seed,
        catalog_sha=catalog.sha256,
    )
    write_manifest(out / "manifest.yaml", Manifest(kind="batch", sources=[source]))
    timing = {
        "wall": round(wall, 3),
        "stages": {k: round(v, 3) for k, v in seconds.items()},
        "proposals": index,
    }
    atomic_write(out / "timings.json", json.dumps(timing, indent=1) + "\n")
    return BatchSummary(out, accepted, index, rejections, seconds, wall)
