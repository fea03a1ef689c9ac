"""Closed-loop evaluation of many policies on the same panel scenes, sharing the simulation.

An episode is what :func:`scenegen.policy.evaluate.run_episode` does: observe, choose a primitive,
run it; after a failure observe again and choose one not tried, up to ``ATTEMPTS`` attempts within
the time limit. A sequence's outcome is a function of the scene and the plans executed, kept in the
sequence store (``sequences.py``: keyed by the plans, so policies seeing through different heads cost
little more than the distinct plans they execute); an observation at a decision is rendered from the
stored state (nominal, or a :class:`~scenegen.experiment.sequences.Variant` of it).
:func:`evaluate_policies` runs in rounds, one attempt per round for every (policy, scene) still going:
decide (observations rendered in a worker pool, cached on disk), serve the attempt from the store where
its plans were executed before (a re-observation's plan compared at its stored state), simulate the
rest (the same pool), counting both and the CPU of every job in a :class:`Cost`; a primitive's expert
label is its one-primitive sequence's success with the oracle's plans (``grasp_choice``)."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.physics import DEFAULT_PHYSICS, ControlPhysics, physics_mark, physics_named
from scenegen.env.scenes import EnvScene
from scenegen.experiment.sequences import (
    NOMINAL,
    SEQUENCE_RULES,
    Cost,
    ObservationStore,
    PathStore,
    Variant,
    again_point,
    decision_token,
    match,
    path_key,
    plan_digest,
    sight,
)
from scenegen.manipulation.primitives import PRIMITIVES, PlanGrid, make_plan
from scenegen.manipulation.task import TIME_LIMIT
from scenegen.policy.evaluate import ATTEMPTS
from scenegen.policy.failures import attempt_cause, attempt_features, out_of_time
from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON, scene_sha256, target_category
from scenegen.schema.condition import RARE_TAGS


# ------------------------------------------------------------------------------------------- workers
def episode_env(scene: EnvScene, physics: ControlPhysics):
    from scenegen.env.robosuite_env import worker_env

    options = {"cameras": CAMERAS, "camera_size": CAMERA_SIZE, "render_each_step": False, "horizon": HORIZON}
    return worker_env(scene, physics=physics, **options)


def _init_worker(coordinator: int | None = None) -> None:
    import torch

    from scenegen.env.robosuite_env import init_worker
    from scenegen.runner.executors import die_with_parent

    if coordinator is not None:  # a pool worker dies with its coordinator
        die_with_parent(coordinator)
    torch.set_num_threads(1)
    init_worker()


_PERCEPTIONS: dict[str, object] = {}


def loaded_perception(retrieval: Path | None):
    """This process's loaded retrieval head of ``retrieval`` (None: the oracle)."""
    if retrieval is None:
        return None
    if str(retrieval) not in _PERCEPTIONS:
        from scenegen.perception.retrieval.perceive import RetrievalPerception

        _PERCEPTIONS[str(retrieval)] = RetrievalPerception.load(retrieval)
    return _PERCEPTIONS[str(retrieval)]


def set_state(env, qpos: Sequence[float] | None) -> None:
    """Put the environment at ``qpos`` (None: leave it at the settled state), at rest."""
    if qpos is None:
        return
    import mujoco

    model, data = env.sim.model._model, env.sim.data._data
    data.qpos[:] = qpos
    data.qvel[:] = 0
    mujoco.mj_forward(model, data)


