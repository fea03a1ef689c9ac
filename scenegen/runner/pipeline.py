"""A batch run: propose -> check -> build -> settle -> render -> store, committed in proposal-index order.

The proposer runs here; each proposal goes through :func:`~scenegen.runner.process.process_proposal`
on a backend (scenegen/runner/executors.py: this process, a spawn pool, or Ray actors), and
:func:`run_batch` is the only writer of the store: it commits outcomes strictly in proposal-index
order, so the accepted set is the N lowest-index accepted proposals whatever the backend and the
number of workers, and a killed batch resumes exactly.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml

from scenegen.propose.base import PROPOSERS, Proposer
from scenegen.runner.config import PipelineConfig
from scenegen.runner.executors import LOCAL, Backend, ordered_outcomes, start_workers, stop_pool
from scenegen.schema.scene import SceneProposal
from scenegen.store.batch import MANIFEST, TIMINGS, BatchStore, atomic_write
from scenegen.tags.predicates import PREDICATE_VERSION

STAGES = ("propose", "check", "build", "settle", "tag", "render", "store")
PROPOSAL_CHUNK = 8  # proposals drawn at a time (each is independent of the chunking)


def proposal_stream(proposer: Proposer, config: PipelineConfig, start: int) -> Iterator[SceneProposal]:
    for first in range(start, config.proposal_cap, PROPOSAL_CHUNK):
        yield from proposer.propose(
            config.condition, range(first, min(first + PROPOSAL_CHUNK, config.proposal_cap)), config.seed
        )


def _capped(config: PipelineConfig, accepted: int, rejections: Counter) -> bool:
    """Whether the recipe's ``max_tries`` are spent."""
    return config.max_tries is not None and accepted + sum(rejections.values()) >= config.max_tries


def _within_cap(config: PipelineConfig, tries: list, done: int) -> list:
    """An index's tries cut at the recipe's ``max_tries`` (``done`` made before it): the cut tries
    are dropped, as if the tries had been made one at a time; its last kept try (a rejection) is
    then the index's own row."""
    if config.max_tries is None or done + len(tries) <= config.max_tries:
        return tries
    return tries[: config.max_tries - done]


def make_proposer(config: PipelineConfig, catalog) -> Proposer:
    """The recipe's proposer, given what a proposer may not compute itself (it imports no MuJoCo):
    the arm's geoms at a robot pose (check.geometry.arm_discs) for a proposer that ``wants_arm``."""
    cls = PROPOSERS[config.proposer.kind]
    if getattr(cls, "wants_arm", False):
        from scenegen.check.geometry import arm_discs

        return cls(config.proposer, catalog, arm=arm_discs)
    return cls(config.proposer, catalog)


def _outcomes(
    proposals, proposer, config: PipelineConfig, workers: int, backend: Backend, seconds, pool=None
):
    """Per proposal index, in index order, the outcomes of its tries: one, or with the proposer's
    ``repairs`` the first pass and its repairs (runner/repairing.py), the repairs' making timed into
    ``seconds['propose']``; on ``pool`` where the workers were started already."""
    if not getattr(config.proposer, "repairs", 0):
        return _one_try_each(ordered_outcomes(proposals, config, workers, backend=backend, pool=pool))
    from scenegen.runner.repairing import repaired_outcomes

    def repair(parent, rejection, attempt):
        t0 = time.perf_counter()
        try:
            return proposer.repair(parent, rejection, attempt)
        finally:
            seconds["propose"] += time.perf_counter() - t0

    return repaired_outcomes(proposals, config, workers, repair, backend=backend, pool=pool)


def _one_try_each(outcomes):
    try:
        for outcome in outcomes:
            yield [outcome]
    finally:
        outcomes.close()  # stops the pool now, not at garbage collection


@dataclass
class BatchSummary:
    out: Path
    accepted: int
    proposals: int
    rejections: Counter
    seconds: dict[str, float]
    accepted_seconds: dict[str, float]
    accepted_cpu: dict[str, float]  # CPU seconds in the workers' stages, accepted scenes only
    wall: float


