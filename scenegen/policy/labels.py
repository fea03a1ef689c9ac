"""Expert labels: every primitive executed from every scene's settled state, the outcome measured by
the simulator (``scenegen label SCENES --out labels.parquet``).

One row per (scene, primitive): the scene (id, source, origin, target category, the rare tags it
holds, ``scene_sha256``), the primitive and its version, the ``observation`` its planner used
(``rgbd``, or the ``state`` ablation), the ``physics`` it was simulated under
(``ControlPhysics.key()``; a row written before the physics was a setting has none and was made under
``exact``), ``success``, ``lift`` (m), ``duration`` (simulated s) and ``failure`` (the failure event,
``RetrieveOutcome.failure``). Scenes whose target is on the floor are left out (infeasible for a
table-top arm). Rows are in (scene, primitive) order and hold no wall-clock data, so the same scenes
give the same file whatever the worker count.

Resumable and cached: every finished row is appended to ``<out>.rows.jsonl`` at once; a rerun (after a
kill, or with more scenes or primitives) reuses every row whose (scene_sha256, primitive, version,
observation, physics) it already holds, from that log or from an existing ``out``, and runs only the
rest. ``out`` is written atomically at the end.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from scenegen.env.physics import DEFAULT_PHYSICS, EXACT_KEY, PHYSICS, ControlPhysics, physics_named
from scenegen.env.scenes import EnvScene, load_scenes, scene_sha256, target_category, unique_category
from scenegen.manipulation.primitives import PRIMITIVES
from scenegen.manipulation.task import feasible, within_limit
from scenegen.perception.observation import CAMERA_SIZE, CAMERAS, KINDS
from scenegen.schema.condition import RARE_TAGS
from scenegen.store.batch import recover_jsonl

HORIZON = 3000  # control steps: longer than any primitive


class LabelError(ValueError):
    """Labelling that cannot start; the message names the input and what to do."""


@dataclass(frozen=True)
class Job:
    scene: EnvScene
    sha256: str
    primitive: str
    version: int
    observation: str = "rgbd"  # what the planner sees: camera frames, or the state ablation
    physics: ControlPhysics = physics_named(DEFAULT_PHYSICS)  # what it is simulated under

    @property
    def key(self) -> tuple[str, str, int, str, str]:
        return (self.sha256, self.primitive, self.version, self.observation, self.physics.key())


def row_physics(row: dict) -> str:
    """The physics a label row was simulated under (its key; rows from before it was a setting:
    ``exact``'s)."""
    return row.get("physics") or EXACT_KEY


def _key(row: dict) -> tuple[str, str, int, str, str]:
    return (
        row["scene_sha256"],
        row["primitive"],
        row["primitive_version"],
        row.get("observation", "rgbd"),
        row_physics(row),
    )


def _row(job: Job, outcome) -> dict:
    scene = job.scene
    category = target_category(scene)
    return {
        "scene_id": scene.scene_id,
        "source": scene.source,
        "origin": scene.origin,
        "scene_sha256": job.sha256,
        "target_category": category,
        "tags": [t for t in RARE_TAGS if scene.tags.get(t)],
        "primitive": job.primitive,
        "primitive_version": job.version,
        "observation": job.observation,
        "physics": job.physics.key(),
        "success": bool(outcome.success),
        "lift": round(float(outcome.lift), 6),
        "duration": round(float(outcome.time), 4),
        "failure": outcome.failure(),
    }


# ------------------------------------------------------------------------------------------- workers
def _init_worker() -> None:
    import torch

    from scenegen.env.robosuite_env import init_worker

    torch.set_num_threads(1)
    init_worker()  # frees the GL context before the interpreter goes


def _run(job: Job) -> dict:
    """Execute one primitive from the scene's settled state in this process's environment."""
    from scenegen.env.robosuite_env import worker_env
    from scenegen.manipulation.rollout import run_primitive

    options = {"cameras": CAMERAS, "camera_size": CAMERA_SIZE, "render_each_step": False, "horizon": HORIZON}
    env = worker_env(job.scene, physics=job.physics, **options)
    env.reset_to(job.scene)
    outcome, _ = run_primitive(env, job.primitive, observation_kind=job.observation)
    return _row(job, outcome)


# -------------------------------------------------------------------------------------------- label
def label_jobs(
    scenes: Sequence[EnvScene],
    primitives: Sequence[str],
    observation: str = "rgbd",
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> list[Job]:
    physics = physics_named(physics)
    unknown = [p for p in primitives if p not in PRIMITIVES]
    if unknown:
        raise LabelError(f"--primitives {unknown}: unknown; choose from {', '.join(PRIMITIVES)}")
    if observation not in KINDS:
        raise LabelError(f"--observation {observation}: choose one of {', '.join(KINDS)}")
    return [
        Job(scene, scene_sha256(scene), name, PRIMITIVES[name].version, observation, physics)
        for scene in scenes
        if feasible(scene)
        for name in primitives
    ]


def timed(row: dict) -> bool:
    """Whether a label row's success can be judged by today's time limit (``task.within_limit``):
    rows were written before the limit held on a success, but each keeps its execution's
    ``duration``; every row of assets/transfer/labels.parquet ended within the 45 s limit."""
    return within_limit(bool(row["success"]), float(row["duration"]), row.get("success_time")) is not None


def current(row: dict, observation: str = "rgbd", physics: str | ControlPhysics = DEFAULT_PHYSICS) -> bool:
    """Whether a label row answers for today's primitives: the primitive's current version, planned
    from ``observation`` (the state ablation's rows say what a planner with the simulator's state
    would do, not what one with the cameras does), simulated under ``physics``, judged by today's
    time limit."""
    primitive = PRIMITIVES.get(row["primitive"])
    return (
        primitive is not None
        and row.get("primitive_version") == primitive.version
        and row.get("observation", "rgbd") == observation
        and row_physics(row) == physics_named(physics).key()
        and timed(row)
    )


def current_rows(
    tables: Sequence[Sequence[dict]],
    observation: str = "rgbd",
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> tuple[list[dict], int]:
    """The rows of several label tables that answer for today's primitives seen through
    ``observation`` under ``physics``, each (scene, primitive) once; and how many rows were left out
    as stale."""
    rows: dict[tuple, dict] = {}
    stale = 0
    for table in tables:
        for row in table:
            if current(row, observation, physics):
                rows.setdefault((row["scene_sha256"], row["primitive"]), row)
            else:
                stale += 1
    return list(rows.values()), stale


def per_tag_selection(scenes: Sequence[EnvScene], n: int) -> list[EnvScene]:
    """The first ``n`` scenes holding each rare tag and the first ``n`` nominal ones, in source order."""
    chosen: set[int] = set()
    for tag in (*RARE_TAGS, "nominal"):
        holding = [i for i, s in enumerate(scenes) if s.tags.get(tag)]
        chosen.update(holding[:n])
    return [scenes[i] for i in sorted(chosen)]


def per_cell_selection(scenes: Sequence[EnvScene], n: int, categories: Sequence[str]) -> list[EnvScene]:
    """The first ``n`` feasible scenes of every (tag, target category) cell, rare tags and nominal, for
    the target categories named, in source order: enough scenes per cell for a within-category table.
    Cells with fewer than ``n`` scenes are left out (too few to report on their own)."""
    chosen: set[int] = set()
    for category in categories:
        in_category = [i for i, s in enumerate(scenes) if target_category(s) == category and feasible(s)]
        for tag in (*RARE_TAGS, "nominal"):
            cell = [i for i in in_category if scenes[i].tags.get(tag)]
            chosen.update(cell[:n] if len(cell) >= n else [])
    return [scenes[i] for i in sorted(chosen)]


def stored_rows(out: Path) -> list[dict]:
    """Every row a label store holds, from its Parquet file and its row log (a run under way)."""
    return list(_cached(Path(out), Path(out).with_name(Path(out).name + ".rows.jsonl")).values())


def _cached(out: Path, log: Path) -> dict[tuple, dict]:
    rows = []
    if out.exists():
        import pyarrow.parquet as pq

        rows += pq.read_table(out).to_pylist()
    rows += recover_jsonl(log)
    # a row the time limit cannot judge is relabelled; every row says its physics (a Parquet table
    # takes its columns from its first row)
    return {_key(r): {**r, "physics": row_physics(r)} for r in rows if timed(r)}


def label(
    source: Path,
    out: Path,
    primitives: Sequence[str] | None = None,
    split: str | None = "train",
    limit: int | None = None,
    workers: int = 1,
    progress: bool = True,
    per_tag: int | None = None,
    observation: str = "rgbd",
    per_cell: tuple[int, Sequence[str]] | None = None,
    outside_panels: bool = False,
    backend=None,
    unique: bool = False,
    until_solved: bool = False,
    physics: str = DEFAULT_PHYSICS,
) -> dict:
    """Label the scenes of ``source`` (a batch, a scene folder or a reference Parquet table) with
    every primitive (or those named); returns counts (rows, run now, reused from the cache).
    ``per_tag``: only the first N scenes holding each rare tag and the first N nominal ones (in
    source order), for a success table per tag without labelling every scene; ``per_cell`` (N,
    categories): the first N of every (tag, category) cell of those categories (added to ``per_tag``'s
    selection when both are given); ``outside_panels``: leave out the transfer experiment's panel
    layouts (version 1's and both sides of version 2's); ``unique``: only scenes holding one object of
    the target's category (chosen before ``per_tag``). ``limit`` counts feasible scenes (on_floor
    targets are out of reach, never labelled).
    ``until_solved``: stop each scene at its first success (``label_until_solved``; ``primitives``,
    if given, is the order), enough to say which scenes are solvable. ``backend``: where the
    ``workers`` run (scenegen.runner.executors.Backend; default a local pool). ``physics``: a name of
    ``env.physics.PHYSICS``, what every primitive is simulated under."""
    try:
        scenes = load_scenes(source, split)
    except (OSError, ValueError) as exc:
        raise LabelError(f"{source}: {str(exc).splitlines()[0]}") from None
    if unique:
        scenes = [s for s in scenes if unique_category(s)]
    if per_tag is not None or per_cell is not None:
        chosen = {id(s) for s in per_tag_selection(scenes, per_tag)} if per_tag is not None else set()
        if per_cell is not None:
            unknown = sorted(set(per_cell[1]) - {target_category(s) for s in scenes})
            if unknown:
                raise LabelError(f"--categories: no target of category {', '.join(unknown)} in {source}")
            chosen |= {id(s) for s in per_cell_selection(scenes, *per_cell)}
        scenes = [s for s in scenes if id(s) in chosen]
    if outside_panels:
        from scenegen.policy.panels import outside_panels as off_panels

        scenes = off_panels(scenes)
    scenes = [s for s in scenes if feasible(s)]
    scenes = scenes[:limit] if limit is not None else scenes
    if physics not in PHYSICS:
        raise LabelError(f"--physics {physics}: unknown; choose from {', '.join(PHYSICS)}")
    if until_solved:
        if observation != "rgbd":
            raise LabelError(
                "--until-solved settles solvability with the cameras' planners: drop --observation"
            )
        rows, ran = label_until_solved(
            scenes, out, primitives or SOLVE_ORDER, workers, progress, backend, physics=physics
        )
    else:
        rows, ran = label_scenes(
            scenes, out, primitives, observation, workers, progress, backend=backend, physics=physics
        )
    return {"rows": len(rows), "ran": ran, "reused": len(rows) - ran, "out": str(out)}


def label_scenes(
    scenes: Sequence[EnvScene],
    out: Path,
    primitives: Sequence[str] | None = None,
    observation: str = "rgbd",
    workers: int = 1,
    progress: bool = True,
    keep: bool = False,
    reuse: Sequence[Path] = (),
    backend=None,
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> tuple[list[dict], int]:
    """Label ``scenes`` (feasible ones) with every primitive (or those named) into ``out`` under
    ``physics``; returns their rows and how many were run now. ``keep``: ``out`` is a store that
    keeps every row it held (a cache shared by several calls); otherwise it holds exactly these
    scenes' rows. ``reuse``: other label files whose rows (same scene content, primitive, version,
    observation and physics) count as done."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    from scenegen.store.batch import atomic_write

    out = Path(out)
    jobs = label_jobs(
        [s for s in scenes if feasible(s)], list(primitives or PRIMITIVES), observation, physics
    )
    log = out.with_name(out.name + ".rows.jsonl")
    out.parent.mkdir(parents=True, exist_ok=True)
    cache = _cached(out, log)
    for path in reuse:
        for key, row in _cached(Path(path), Path(path).with_name(Path(path).name + ".rows.jsonl")).items():
            cache.setdefault(key, row)
    todo = [job for job in jobs if job.key not in cache]
    with open(log, "a") as sink:
        rows_out = _execute(todo, workers, backend)
        for row in tqdm(rows_out, total=len(todo), disable=not progress, desc="label"):
            sink.write(json.dumps(row, sort_keys=True) + "\n")
            sink.flush()
            cache[_key(row)] = row
    rows = [{**cache[job.key], "observation": job.observation} for job in jobs]
    stored = [cache[k] for k in sorted(cache)] if keep else rows
    # as the log holds them (sorted keys, JSON types): a run resumed from the log writes the same bytes
    stored = [json.loads(json.dumps(row, sort_keys=True)) for row in stored]
    buffer = pa.BufferOutputStream()
    pq.write_table(pa.Table.from_pylist(stored), buffer)
    atomic_write(out, buffer.getvalue().to_pybytes())
    log.unlink(missing_ok=True)
    return rows, len(todo)


# Cheapest order to settle solvability: on the 296 fully labelled unique-category held-out layouts
# (assets/panels/v2), the greedy cover toppled_grasp 174, top_grasp +33, pull_out_then_grasp +7,
# side_grasp +1, push_from_edge_then_grasp +1 of 216 solvable. The order changes only the cost: the
# answer (does any primitive succeed) is the same in every order.
SOLVE_ORDER = ("toppled_grasp", "top_grasp", "pull_out_then_grasp", "side_grasp", "push_from_edge_then_grasp")


def label_until_solved(
    scenes: Sequence[EnvScene],
    out: Path,
    order: Sequence[str] = SOLVE_ORDER,
    workers: int = 1,
    progress: bool = True,
    backend=None,
    reuse: Sequence[Path] = (),
    physics: str | ControlPhysics = DEFAULT_PHYSICS,
) -> tuple[list[dict], int]:
    """Whether each scene is solvable (under ``physics``), at the least labelling: one round per
    primitive of ``order`` over the scenes no row of ``out`` shows solved yet, so a scene stops at its
    first success (``solvable_scenes`` reads the partial rows). ``out`` keeps every row it held
    (rounds add to it). ``reuse``: other label files whose rows count as done (``label_scenes``).
    Returns the rows of the rounds these scenes took, and how many were run now."""
    unknown = sorted(set(PRIMITIVES) - set(order))
    if unknown:
        raise LabelError(f"--primitives: order all of {', '.join(PRIMITIVES)} to settle solvability")
    out = Path(out)
    solved = {
        sha for sha, ok in solvable_scenes(stored_rows(out), physics).items() if ok
    }  # known at the start
    remaining = [s for s in scenes if feasible(s) and scene_sha256(s) not in solved]
    rows: list[dict] = []
    ran = 0
    for primitive in order:
        if not remaining:
            break
        got, n = label_scenes(
            remaining, out, [primitive], "rgbd", workers, progress, True, reuse, backend, physics
        )
        rows += got
        ran += n
        solved = {r["scene_sha256"] for r in got if r["success"]}
        remaining = [s for s in remaining if scene_sha256(s) not in solved]
    return rows, ran


def _execute(jobs: list[Job], workers: int, backend=None) -> Iterator[dict]:
    """Rows of ``jobs`` in order: here, or on ``workers`` workers of ``backend`` (runner/executors.py)."""
    from scenegen.runner.executors import LOCAL, ordered_map

    backend = backend or LOCAL
    if workers <= 1 and backend.kind == "local":
        _init_worker()
        try:
            yield from map(_run, jobs)
        finally:
            from scenegen.env.robosuite_env import close_worker_envs

            close_worker_envs()
        return
    yield from ordered_map(_run, jobs, workers, _init_worker, (), backend)


def solvable_scenes(label_rows, physics: str | ControlPhysics = DEFAULT_PHYSICS) -> dict[str, bool]:
    """Per scene sha256 whose answer the current rows (under ``physics``) settle: True once one
    primitive succeeds (the others may be unlabelled, as ``label_until_solved`` leaves them), False
    when every primitive is labelled and none succeeds; a scene with neither is left out (not yet
    known)."""
    rows, _ = current_rows([list(label_rows)], physics=physics)
    labelled: dict[str, dict[str, bool]] = {}
    for row in rows:
        labelled.setdefault(row["scene_sha256"], {})[row["primitive"]] = bool(row["success"])
    return {
        sha: any(bits.values())
        for sha, bits in labelled.items()
        if any(bits.values()) or set(bits) >= set(PRIMITIVES)
    }
