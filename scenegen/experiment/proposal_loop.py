"""The proposal model in closed loop (issue 63, point 4): at each decision the robot observes (through
a retrieval head, or the simulator's masks), the sampler proposes candidates from what it sees, the
model scores them and the best not yet executed is executed; after a failure, or after a push or a
pull, it observes again and proposes anew, up to ``ATTEMPTS`` attempts within the task's time limit.

As :func:`closed_loop.evaluate_policies`, in rounds over every (scene) still going: decide in a
worker (the frames rendered at the stored state; the decision job is given the scene, the state
and the model, never a store), then serve the attempt from the sequence store where the same
candidates were executed before (keyed by ``candidate_token``), else simulate the whole sequence
(``proposal_labels.simulate_candidates``). Decisions are kept in an observation store keyed by the
decision point, the sight and the model's folder digest, so a rerun decides nothing twice.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenegen.env.physics import physics_mark
from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.experiment.closed_loop import Workers, episode_env, loaded_perception, set_state
from scenegen.experiment.proposal_data import seen_frames
from scenegen.experiment.proposal_labels import DEFAULT_LABELS, LabelConfig, point_rng
from scenegen.experiment.sequences import (
    NOMINAL,
    Cost,
    ObservationStore,
    PathStore,
    Variant,
    candidate_token,
    sight,
)
from scenegen.manipulation.proposals import Candidate, SamplerConfig, sample_candidates
from scenegen.manipulation.task import TIME_LIMIT
from scenegen.policy.evaluate import ATTEMPTS
from scenegen.schema.condition import RARE_TAGS

# A decision proposes more than a layout's labels hold: scoring is cheap (0.095 CPU-s for 36
# candidates against 0.025 for the labels' 10; the frames cost 0.5-0.7 either way: docs/policy.md)
DECISIONS = dataclasses.replace(DEFAULT_LABELS, sampler=SamplerConfig(top=24, side=8, push=2, pull=2))
_MODELS: dict[str, object] = {}


def loaded_model(folder: Path):
    """This process's loaded proposal model of ``folder``."""
    from scenegen.policy.proposal_model import ProposalModel

    if str(folder) not in _MODELS:
        _MODELS[str(folder)] = ProposalModel.load(folder)
    return _MODELS[str(folder)]


def decide(
    scene: EnvScene,
    qpos: Sequence[float] | None,
    tokens: Sequence[str],
    tried: Sequence[str],
    model: Path,
    retrieval: Path | None,
    variant: Variant,
    config: LabelConfig,
    physics,
) -> dict:
    """The decision at ``scene``'s point after ``tokens`` (state ``qpos``; None: settled): observe
    through ``retrieval`` (None: the oracle), propose, score, choose the best candidate whose token
    is not in ``tried``. Reads frames, the cameras, the robot's state and the requested category;
    no store. ``{"candidate": dict or None (not seen, or nothing new), "score", "proposed"}``."""
    from scenegen.experiment.sequences import path_key

    env = episode_env(scene, physics)
    perception = loaded_perception(retrieval)
    env.reset_to(variant.apply(scene) if perception is not None else scene)
    set_state(env, qpos)
    sha = scene_sha256(scene)
    variant.sense(env, path_key(sha, tokens))
    frames, cameras, view = seen_frames(env, perception)
    if view is None:
        return {"candidate": None, "score": None, "proposed": 0}
    candidates = sample_candidates(view, point_rng(config.seed, sha, tokens), config.sampler, config.grid)
    tried = set(tried)
    fresh = [c for c in candidates if candidate_token(c, physics) not in tried]
    if not fresh:
        return {"candidate": None, "score": None, "proposed": len(candidates)}
    scores = loaded_model(model).rank(fresh, view, frames, cameras)
    best = int(np.argmax(scores))
    return {"candidate": fresh[best].as_dict(), "score": float(scores[best]), "proposed": len(candidates)}


def _job(job: tuple) -> tuple:
    kind, scene, arg, physics = job
    began = time.process_time()
    if kind == "decide":
        key, *rest = arg
        result = (key, decide(scene, *rest, physics=physics))
    else:
        from scenegen.experiment.proposal_labels import simulate_candidates

        result = simulate_candidates(scene, [Candidate.from_dict(c) for c in arg], physics)
    return kind, result, time.process_time() - began


@dataclass
class _Run:
    scene: EnvScene
    sha: str
    sequence: list[dict] = field(default_factory=list)  # the candidates executed
    tokens: tuple[str, ...] = ()
    decisions: list[dict] = field(default_factory=list)
    entry: dict | None = None
    done: bool = False
    success: bool = False


