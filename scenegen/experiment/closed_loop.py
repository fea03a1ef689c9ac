"""Closed-loop evaluation of many policies on the same panel scenes, sharing the simulation.

An episode is what :func:`scenegen.policy.evaluate.run_episode` does: from the scene's settled state the
policy observes, chooses a primitive, the primitive runs; after a failure it observes again and chooses
one it has not tried, up to ``ATTEMPTS`` attempts within the task's time limit. The physics is
deterministic, so the outcome of a primitive sequence ``(p1, ..., pk)`` from a scene is a function of
the scene and the sequence alone. :class:`PathStore` keeps it, keyed by the scene's sha256, the
rules' version (``SEQUENCE_RULES``) and the primitives with their versions: whether the last attempt
succeeded (the hold complete within the task's time limit, counted from the episode's start) and
when, the simulated time so far, the failure rules' features of the last attempt
(:func:`~scenegen.policy.failures.attempt_features`) and the state after it (``qpos``). Policies
differ only in which sequences they ask for, so twenty policies on one panel cost little more than the
distinct sequences they choose; an observation at a decision is rendered from the stored state (the
nominal view, or a :class:`Variant` of it). Everything is appended as it is measured, so a killed
evaluation continues where it stopped.

:func:`evaluate_policies` runs in rounds, one attempt per round for every (policy, scene) still going:
decide (observations rendered in a worker pool, cached on disk), then simulate the sequences nobody
has measured yet (the same pool). The expert label of a primitive on a scene is its one-primitive
sequence's success, which the failure labeller's ``grasp_choice`` rule reads.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.env.scenes import EnvScene
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.task import TIME_LIMIT
from scenegen.policy.evaluate import ATTEMPTS
from scenegen.policy.failures import attempt_cause, attempt_features, out_of_time
from scenegen.policy.labels import CAMERA_SIZE, CAMERAS, HORIZON, scene_sha256, target_category
from scenegen.schema.condition import RARE_TAGS
from scenegen.store.batch import atomic_write, recover_jsonl


@dataclass(frozen=True)
class Variant:
    """What the cameras see: ``nominal``, or a shift of the scene's lighting (every light's intensity
    and the ambient term scaled by ``light_scale``). Lighting changes only the colour frames, which
    the policy reads; the planners read depth and the instance mask, so the physics of a sequence is
    the same under every variant and one PathStore serves them all."""

    name: str = "nominal"
    light_scale: float = 1.0

    def apply(self, scene: EnvScene) -> EnvScene:
        if self.light_scale == 1.0:
            return scene
        lighting = scene.lighting
        lights = tuple(
            light.model_copy(update={"intensity": min(3.0, light.intensity * self.light_scale)})
            for light in lighting.lights
        )
        ambient = tuple(min(1.0, a * self.light_scale) for a in lighting.ambient)
        shifted = lighting.model_copy(update={"lights": lights, "ambient": ambient})
        return dataclasses.replace(scene, lighting=shifted)


NOMINAL = Variant()


# 2: success held to the time limit from the episode's start, features per attempt, other objects
# touched (version 1, assets/transfer/paths.jsonl: success per attempt, features over the episode)
SEQUENCE_RULES = 2


def path_key(sha: str, prefix: Sequence[str], seen: str = "oracle") -> str:
    """A sequence's key: the scene, the rules, what the planners saw (``sight``) and the steps."""
    steps = ",".join(f"{p}@{PRIMITIVES[p].version}" for p in prefix)
    return f"{sha}|rules{SEQUENCE_RULES}|{seen}|{steps}"


def sight(retrieval: Path | None, variant: Variant) -> str:
    """What the planners see through: ``oracle`` (the simulator's masks: lighting cannot change a
    plan), or a retrieval head (its weights' sha256) under ``variant``'s lighting, which its
    predictions, hence the plans and the physics, depend on."""
    if retrieval is None:
        return "oracle"
    from scenegen.core.files import sha256_file

    digest = sha256_file(Path(retrieval) / "model.safetensors")[:16]
    return f"retrieval:{digest}@{variant.name}:{variant.light_scale}"


