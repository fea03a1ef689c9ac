"""Labels for the proposal model (issue 63, point 2): every candidate the sampler proposes at a
layout's first decision, executed through the controller from the settled state, its success by the
task monitor's rule.

A candidate's attempt is a row of the sequence store (:class:`~scenegen.experiment.sequences.PathStore`,
keyed by the scene and the candidates executed, ``candidate_token``: action, executor and sampler
versions, the physics, the parameters on the plan grid), so a closed loop that executes the same
candidate later reads it instead of simulating, and a model's offline figure is a lookup of the
candidate it ranks first. What was proposed at a decision point is kept in an
:class:`~scenegen.experiment.sequences.ObservationStore` (its meta: the candidates), so a rerun
proposes nothing twice.

A push or a pull ends its decision: its value is what a next decision can make of it. Where no
grasp of the first decision lifts the target, each push and pull is followed by the sampler's
grasps (``LabelConfig.follow``) proposed from the observation at the state it left, each executed
after it: the sequence [push, grasp] is a row of the same store. Elsewhere a push or pull keeps its
own row only (a grasp alone already works there).

The labels are seen through the oracle (the simulator's instance masks: the action side alone).
Resumable: every result is stored as it comes; a rerun, after a kill or with more scenes, runs only
what the stores lack. No wall-clock data enters a row.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenegen.env.physics import DEFAULT_PHYSICS, ControlPhysics, physics_named
from scenegen.env.scenes import EnvScene, scene_sha256
from scenegen.experiment.closed_loop import Workers, episode_env, set_state
from scenegen.experiment.sequences import (
    NOMINAL,
    SEQUENCE_RULES,
    ObservationStore,
    PathStore,
    candidate_token,
    path_key,
)
from scenegen.manipulation.primitives import PlanGrid
from scenegen.manipulation.proposals import SAMPLER_VERSION, Candidate, SamplerConfig, sample_candidates
from scenegen.manipulation.task import feasible
from scenegen.policy.failures import attempt_features
from scenegen.store.batch import atomic_write

GRID = PlanGrid(metres=0.005, degrees=10.0)  # candidates closer than this are one attempt
# Issue 63's labels, sized to its 12 CPU-hour budget over LABEL_SETS' 1,456 layouts (measured under
# dt5, docs/policy.md): a top grasp about 8 simulated seconds, a side grasp 16, a push 9, a pull 23, at
# about 0.14 CPU-s a simulated second; the follow-ups run only where no first grasp lifted the target.
SAMPLER = SamplerConfig(top=6, side=1, push=1, pull=1)  # side grasps: the costliest, 9 % lift (v2 pilot)
FOLLOW = SamplerConfig(top=2, side=1, push=0, pull=0)


@dataclass(frozen=True)
class LabelConfig:
    """What is proposed at a layout's first decision (``sampler``) and after a push or pull where
    no grasp worked (``follow``), on ``grid``, drawn from ``seed``, simulated under ``physics``."""

    sampler: SamplerConfig = SAMPLER
    follow: SamplerConfig = FOLLOW
    grid: PlanGrid = GRID
    seed: int = 0
    physics: str = DEFAULT_PHYSICS  # a name of env.physics.PHYSICS: what the attempts run under

    def inputs(self, sampler: SamplerConfig) -> str:
        """The observation store's input kind of a decision point proposed by ``sampler``."""
        counts = f"{sampler.top}.{sampler.side}.{sampler.push}.{sampler.pull}"
        return f"proposals:s{SAMPLER_VERSION}:{counts}:{self.grid.key()}:seed{self.seed}"


DEFAULT_LABELS = LabelConfig()
# The default label folder (generated data: not tracked; `scenegen proposals label` remakes it,
# resumable). A folder of another sampler version is refused, so the name changes with none.
LABELS_FOLDER = Path("runs/proposal_labels")
SETTINGS = "labels.json"  # a label folder's LabelConfig