def simulate(
    scene: EnvScene,
    prefix: Sequence[str],
    retrieval: Path | None = None,
    variant: Variant = NOMINAL,
    grid: PlanGrid | None = None,
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> list[dict]:
    """Run ``prefix`` from ``scene``'s settled state in this process's environment under
    ``physics``, every decision and re-observation seen through ``retrieval`` (None: the oracle)
    under ``variant``'s lighting, its plans executed on ``grid``;
    one store row per step of it (the sequence up to and including that primitive), keyed by the
    plans executed. A re-observation inside a primitive keeps its state (``regrasp.qpos``) and its
    plan, so that another head's plan there can be compared without simulating."""
    import mujoco

    from scenegen.env.episodes import EpisodeRecorder
    from scenegen.manipulation.rollout import run_primitive
    from scenegen.perception.observation import observe as look

    physics = physics_named(physics)
    perception = loaded_perception(retrieval)
    env = episode_env(scene, physics)
    env.reset_to(variant.apply(scene) if perception is not None else scene)
    data = env.sim.data._data
    start = float(data.time)
    episode = (start, float(env.target_pose()[0][2]))
    recorder = EpisodeRecorder(env, "path", observation_kind="rgbd")
    sha, rows, tokens = scene_sha256(scene), [], []
    again: list[dict] = []  # the re-observations inside the attempt under way
    name = ""

    def look_again():
        # the store's record of the state looked at (read before the decision: the head and the
        # planner see frames only); the frames show the kinematics computed before the last step's
        # integration: keep that state
        seen = data.qpos.copy()
        mujoco.mj_integratePos(env.sim.model._model, seen, data.qvel, -env.sim.model._model.opt.timestep)
        variant.sense(env, again_point(sha, tokens, name, len(again)))
        obs, view = look(env, perception, image=False)
        plan = None if view is None else make_plan("top_grasp", view, grid)
        again.append({"qpos": seen.tolist(), "plan": plan_digest(plan)})
        return obs, view

    for k, name in enumerate(prefix):
        again.clear()
        variant.sense(env, path_key(sha, tokens))  # the decision point, as observe() sees it
        outcome, params = run_primitive(  # the record is read for its trace: no colour images
            env,
            name,
            recorder,
            episode=episode,
            perception=perception,
            look=look_again,
            images=False,
            grid=grid,
        )
        decision = decision_token(name, params, physics)
        regrasp = again[0] if again else None
        tokens.append(decision + (f"+{regrasp['plan']}" if regrasp else ""))
        features = attempt_features(recorder.snapshot(), scene.target_id, k, outcome.other_touched)
        rows.append(
            {
                "key": path_key(sha, tokens),
                "rules": SEQUENCE_RULES,
                "scene_sha256": sha,
                "prefix": list(prefix[: k + 1]),
                "tokens": list(tokens),
                "decision": decision,
                "regrasp": regrasp,
                "success": bool(outcome.success),
                "success_time": None if outcome.success_time is None else round(outcome.success_time, 6),
                "time": round(float(data.time) - start, 6),
                "features": {k: v for k, v in features.items() if k not in ("mask_pixels", "mask_missed")},
                "qpos": data.qpos.tolist(),
            }
        )
        if outcome.success:
            break
    return rows


def observe(
    scene: EnvScene,
    qpos: Sequence[float] | None,
    variant: Variant,
    inputs: str,
    retrieval: Path | None = None,
    point: str = "",
    grid: PlanGrid | None = None,
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> tuple[np.ndarray, dict]:
    """A decision point of ``scene`` (``point``: its path_key, which seeds a variant's sensor) at
    ``qpos`` (None: the settled state), as ``variant`` shows it, the plans on ``grid``:
    the policy input (``rgbd``: the front camera crop, its mask the ``retrieval`` head's prediction
    or the oracle's; ``state``: the state features) and what the decision needs besides: each
    primitive's plan token from what the planners see there, the pixels of the target's mask
    the decision used and, through a head, its prediction's score against the truth."""
    from scenegen.perception.observation import observe as look
    from scenegen.perception.observation import state_features
    from scenegen.policy.failures import _mask_pixels
    from scenegen.policy.train import policy_input

    physics = physics_named(physics)
    env = episode_env(scene, physics)
    perception = loaded_perception(retrieval)
    env.reset_to(variant.apply(scene))
    set_state(env, qpos)
    variant.sense(env, point)
    obs, view = look(env, perception)
    plans = {
        name: decision_token(name, None if view is None else make_plan(name, view, grid), physics)
        for name in PRIMITIVES
    }
    truth = scene.target_id if perception is None else None  # a head's observation holds its prediction
    meta = {"plans": plans, "mask_pixels": _mask_pixels(obs, truth), "score": None}
    if perception is not None:
        from scenegen.perception.retrieval.evaluate import score_observation

        score = score_observation(env, obs)
        meta["score"] = {k: bool(score[k]) for k in ("hit", "hit_iou", "wrong_object")}
    value = state_features(env) if inputs == "state" else policy_input(obs, truth)
    return value, meta


def regrasp_plan(
    scene: EnvScene,
    qpos: Sequence[float],
    variant: Variant,
    retrieval: Path | None,
    point: str = "",
    grid: PlanGrid | None = None,
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> str:
    """The plan (on ``grid``) a re-observation at ``qpos`` makes through ``retrieval`` (None: the
    oracle); ``point``: the re-observation's (:func:`again_point`), which seeds a variant's sensor."""
    from scenegen.perception.observation import observe as look

    physics = physics_named(physics)
    env = episode_env(scene, physics)
    perception = loaded_perception(retrieval)
    env.reset_to(variant.apply(scene) if perception is not None else scene)
    set_state(env, qpos)
    variant.sense(env, point)
    _, view = look(env, perception)
    return plan_digest(None if view is None else make_plan("top_grasp", view, grid))


def _job(job: tuple) -> tuple:
    """One job for a worker; returns (kind, result, CPU seconds it took)."""
    import time

    kind, scene, arg, physics = job
    began = time.process_time()
    if kind == "simulate":  # (prefix, retrieval, variant, grid)
        result = simulate(scene, *arg, physics=physics)
    elif kind == "regrasp":  # (qpos, variant, key, retrieval, point, grid)
        qpos, variant, key, *rest = arg
        result = (key, regrasp_plan(scene, qpos, variant, *rest, physics=physics))
    else:
        qpos, variant, inputs, key, *retrieval = arg
        result = (key, *observe(scene, qpos, variant, inputs, *retrieval, physics=physics))
    return kind, result, time.process_time() - began


class Workers:
    """Where sequences are simulated and observations rendered: this process (``workers`` <= 1) or a
    spawn pool of ``workers`` processes, each with its own environment, kept for the whole
    evaluation; ``physics`` (a name of ``env.physics.PHYSICS``): what they simulate under."""

    def __init__(self, workers: int = 1, physics: str | ControlPhysics = DEFAULT_PHYSICS):
        self.workers = workers
        self.physics = physics_named(physics)
        self.pool = None

    def __enter__(self) -> Workers:
        if self.workers <= 1:
            _init_worker()
        else:
            context = multiprocessing.get_context("spawn")
            self.pool = ProcessPoolExecutor(
                self.workers, mp_context=context, initializer=_init_worker, initargs=(os.getpid(),)
            )
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)

    def map(self, jobs: list[tuple], run=None) -> Iterator[tuple]:
        """``(kind, result, CPU seconds)`` of each ``(kind, scene, arguments)`` job, in order, under
        this pool's physics, done by ``run`` (default: the closed loop's jobs)."""
        if not jobs:
            return iter(())
        jobs = [(*job, self.physics) for job in jobs]
        if self.pool is None:
            return map(run or _job, jobs)
        return self.pool.map(run or _job, jobs, chunksize=1)


@dataclass
class _Run:
    policy: str
    scene: EnvScene
    sha: str
    prefix: tuple[str, ...] = ()  # the primitives chosen
    tokens: tuple[str, ...] = ()  # the plans executed (path_key)
    decisions: list = dataclasses.field(default_factory=list)  # each decision's meta (observe)
    entry: dict | None = None  # the store row after the last attempt
    done: bool = False
    success: bool = False


def _observations(
    runs, inputs_of, observations, variant, seen, retrieval, workers, cost, progress, grid=None
):
    """Render the decision points the observation store lacks (``inputs_of(run)``: the input kind)."""
    wanted = {}
    for r in runs:
        inputs = inputs_of(r)
        key = ObservationStore.key(r.sha, r.tokens, variant, inputs, seen)
        if observations.meta(key) is None or observations.get(key) is None:
            qpos = r.entry["qpos"] if r.entry else None
            point = path_key(r.sha, r.tokens)
            wanted[key] = ("observe", r.scene, (qpos, variant, inputs, key, retrieval, point, grid))
    for kind, (key, value, meta), seconds in workers.map(list(wanted.values())):
        observations.put(key, value, meta)
        cost.add(kind, seconds)
        progress and progress("observation")


def _resolve(runs, store, observations, variant, seen, retrieval, workers, cost, progress, grid=None) -> None:
    """Each run's chosen attempt (``r.prefix[-1]``, decided as ``r.decisions[-1]``): from the store
    where the same plans were executed before (a re-observation's plan compared at its stored state),
    else simulated; sets ``r.entry`` and ``r.tokens``."""
    checks = {}
    for r in runs:
        decision = r.decisions[-1]["plans"][r.prefix[-1]]
        found = store.candidates(r.sha, r.tokens, decision)
        if found and all(row["regrasp"] is not None for row in found):
            key = _regrasp_key(r, decision, variant, seen)
            if observations.meta(key) is None:
                point = again_point(r.sha, r.tokens, r.prefix[-1], 0)
                job = (found[0]["regrasp"]["qpos"], variant, key, retrieval, point, grid)
                checks[key] = ("regrasp", r.scene, job)
    for kind, (key, plan), seconds in workers.map(list(checks.values())):
        observations.put(key, None, {"plan": plan})
        cost.add(kind, seconds)
    missing: dict[tuple, tuple] = {}
    for r in runs:
        cost.attempts += 1
        decision = r.decisions[-1]["plans"][r.prefix[-1]]
        meta = observations.meta(_regrasp_key(r, decision, variant, seen))
        r.entry = match(store, r.sha, r.tokens, decision, meta and meta["plan"])
        if r.entry is not None:
            cost.shared += 1
        else:
            missing.setdefault((r.sha, r.prefix), ("simulate", r.scene, (r.prefix, retrieval, variant, grid)))
    measured = {}
    results = workers.map(list(missing.values()))
    for job_key, (kind, rows, seconds) in zip(list(missing), results, strict=True):
        store.add(rows)
        measured[job_key] = store.entries[rows[-1]["key"]]
        cost.add(kind, seconds)
        cost.simulated += 1
        progress and progress("simulation")
    for r in runs:
        r.entry = r.entry or measured[(r.sha, r.prefix)]
        r.tokens = tuple(r.entry["tokens"])


def _regrasp_key(r: _Run, decision: str, variant: Variant, seen: str) -> str:
    return ObservationStore.key(r.sha, (*r.tokens, decision), variant, "regrasp", seen)


def evaluate_policies(
    policies: dict[str, object],
    scenes: Sequence[EnvScene],
    store: PathStore,
    observations: ObservationStore,
    variant: Variant = NOMINAL,
    workers: Workers | None = None,
    progress=None,
    retrieval: Path | None = None,
    cost: Cost | None = None,
    rules: int | None = None,
    grid: PlanGrid | None = None,
    attempts: int = ATTEMPTS,
    experts: bool = True,
) -> list[dict]:
    """Episodes of every policy (name -> loaded PrimitivePolicy) on every scene; one record each:
    policy, scene id, tags, target category, the primitives chosen, success, failure labels.
    ``workers``: an open :class:`Workers` (default: this process, under the default physics), whose
    physics the episodes are simulated under; ``retrieval``: the retrieval
    head every decision and re-observation sees through (None: the oracle's masks); ``cost``: a
    :class:`Cost` to count the sharing and the CPU in; ``rules``: the perception rules' version that
    scores a head's decisions (default ``PERCEPTION_RULES``; observations are kept per version);
    ``grid``: the resolution plans are executed at (None: as planned); ``attempts``: per episode (1:
    first decisions only). The expert rows (``experts``) stay the oracle's, as planned: they say what
    the physics allows."""
    import torch

    from scenegen.perception.retrieval.evaluate import PERCEPTION_RULES

    rules = PERCEPTION_RULES if rules is None else rules
    if workers is None:
        with Workers(1) as here:
            options = {"rules": rules, "grid": grid, "attempts": attempts, "experts": experts}
            return evaluate_policies(
                policies, scenes, store, observations, variant, here, progress, retrieval, cost, **options
            )
    cost = cost if cost is not None else Cost()
    seen = sight(retrieval, variant, rules) + (f"|{grid.key()}" if grid is not None else "")
    seen += physics_mark(workers.physics)  # a decision's plan tokens name the physics they run under
    runs = [_Run(name, s, scene_sha256(s)) for name in policies for s in scenes]
    for _ in range(attempts):
        for r in runs:  # a policy that has tried every primitive it knows stops; so does the clock
            r.done = r.done or len(r.prefix) >= len(policies[r.policy].primitives)
            r.done = r.done or (r.entry is not None and r.entry["time"] >= TIME_LIMIT)
        going = [r for r in runs if not r.done]
        if not going:
            break
        inputs_of = lambda r: policies[r.policy].inputs  # noqa: E731
        _observations(going, inputs_of, observations, variant, seen, retrieval, workers, cost, progress, grid)
        for r in going:
            key = ObservationStore.key(r.sha, r.tokens, variant, policies[r.policy].inputs, seen)
            x = observations.get(key)
            r.decisions.append(observations.meta(key))
            r.prefix = (*r.prefix, policies[r.policy].choose(torch.from_numpy(x), exclude=set(r.prefix)))
            r.entry = None
        _resolve(going, store, observations, variant, seen, retrieval, workers, cost, progress, grid)
        for r in going:
            r.success = r.done = bool(r.entry["success"])
    failed = {r.sha: r.scene for r in runs if not r.success and experts}
    known = sorted({p for policy in policies.values() for p in policy.primitives}, key=list(PRIMITIVES).index)
    experts = expert_rows(store, observations, failed.values(), known, workers, progress)
    return [_record(r, store, experts, policies[r.policy], rules) for r in runs]


def expert_rows(
    store: PathStore,
    observations: ObservationStore,
    scenes,
    primitives: Sequence[str],
    workers: Workers,
    progress=None,
) -> dict[str, list[dict]]:
    """Per scene sha256, the expert label rows (primitive, success) of ``primitives``: each one
    executed first, with the oracle's plans (from the store, simulated where missing)."""
    runs = [_Run(name, s, scene_sha256(s), prefix=(name,)) for s in scenes for name in primitives]
    if not runs:
        return {}
    cost = Cost()
    seen = "oracle" + physics_mark(workers.physics)
    _observations(runs, lambda r: "rgbd", observations, NOMINAL, seen, None, workers, cost, progress)
    for r in runs:
        r.decisions.append(observations.meta(ObservationStore.key(r.sha, (), NOMINAL, "rgbd", seen)))
    _resolve(runs, store, observations, NOMINAL, seen, None, workers, cost, progress)
    experts: dict[str, list[dict]] = {}
    for r in runs:
        experts.setdefault(r.sha, []).append({"primitive": r.prefix[0], "success": bool(r.entry["success"])})
    return experts


def _record(run: _Run, store: PathStore, experts: dict, policy, rules: int) -> dict:
    from scenegen.perception.retrieval.evaluate import perception_missed

    scene = run.scene
    tags = [t for t in RARE_TAGS if scene.tags.get(t)]
    category = target_category(scene)
    entry = run.entry
    causes: list[str] = []
    if not run.success:
        coverage = {(t, c): n for t, c, n in policy.trained_on.get("coverage", [])} or None
        for k, primitive in enumerate(run.prefix):
            decided = run.decisions[k]
            score = decided["score"]
            features = {
                **store.get(run.sha, run.tokens[: k + 1])["features"],
                "mask_pixels": decided["mask_pixels"],
                "mask_missed": None if score is None else perception_missed(score, rules),
            }
            expert = experts.get(run.sha, ())
            causes.append(
                attempt_cause(features, primitive, expert, tags or ["nominal"], category, coverage, k == 0)
            )
        causes = causes or ["perception"]
    return {
        "policy": run.policy,
        "scene_id": scene.scene_id,
        "scene_sha256": run.sha,
        "tags": tags,
        "target_category": category,
        "choices": list(run.prefix),
        "plans": list(run.tokens),
        "success": run.success,
        "first_attempt": bool(run.success and len(run.prefix) == 1),
        "time": entry["time"] if entry else 0.0,
        "perception": [d["score"] for d in run.decisions],
        "failure": causes[0] if causes else "",
        "attempt_failures": causes,
        "out_of_time": bool(not run.success and entry is not None and out_of_time(entry["time"])),
    }