class PathStore:
    """Measured primitive sequences, appended to a JSONL file (a torn last line is dropped)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.entries = {row["key"]: row for row in recover_jsonl(self.path)}

    def get(self, sha: str, prefix: Sequence[str], seen: str = "oracle") -> dict | None:
        return self.entries.get(path_key(sha, prefix, seen))

    def add(self, rows: Sequence[dict]) -> None:
        with open(self.path, "a") as sink:
            for row in rows:
                if row["key"] not in self.entries:
                    sink.write(json.dumps(row, sort_keys=True) + "\n")
                    self.entries[row["key"]] = row
            sink.flush()
            os.fsync(sink.fileno())


class ObservationStore:
    """Policy inputs at decision points, one ``.npy`` per (sequence, variant, input kind), written
    atomically."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    @staticmethod
    def key(sha: str, prefix: Sequence[str], variant: Variant, inputs: str, seen: str = "oracle") -> str:
        text = f"{path_key(sha, prefix, seen)}|{variant.name}:{variant.light_scale}|{inputs}"
        return hashlib.sha256(text.encode()).hexdigest()[:32]

    def get(self, key: str) -> np.ndarray | None:
        path = self.folder / f"{key}.npy"
        return np.load(path, allow_pickle=False) if path.exists() else None

    def put(self, key: str, value: np.ndarray) -> None:
        import io

        buffer = io.BytesIO()
        np.save(buffer, value, allow_pickle=False)
        atomic_write(self.folder / f"{key}.npy", buffer.getvalue())


# ------------------------------------------------------------------------------------------- workers
_ENV = None


def _env(scene: EnvScene):
    global _ENV
    if _ENV is None:
        from scenegen.env.robosuite_env import SceneEnv

        _ENV = SceneEnv(
            scene, cameras=CAMERAS, camera_size=CAMERA_SIZE, render_each_step=False, horizon=HORIZON
        )
    return _ENV


def _init_worker() -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    import torch

    torch.set_num_threads(1)
    from scenegen.env.robosuite_env import close_at_exit

    close_at_exit(_close_env)


def _close_env() -> None:
    global _ENV
    if _ENV is not None:
        from scenegen.env.robosuite_env import close_quietly

        close_quietly(_ENV)
        _ENV = None


_PERCEPTIONS: dict[str, object] = {}


def _perception(retrieval: Path | None):
    """This process's loaded retrieval head of ``retrieval`` (None: the oracle)."""
    if retrieval is None:
        return None
    if str(retrieval) not in _PERCEPTIONS:
        from scenegen.perception.retrieval.perceive import RetrievalPerception

        _PERCEPTIONS[str(retrieval)] = RetrievalPerception.load(retrieval)
    return _PERCEPTIONS[str(retrieval)]