def evaluate_proposals(
    model: Path,
    scenes: Sequence[EnvScene],
    store: PathStore,
    observations: ObservationStore,
    workers: Workers,
    retrieval: Path | None = None,
    variant: Variant = NOMINAL,
    config: LabelConfig = DECISIONS,
    cost: Cost | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """One episode of the proposal model at ``model`` on each scene, seen through ``retrieval``
    (None: the oracle) under ``variant``, its candidates drawn as ``config`` says, simulated under
    ``workers``' physics; one record each (module docstring)."""
    from scenegen.core.files import folder_sha256

    cost = cost if cost is not None else Cost()
    physics = workers.physics
    seen = f"{sight(retrieval, variant)}|proposals:{folder_sha256(Path(model))[:16]}" + physics_mark(physics)
    inputs = config.inputs(config.sampler)
    runs = [_Run(s, scene_sha256(s)) for s in scenes]
    for _ in range(ATTEMPTS):
        for r in runs:
            r.done = r.done or (r.entry is not None and r.entry["time"] >= TIME_LIMIT)
        going = [r for r in runs if not r.done]
        if not going:
            break
        wanted = {}
        for r in going:
            key = ObservationStore.key(r.sha, r.tokens, variant, inputs, seen)
            if observations.meta(key) is None:
                qpos = r.entry["qpos"] if r.entry else None
                args = (key, qpos, list(r.tokens), list(r.tokens), model, retrieval, variant, config)
                wanted[key] = ("decide", r.scene, args)
        for _, (key, decision), seconds in workers.map(list(wanted.values()), run=_job):
            observations.put(key, None, decision)
            cost.add("observe", seconds)
            progress and progress("decision")
        missing, acted = {}, []
        for r in going:
            decision = observations.meta(ObservationStore.key(r.sha, r.tokens, variant, inputs, seen))
            r.decisions.append(decision)
            if decision["candidate"] is None:  # nothing seen, or nothing new to try: the episode ends
                r.done = True
                continue
            r.sequence.append(decision["candidate"])
            r.tokens = (*r.tokens, candidate_token(Candidate.from_dict(decision["candidate"]), physics))
            acted.append(r)
            cost.attempts += 1
            if store.get(r.sha, r.tokens) is not None:
                cost.shared += 1
            else:
                missing.setdefault((r.sha, r.tokens), ("simulate", r.scene, list(r.sequence)))
        for kind, rows, seconds in workers.map(list(missing.values()), run=_job):
            store.add(rows)
            cost.add(kind, seconds)
            cost.simulated += 1
            progress and progress("simulation")
        for r in acted:
            r.entry = store.get(r.sha, r.tokens)
            r.success = r.done = bool(r.entry["success"])
    return [_record(r) for r in runs]


def _record(run: _Run) -> dict:
    scene = run.scene
    return {
        "policy": "proposals",
        "scene_id": scene.scene_id,
        "scene_sha256": run.sha,
        "tags": [t for t in RARE_TAGS if scene.tags.get(t)],
        "actions": [
            c["action"] if c["action"] != "grasp" else f"grasp_{c['approach']}" for c in run.sequence
        ],
        "plans": list(run.tokens),
        "success": run.success,
        "first_attempt": bool(run.success and len(run.sequence) == 1),
        "time": run.entry["time"] if run.entry else 0.0,
        "scores": [d["score"] for d in run.decisions],
        # as closed_loop's records, for perception_gap's summary: no failure labeller here yet
        "perception": [],
        "attempt_failures": [],
        "failure": "" if run.success else ("target_not_seen" if not run.sequence else "unlabelled"),
        "out_of_time": bool(not run.success and run.entry is not None and run.entry["time"] >= TIME_LIMIT),
    }


def compare_episodes(first: Sequence[dict], second: Sequence[dict], replicates: int = 2000) -> dict:
    """Paired by layout (scene sha256): per measure (``first_attempt``, ``success``) and group
    (``all``, each rare tag, ``nominal``), both policies' rates and ``first`` minus ``second`` with
    its 95 % bootstrap interval over layouts. ValueError when the two ran on different layouts."""
    from scenegen.experiment.transfer_stats import difference

    a = {r["scene_sha256"]: r for r in first}
    b = {r["scene_sha256"]: r for r in second}
    if set(a) != set(b):
        raise ValueError(f"the episodes cover different layouts ({len(set(a) ^ set(b))} on one side only)")
    order = sorted(a)
    groups = {"all": order, "nominal": [k for k in order if not a[k]["tags"]]}
    for tag in RARE_TAGS:
        groups[tag] = [k for k in order if tag in a[k]["tags"]]
    out: dict = {}
    for measure in ("first_attempt", "success"):
        for name, keys in groups.items():
            if not keys:
                continue
            x = np.array([[float(a[k][measure]) for k in keys]])
            y = np.array([[float(b[k][measure]) for k in keys]])
            out.setdefault(measure, {})[name] = {
                "first": round(float(x.mean()), 4),
                "second": round(float(y.mean()), 4),
                "difference": difference(x, y, replicates, seed=len(keys)),
            }
    return out


def evaluate_scenes(
    model: Path, scenes: Sequence[EnvScene], out: Path, retrieval: Path | None, physics: str, progress: bool
) -> dict:
    """`scenegen policy eval --proposals`: one episode of the proposal model at ``model`` on each of
    ``scenes``, seen through ``retrieval`` (None: the simulator's masks), under ``physics``. Writes
    ``out/episodes.jsonl`` (one record each, as ``perception-gap --proposals`` writes them) and
    ``out/summary.json``; the sequence and decision stores beside them make a rerun decide and
    simulate nothing twice."""
    import json

    from tqdm import tqdm

    from scenegen.core.files import folder_sha256
    from scenegen.experiment.transfer_stats import episodes_block
    from scenegen.store.batch import atomic_write

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    store, observations = PathStore(out / "paths.jsonl"), ObservationStore(out / "observations")
    with tqdm(desc="proposals", unit=" jobs", disable=not progress) as bar, Workers(1, physics) as pool:
        records = evaluate_proposals(
            model, scenes, store, observations, pool, retrieval, progress=lambda _: bar.update()
        )
    atomic_write(out / "episodes.jsonl", "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
    summary = {
        "policy": "proposals",
        "proposals": str(model),
        "proposals_sha256": folder_sha256(Path(model)),
        "retrieval": str(retrieval) if retrieval is not None else "oracle",
        "physics": physics,
        **episodes_block(records),
        "first_attempt": round(sum(r["first_attempt"] for r in records) / max(len(records), 1), 4),
    }
    atomic_write(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    return summary