def _settings(config: LabelConfig) -> dict:
    return {
        "sampler": dataclasses.asdict(config.sampler),
        "follow": dataclasses.asdict(config.follow),
        "grid": {"metres": config.grid.metres, "degrees": config.grid.degrees},
        "seed": config.seed,
        "physics": config.physics,
        "sampler_version": SAMPLER_VERSION,
    }


def open_labels(
    folder: Path, config: LabelConfig | None = None
) -> tuple[LabelConfig, PathStore, ObservationStore]:
    """A label folder's settings, sequence store and proposed decision points. ``config``: what a
    labelling run asks; the folder's first run records it (``labels.json``), a later one must ask
    the same (ValueError naming the file otherwise). Without ``config`` (training, scoring) the
    recorded one is read; ValueError when the folder holds none."""
    folder = Path(folder)
    path = folder / SETTINGS
    if path.is_file():
        recorded = json.loads(path.read_text())
        known = LabelConfig(
            sampler=SamplerConfig(**recorded["sampler"]),
            follow=SamplerConfig(**recorded["follow"]),
            grid=PlanGrid(**recorded["grid"]),
            seed=int(recorded["seed"]),
            physics=str(recorded["physics"]),
        )
        if recorded.get("sampler_version") != SAMPLER_VERSION:
            raise ValueError(f"{path}: labelled by sampler version {recorded.get('sampler_version')}, "
                             f"this is {SAMPLER_VERSION}: label into a new folder")  # fmt: skip
        if config is not None and config != known:

            def said(c: LabelConfig) -> str:
                counts = " ".join(str(v) for v in dataclasses.astuple(c.sampler))
                return f"sampler {counts} seed {c.seed} physics {c.physics}"

            raise ValueError(
                f"{path}: labelled with {said(known)}, not {said(config)}: use those or a new folder"
            )
        config = known
    elif config is None:
        raise ValueError(f"{folder}: no {SETTINGS}; run `scenegen proposals label --out {folder}` first")
    else:
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write(path, json.dumps(_settings(config), indent=1, sort_keys=True) + "\n")
    return config, PathStore(folder / "paths.jsonl"), ObservationStore(folder / "views")


def point_rng(seed: int, sha: str, tokens: Sequence[str]) -> np.random.Generator:
    """The sampler's random stream at a decision point: the seed and the point (scene and the
    attempts before it), so any process and any order draws the same candidates there."""
    digest = hashlib.sha256(path_key(sha, tokens).encode()).digest()
    return np.random.default_rng([seed, int.from_bytes(digest[:8], "little")])


# ------------------------------------------------------------------------------------------- jobs
def propose(
    scene: EnvScene,
    qpos: Sequence[float] | None,
    tokens: Sequence[str],
    sampler: SamplerConfig,
    config: LabelConfig,
    physics: ControlPhysics,
) -> list[dict]:
    """The candidates (as dicts) the sampler proposes at ``scene``'s decision point after ``tokens``
    (the state ``qpos``; None: the settled state), seen through the oracle; [] if the target is not
    seen."""
    from scenegen.perception.observation import observe

    env = episode_env(scene, physics)
    env.reset_to(scene)
    set_state(env, qpos)
    _, view = observe(env, image=False)
    if view is None:
        return []
    rng = point_rng(config.seed, scene_sha256(scene), tokens)
    return [c.as_dict() for c in sample_candidates(view, rng, sampler, config.grid)]