def simulate(
    scene: EnvScene, prefix: Sequence[str], retrieval: Path | None = None, variant: Variant = NOMINAL
) -> list[dict]:
    """Run ``prefix`` from ``scene``'s settled state in this process's environment; one store row per
    step of it (the sequence up to and including that primitive). ``retrieval``: the head every
    observation goes through (under ``variant``'s lighting), each decision's prediction scored
    against the truth for the failure labeller; None: the oracle."""
    from scenegen.env.episodes import EpisodeRecorder
    from scenegen.manipulation.rollout import run_primitive
    from scenegen.perception.observation import observe as look

    perception = _perception(retrieval)
    seen = sight(retrieval, variant)
    env = _env(scene)
    env.reset_to(variant.apply(scene) if perception is not None else scene)
    data = env.sim.data._data
    start = float(data.time)
    episode = (start, float(env.target_pose()[0][2]))
    recorder = EpisodeRecorder(env, "path", observation_kind="rgbd")
    sha, rows = scene_sha256(scene), []
    for k, name in enumerate(prefix):
        observed = score = None
        if perception is not None:
            from scenegen.perception.retrieval.evaluate import score_observation

            observed = look(env, perception)
            score = score_observation(env, observed[0])
        outcome, _ = run_primitive(
            env, name, recorder, episode=episode, perception=perception, observed=observed
        )
        features = attempt_features(recorder.snapshot(), scene.target_id, k, outcome.other_touched)
        if score is not None:
            features["mask_missed"] = not score["hit"] or score["wrong_object"]
        rows.append(
            {
                "key": path_key(sha, prefix[: k + 1], seen),
                "scene_sha256": sha,
                "prefix": list(prefix[: k + 1]),
                "success": bool(outcome.success),
                "success_time": None if outcome.success_time is None else round(outcome.success_time, 6),
                "time": round(float(data.time) - start, 6),
                "features": features,
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
) -> np.ndarray:
    """The policy input (``rgbd``: the front camera crop, its mask the ``retrieval`` head's
    prediction or the oracle's; ``state``: the state features) of ``scene`` (as ``variant`` shows
    it) at ``qpos`` (None: the settled state)."""
    import mujoco

    from scenegen.perception.observation import state_features
    from scenegen.policy.train import policy_input

    env = _env(scene)
    shown = variant.apply(scene)
    env.reset_to(shown)
    if qpos is not None:
        model, data = env.sim.model._model, env.sim.data._data
        data.qpos[:] = qpos
        data.qvel[:] = 0
        mujoco.mj_forward(model, data)
    if inputs == "state":
        return state_features(env)
    perception = _perception(retrieval)
    if perception is not None:
        from scenegen.perception.observation import observe as look

        return policy_input(look(env, perception)[0])
    return policy_input(env.camera_observations(), scene.target_id)


def _job(job: tuple) -> tuple:
    kind, scene, arg = job[0], job[1], job[2]
    if kind == "simulate":  # (prefix, retrieval, variant)
        return kind, simulate(scene, *arg)
    qpos, variant, inputs, key, *retrieval = arg
    return kind, (key, observe(scene, qpos, variant, inputs, *retrieval))


class Workers:
    """Where sequences are simulated and observations rendered: this process (``workers`` <= 1) or a
    spawn pool of ``workers`` processes, each with its own environment, kept for the whole
    evaluation."""

    def __init__(self, workers: int = 1):
        self.workers = workers
        self.pool = None

    def __enter__(self) -> Workers:
        if self.workers <= 1:
            _init_worker()
        else:
            context = multiprocessing.get_context("spawn")
            self.pool = ProcessPoolExecutor(self.workers, mp_context=context, initializer=_init_worker)
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)

    def map(self, jobs: list[tuple]) -> Iterator[tuple]:
        if not jobs:
            return iter(())
        if self.pool is None:
            return map(_job, jobs)
        return self.pool.map(_job, jobs, chunksize=1)


# ---------------------------------------------------------------------------------------- evaluation
@dataclass
class _Run:
    policy: str
    scene: EnvScene
    sha: str
    prefix: tuple[str, ...] = ()
    done: bool = False
    success: bool = False