def run_batch(
    config: PipelineConfig,
    out: Path,
    workers: int = 1,
    progress: bool = True,
    backend: Backend = LOCAL,
) -> BatchSummary:
    """Generate ``config.n`` accepted scenes into ``out`` with ``workers`` workers of ``backend``,
    resuming a killed batch of the same recipe."""
    from tqdm import tqdm

    catalog = config.catalog()
    pool = start_workers(config, workers, backend)  # their start-up overlaps the proposer's loading
    try:
        proposer = make_proposer(config, catalog)
        store = BatchStore(out)
        state = store.open(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    except BaseException:
        if pool is not None:
            stop_pool(pool)
        raise
    seconds = dict.fromkeys(STAGES, 0.0)  # all proposals, summed over workers
    accepted_seconds = dict.fromkeys(STAGES, 0.0)  # accepted scenes only
    accepted_cpu = dict.fromkeys(STAGES, 0.0)
    cpu = dict.fromkeys(STAGES, 0.0)  # all proposals: the workers' CPU, the coordinator's proposing
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

    proposals = _timed(proposal_stream(proposer, config, index), seconds, cpu)
    outcomes = _outcomes(proposals, proposer, config, workers, backend, seconds, pool)  # lazy
    try:
        for tries in outcomes if accepted < config.n and not _capped(config, accepted, rejections) else ():
            tries = _within_cap(config, tries, accepted + sum(rejections.values()))
            *repaired, outcome = tries
            t0 = time.perf_counter()
            for rejected in repaired:  # tries that a repair followed
                for stage, s in rejected.seconds.items():
                    seconds[stage] += s
                for stage, s in rejected.cpu.items():
                    cpu[stage] += s
                store.log_rejection(rejected.rejection.model_copy(update={"repaired": True}))
                rejections[rejected.rejection.label] += 1
            seconds["store"] += time.perf_counter() - t0
            index = outcome.proposal_index + 1
            for stage, s in outcome.seconds.items():
                seconds[stage] += s
            for stage, s in outcome.cpu.items():
                cpu[stage] += s
            t0 = time.perf_counter()
            if outcome.record is not None:
                store.commit_scene(outcome.record, outcome.xml, outcome.needed, outcome.images)
                accepted += 1
                for stage, s in outcome.seconds.items():
                    accepted_seconds[stage] += s
                for stage, s in outcome.cpu.items():
                    accepted_cpu[stage] += s
                bar.update(1)
            else:
                store.log_rejection(outcome.rejection)
                rejections[outcome.rejection.label] += 1
            seconds["store"] += time.perf_counter() - t0
            bar.set_postfix_str(
                f"tries={index} " + " ".join(f"{k}={v}" for k, v in sorted(rejections.items())),
                refresh=False,
            )
            if accepted == config.n or _capped(config, accepted, rejections):
                break
    finally:
        outcomes.close()  # stops the pool now, not at garbage collection
        if pool is not None:  # never handed over when the batch was complete already
            stop_pool(pool)
        bar.close()
    wall = time.perf_counter() - start
    write_batch_manifest(out, config, catalog.sha256)
    proposals_done = accepted + sum(rejections.values())
    done = proposals_done - done_before
    run = {"wall": wall, "workers": workers, "backend": backend.kind, "proposals": done}
    write_timings(out / TIMINGS, run, seconds, cpu)
    return BatchSummary(
        out, accepted, proposals_done, rejections, seconds, accepted_seconds, accepted_cpu, wall
    )


def write_timings(path: Path, run: dict, seconds: Counter, cpu: Counter) -> None:
    """timings.json: wall and CPU seconds per stage summed over every finished run of the batch (a
    resumed batch's earlier runs included), each run's own wall, workers, backend and proposals under
    ``runs``; ``workers``, ``backend`` and ``proposals_this_run`` are the last run's. A run killed
    before its end adds nothing. Not part of the deterministic output."""
    runs, stages, cpus = _previous(path)
    if runs and not run["proposals"]:
        return  # a rerun of a complete batch: nothing done, nothing to add
    stages.update(seconds)
    cpus.update(cpu)
    runs.append({**run, "wall": round(run["wall"], 3)})
    timing = {
        "wall": round(sum(r["wall"] for r in runs), 3),
        "workers": run["workers"],
        "backend": run["backend"],
        "stages": {k: round(v, 3) for k, v in stages.items()},
        "cpu": {k: round(v, 3) for k, v in cpus.items()},
        "proposals_this_run": run["proposals"],
        "runs": runs,
    }
    atomic_write(path, json.dumps(timing, indent=1) + "\n")


def _previous(path: Path) -> tuple[list[dict], Counter, Counter]:
    """The runs and per-stage sums an earlier timings.json holds; none when there is none or it is not
    one this code wrote (a file from before ``runs`` existed counts as its one run)."""
    try:
        before = json.loads(path.read_text())
        runs = list(before.get("runs") or [_as_run(before)])
        stages, cpus = Counter(before.get("stages") or {}), Counter(before.get("cpu") or {})
        numbers = [r["wall"] for r in runs] + [*stages.values(), *cpus.values()]
        if all(isinstance(x, int | float) and not isinstance(x, bool) for x in numbers):
            return runs, stages, cpus
    except (OSError, ValueError, TypeError, AttributeError, KeyError):
        pass
    return [], Counter(), Counter()


def _as_run(timing: dict) -> dict:
    """A timings.json written before ``runs`` existed, as its one run."""
    keys = ("wall", "workers", "backend")
    return {**{k: timing[k] for k in keys}, "proposals": timing.get("proposals_this_run", 0)}


def write_batch_manifest(out: Path, config: PipelineConfig, catalog_sha: str):
    """Derive the batch's source from its files, compute its realism checks, and write
    ``out/manifest.yaml`` atomically (a run killed here leaves the previous manifest or none)."""
    from scenegen.manifest import Manifest, write_manifest
    from scenegen.manifest.derive import batch_source
    from scenegen.manifest.realism_checks import batch_realism

    source = batch_source(out, config, catalog_sha, PREDICATE_VERSION)
    source = source.model_copy(update={"realism": batch_realism(out, config, source.checksums.root)})
    manifest = Manifest(kind="batch", sources=[source])
    write_manifest(out / MANIFEST, manifest)
    return manifest


def _timed(
    proposals: Iterator[SceneProposal], seconds: dict[str, float], cpu: dict[str, float]
) -> Iterator[SceneProposal]:
    """Pass proposals through, adding the wall and CPU time spent making them to ``propose``."""
    while True:
        t0, c0 = time.perf_counter(), time.process_time()
        proposal = next(proposals, None)
        seconds["propose"] += time.perf_counter() - t0
        cpu["propose"] += time.process_time() - c0
        if proposal is None:
            return
        yield proposal