def simulate_candidates(
    scene: EnvScene, sequence: Sequence[Candidate], physics: ControlPhysics
) -> list[dict]:
    """Execute ``sequence`` from ``scene``'s settled state under ``physics``; one store row per
    attempt (the sequence up to and including it), as :func:`closed_loop.simulate` writes them,
    plus the candidate executed."""
    from scenegen.env.episodes import EpisodeRecorder
    from scenegen.manipulation.rollout import run_candidate

    env = episode_env(scene, physics)
    env.reset_to(scene)
    data = env.sim.data._data
    start = float(data.time)
    episode = (start, float(env.target_pose()[0][2]))
    recorder = EpisodeRecorder(env, "candidates", observation_kind="rgbd")
    sha, rows, tokens = scene_sha256(scene), [], []
    for k, candidate in enumerate(sequence):
        recorder.decide({}, {"primitive": candidate.action, "observation_kind": "rgbd"})
        outcome = run_candidate(env, candidate, recorder, episode=episode)
        decision = candidate_token(candidate, physics)
        tokens.append(decision)
        features = attempt_features(recorder.snapshot(), scene.target_id, k, outcome.other_touched)
        rows.append(
            {
                "key": path_key(sha, tokens),
                "rules": SEQUENCE_RULES,
                "scene_sha256": sha,
                "prefix": [c.action for c in sequence[: k + 1]],
                "tokens": list(tokens),
                "decision": decision,
                "regrasp": None,
                "candidate": candidate.as_dict(),
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


def _job(job: tuple) -> tuple:
    """One labelling job for a worker: (kind, result, CPU seconds)."""
    kind, scene, arg, physics = job
    began = time.process_time()
    if kind == "propose":  # (key, qpos, tokens, sampler, config)
        key, *rest = arg
        result = (key, propose(scene, *rest, physics=physics))
    else:  # "simulate": the candidates' dicts, in order
        result = simulate_candidates(scene, [Candidate.from_dict(c) for c in arg], physics)
    return kind, result, time.process_time() - began


# ------------------------------------------------------------------------------------------ labels
@dataclass
class LabelCost:
    """What a labelling run did: candidates simulated and served from the store, CPU per kind."""

    simulated: int = 0
    stored: int = 0
    cpu: dict = field(default_factory=lambda: {"propose": 0.0, "simulate": 0.0})

    def per_candidate(self) -> float | None:
        return self.cpu["simulate"] / self.simulated if self.simulated else None


def proposed_at(views: ObservationStore, sha: str, tokens: Sequence[str], inputs: str) -> list[dict] | None:
    """The candidates proposed at the decision point after ``tokens`` ([] where the target was not
    seen), or None where nothing was proposed there yet."""
    meta = views.meta(ObservationStore.key(sha, tokens, NOMINAL, inputs))
    return None if meta is None else meta["candidates"]


def _propose_missing(points, views, config, workers, cost, progress) -> None:
    """Propose at each ``(scene, qpos, tokens, sampler)`` decision point the view store lacks."""
    wanted = {}
    for scene, qpos, tokens, sampler in points:
        sha = scene_sha256(scene)
        key = ObservationStore.key(sha, tokens, NOMINAL, config.inputs(sampler))
        if views.meta(key) is None:
            wanted[key] = ("propose", scene, (key, qpos, list(tokens), sampler, config))
    for kind, (key, candidates), seconds in workers.map(list(wanted.values()), run=_job):
        views.put(key, None, {"candidates": candidates})
        cost.cpu[kind] += seconds
        progress and progress("propose")


def _simulate_missing(sequences, store, physics, workers, cost, progress) -> None:
    """Simulate each ``(scene, [candidate, ...])`` whose last attempt the store lacks."""
    jobs = {}
    for scene, sequence in sequences:
        sha = scene_sha256(scene)
        tokens = [candidate_token(Candidate.from_dict(c), physics) for c in sequence]
        if store.get(sha, tokens) is None:
            jobs.setdefault(path_key(sha, tokens), ("simulate", scene, list(sequence)))
        else:
            cost.stored += 1
    for kind, rows, seconds in workers.map(list(jobs.values()), run=_job):
        store.add(rows)
        cost.simulated += 1
        cost.cpu[kind] += seconds
        progress and progress("simulate")


def label_proposals(
    scenes: Sequence[EnvScene],
    store: PathStore,
    views: ObservationStore,
    config: LabelConfig = DEFAULT_LABELS,
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
) -> LabelCost:
    """Label every candidate of ``scenes``' first decisions, then the grasps after each push and
    pull where no first grasp worked (module docstring), under ``config.physics``; the cost of what
    this run did."""
    physics = physics_named(config.physics)
    cost = LabelCost()
    with Workers(workers, physics) as pool:
        _propose_missing([(s, None, (), config.sampler) for s in scenes], views, config, pool, cost, progress)
        first = {
            scene_sha256(s): proposed_at(views, scene_sha256(s), (), config.inputs(config.sampler))
            for s in scenes
        }
        _simulate_missing(
            [(s, [c]) for s in scenes for c in first[scene_sha256(s)]], store, physics, pool, cost, progress
        )
        movers = []  # (scene, the push or pull, its row) where no first grasp lifted the target
        for s in scenes:
            sha = scene_sha256(s)
            rows = [
                (c, store.get(sha, [candidate_token(Candidate.from_dict(c), physics)])) for c in first[sha]
            ]
            if any(c["action"] == "grasp" and row["success"] for c, row in rows):
                continue
            movers += [(s, c, row) for c, row in rows if c["action"] != "grasp" and not row["success"]]
        points = [(s, row["qpos"], row["tokens"], config.follow) for s, _, row in movers]
        _propose_missing(points, views, config, pool, cost, progress)
        follow = []
        for s, c, row in movers:
            after = proposed_at(views, row["scene_sha256"], row["tokens"], config.inputs(config.follow))
            follow += [(s, [c, g]) for g in after]
        _simulate_missing(follow, store, physics, pool, cost, progress)
    return cost


def candidate_labels(
    scenes: Sequence[EnvScene],
    store: PathStore,
    views: ObservationStore,
    config: LabelConfig = DEFAULT_LABELS,
) -> list[dict]:
    """One record per first-decision candidate of each labelled scene: the candidate, its own
    ``success``, and for a push or pull that was followed up, ``after``: the follow-up grasps'
    successes (None where it was not: a grasp alone worked there). Scenes not yet labelled are left
    out."""
    physics = physics_named(config.physics)
    out = []
    for s in scenes:
        sha = scene_sha256(s)
        proposed = proposed_at(views, sha, (), config.inputs(config.sampler))
        if proposed is None:
            continue
        for c in proposed:
            token = candidate_token(Candidate.from_dict(c), physics)
            row = store.get(sha, [token])
            if row is None:
                continue
            after = proposed_at(views, sha, [token], config.inputs(config.follow))
            successes = None
            if after is not None:
                rows = [
                    store.get(sha, [token, candidate_token(Candidate.from_dict(g), physics)]) for g in after
                ]
                successes = [r["success"] for r in rows if r is not None]
            out.append({"scene_sha256": sha, "candidate": c, "success": row["success"], "after": successes})
    return out


# ----------------------------------------------------------------------------------------- layouts
LABEL_SETS = ("natural:600", "rare_rich:100", "rare_rich:300", "rare_rich:600", "curve", "validation")


def label_layouts(specs: Sequence[str] = LABEL_SETS, limit: int | None = None) -> dict[str, list[EnvScene]]:
    """The layouts each spec names: ``natural:N`` and ``rare_rich:N`` (the learning curves'
    training sets, ``retrieval_curves.training_sets``), ``curve`` (their curve set: rare layouts on
    no panel), ``validation`` (the version 2 validation panel's layouts); ``limit``: the first N of
    each (a pilot). Only feasible layouts (a target on the floor is out of a table-top arm's reach).
    The test panel is never read. ValueError names a spec it does not know."""
    from scenegen.experiment.retrieval_curves import PANEL, curve_set, training_sets
    from scenegen.policy.panels_v2 import load_panels_v2, panel_id, panel_scenes

    out = {}
    for spec in specs:
        name, _, size = spec.partition(":")
        if name in ("natural", "rare_rich") and size.isdigit() and int(size) > 0:
            scenes = training_sets(int(size))[name]
        elif spec == "curve":
            scenes = curve_set()
        elif spec == PANEL:
            panel = panel_scenes(load_panels_v2(), PANEL)  # the validation side's layouts only
            scenes = list({panel_id(s): s for ss in panel.values() for s in ss}.values())
        else:
            raise ValueError(f"layouts {spec!r}: use natural:N, rare_rich:N, curve or validation")
        scenes = [s for s in scenes if feasible(s)]
        out[spec] = scenes[:limit] if limit is not None else scenes
    return out