def evaluate_policies(
    policies: dict[str, object],
    scenes: Sequence[EnvScene],
    store: PathStore,
    observations: ObservationStore,
    variant: Variant = NOMINAL,
    workers: Workers | None = None,
    progress=None,
    retrieval: Path | None = None,
) -> list[dict]:
    """Episodes of every policy (name -> loaded PrimitivePolicy) on every scene; one record each:
    policy, scene id, tags, target category, the primitives chosen, success, failure labels.
    ``workers``: an open :class:`Workers` (default: this process); ``retrieval``: the retrieval
    head every decision and re-observation sees through (None: the oracle's masks). The expert rows
    stay the oracle's: they say what the physics allows."""
    import torch

    if workers is None:
        with Workers(1) as here:
            return evaluate_policies(
                policies, scenes, store, observations, variant, here, progress, retrieval
            )
    seen = sight(retrieval, variant)

    runs = [_Run(name, s, scene_sha256(s)) for name in policies for s in scenes]
    for _ in range(ATTEMPTS):
        for r in runs:  # a policy that has tried every primitive it knows stops
            r.done = r.done or len(r.prefix) >= len(policies[r.policy].primitives)
        going = [r for r in runs if not r.done]
        if not going:
            break
        inputs = {r.policy: policies[r.policy].inputs for r in going}
        wanted = {}
        for r in going:
            entry = store.get(r.sha, r.prefix, seen) if r.prefix else None
            if entry is not None and entry["time"] >= TIME_LIMIT:  # the time limit: no new attempt
                r.done = True
                continue
            key = ObservationStore.key(r.sha, r.prefix, variant, inputs[r.policy], seen)
            if observations.get(key) is None:
                qpos = entry["qpos"] if entry else None
                wanted[key] = ("observe", r.scene, (qpos, variant, inputs[r.policy], key, retrieval))
        for _, (key, value) in workers.map(list(wanted.values())):
            observations.put(key, value)
            progress and progress("observation")
        missing = {}
        for r in going:
            if r.done:
                continue
            x = observations.get(ObservationStore.key(r.sha, r.prefix, variant, inputs[r.policy], seen))
            choice = policies[r.policy].choose(torch.from_numpy(x), exclude=set(r.prefix))
            r.prefix = (*r.prefix, choice)
            if store.get(r.sha, r.prefix, seen) is None:
                missing[path_key(r.sha, r.prefix, seen)] = (
                    "simulate",
                    r.scene,
                    (r.prefix, retrieval, variant),
                )
        _simulate(store, list(missing.values()), workers, progress)
        for r in going:
            if not r.done:
                r.success = store.get(r.sha, r.prefix, seen)["success"]
                r.done = r.success
    failed = {r.sha: r.scene for r in runs if not r.success}
    known = sorted({p for policy in policies.values() for p in policy.primitives}, key=list(PRIMITIVES).index)
    experts = expert_rows(store, failed.values(), known, workers, progress)
    return [_record(r, store, experts, policies[r.policy], seen) for r in runs]


def _simulate(store: PathStore, jobs: list[tuple], workers: Workers, progress=None) -> None:
    for _, rows in workers.map(jobs):
        store.add(rows)
        progress and progress("simulation")


def expert_rows(
    store: PathStore, scenes, primitives: Sequence[str], workers: Workers, progress=None
) -> dict[str, list[dict]]:
    """Per scene sha256, the expert label rows (primitive, success) of ``primitives``, from the
    one-primitive sequences (simulated where missing)."""
    scenes = list(scenes)
    jobs = [
        ("simulate", s, ((name,), None, NOMINAL))
        for s in scenes
        for name in primitives
        if store.get(scene_sha256(s), (name,)) is None
    ]
    _simulate(store, jobs, workers, progress)
    return {
        sha: [{"primitive": n, "success": store.get(sha, (n,))["success"]} for n in primitives]
        for sha in {scene_sha256(s) for s in scenes}
    }


def _record(run: _Run, store: PathStore, experts: dict, policy, seen: str = "oracle") -> dict:
    scene = run.scene
    tags = [t for t in RARE_TAGS if scene.tags.get(t)]
    category = target_category(scene)
    entry = store.get(run.sha, run.prefix, seen) if run.prefix else None
    causes: list[str] = []
    if not run.success:
        coverage = {(t, c): n for t, c, n in policy.trained_on.get("coverage", [])} or None
        for k, primitive in enumerate(run.prefix):
            features = store.get(run.sha, run.prefix[: k + 1], seen)["features"]
            first = k == 0
            expert = experts.get(run.sha, ())
            causes.append(
                attempt_cause(features, primitive, expert, tags or ["nominal"], category, coverage, first)
            )
        causes = causes or ["perception"]
    return {
        "policy": run.policy,
        "scene_id": scene.scene_id,
        "scene_sha256": run.sha,
        "tags": tags,
        "target_category": category,
        "choices": list(run.prefix),
        "success": run.success,
        "first_attempt": bool(run.success and len(run.prefix) == 1),
        "time": entry["time"] if entry else 0.0,
        "failure": causes[0] if causes else "",
        "attempt_failures": causes,
        "out_of_time": bool(not run.success and entry is not None and out_of_time(entry["time"])),
    }
