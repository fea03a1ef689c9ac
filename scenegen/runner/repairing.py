"""Proposals with repairs: each proposal index's tries (the first pass, then repairs made here, in the
coordinator, by the proposer) through the workers, the indices' outcomes in index order.

A worker imports no torch: a rejected try comes back here, the index's
:class:`~scenegen.propose.repair.RepairSearch` picks what to repair, the proposer makes the repair,
and it goes out again. Tries of different indices run side by side, and each index's tries are a
function of its first-pass proposal alone (every try is checked by the same pure stages, every
repair's noise is its own, the search decides only on complete expansions), so what an index ends
with does not depend on the number of workers or on which answered first. :func:`repaired_outcomes`
yields, per index and in index order, the outcomes of all its tries in attempt order; the last is
the index's own (accepted, or the last rejection).
"""

from __future__ import annotations

import concurrent.futures
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

from scenegen.propose.repair import RepairSearch
from scenegen.runner.config import PipelineConfig
from scenegen.runner.executors import (
    IN_FLIGHT_PER_WORKER,
    LOCAL,
    Backend,
    _torch_threads,
    one_blas_thread,
    ray_actor_pool,
    start_pool,
    stop_pool,
)
from scenegen.runner.process import Outcome, init_worker, shared_state, work
from scenegen.schema.scene import SceneProposal


@dataclass
class _Index:
    """One proposal index in flight: its search, tries sent out, outcomes back."""

    search: RepairSearch
    out: int = 0  # tries sent and not yet back
    outcomes: list[Outcome] = field(default_factory=list)
    done: bool = False


def repaired_outcomes(
    proposals: Iterator[SceneProposal],
    config: PipelineConfig,
    workers: int,
    repair,
    export: bool = True,
    backend: Backend = LOCAL,
    pool=None,
) -> Iterator[list[Outcome]]:
    """Per proposal index, in index order, the outcomes of its tries (see the module docstring);
    ``repair(parent, rejection, attempt)`` (the proposer's) makes a repair, ``config.proposer.repairs`` and
    ``repair_width`` bound the search; ``pool``: the local workers executors.start_workers started
    for them (stopped at the end)."""
    settings = config.proposer
    serial = workers <= 1 and backend.kind == "local"
    # One torch thread for the proposer, serial or not: besides sharing the cores with the workers,
    # its float32 sums then do not depend on the worker count (with 2 threads a projected repair
    # moved an object 0.7 micrometres from where it moved beside 2 workers, and the batch differed).
    threads = _torch_threads(1)
    if serial:
        init_worker(config.model_dump_json(), False, export)
        runner = _Serial()
    else:
        try:
            if pool is not None:
                runner = _Pool(workers, (), pool=pool)
            else:
                initargs = (config.model_dump_json(), True, export, shared_state(config))
                runner = (
                    _Ray(workers, initargs, backend)
                    if backend.kind == "ray"
                    else _Pool(workers, initargs, backend.recycle_after)
                )
        except BaseException:
            _torch_threads(threads)
            raise
    indices: dict[int, _Index] = {}
    order: deque[int] = deque()
    proposals = iter(proposals)
    exhausted = False
    try:
        with one_blas_thread():
            while True:
                ahead = IN_FLIGHT_PER_WORKER * max(workers, 1)
                # bounded by tries out and by indices waiting behind an unfinished head (a long chain
                # there must not let finished later indices, images and all, pile up in memory)
                while not exhausted and runner.in_flight < ahead and len(order) < 2 * ahead:
                    proposal = next(proposals, None)
                    if proposal is None:
                        exhausted = True
                        break
                    search = RepairSearch(settings.repairs, settings.repair_width, settings.repair_labels)
                    indices[proposal.index] = _Index(search)
                    order.append(proposal.index)
                    _send(runner, indices[proposal.index], proposal)
                while order and indices[order[0]].done:
                    yield _finished(indices.pop(order.popleft()))
                if not runner.in_flight:
                    if exhausted and not order:
                        return
                    continue
                proposal, outcome = runner.next_done()
                _returned(indices[proposal.index], proposal, outcome, runner, repair)
    finally:
        runner.close()
        _torch_threads(threads)


def _send(runner, state: _Index, proposal: SceneProposal) -> None:
    state.out += 1
    runner.submit(proposal)


def _returned(state: _Index, proposal: SceneProposal, outcome: Outcome, runner, repair) -> None:
    """A try came back: record it, and once every try of the expansion is back, expand or finish."""
    state.out -= 1
    state.outcomes.append(outcome)
    if outcome.record is None:
        state.search.add(proposal, outcome.rejection)
    if state.out:
        return  # siblings still out: decide on the whole expansion
    if any(o.record is not None for o in state.outcomes):
        state.done = True
        return
    for parent, rejection, attempt in state.search.next_parents():
        child = repair(parent, rejection, attempt)
        if child is not None:
            _send(runner, state, child)
    state.done = state.out == 0


def _finished(state: _Index) -> list[Outcome]:
    """The index's outcomes in attempt order, ending with its own: the accepted try of the lowest
    attempt (later accepted siblings and their rejected siblings after it are dropped), else the
    last rejection."""
    outcomes = sorted(state.outcomes, key=lambda o: o.attempt)
    accepted = [o for o in outcomes if o.record is not None]
    if not accepted:
        return outcomes
    return [o for o in outcomes if o.record is None and o.attempt < accepted[0].attempt] + [accepted[0]]


class _Serial:
    """This process: a try runs when its outcome is asked for."""

    def __init__(self):
        self.queue: deque[SceneProposal] = deque()

    @property
    def in_flight(self) -> int:
        return len(self.queue)

    def submit(self, proposal: SceneProposal) -> None:
        self.queue.append(proposal)

    def next_done(self) -> tuple[SceneProposal, Outcome]:
        proposal = self.queue.popleft()
        return proposal, work(proposal)

    def close(self) -> None:
        pass


class _Pool:
    """A local spawn pool (executors.start_pool), outcomes taken as they finish."""

    def __init__(self, workers: int, initargs: tuple, recycle_after: int | None = None, pool=None):
        self.pool = pool or start_pool(workers, init_worker, initargs, recycle_after)
        self.pending: dict[concurrent.futures.Future, SceneProposal] = {}

    @property
    def in_flight(self) -> int:
        return len(self.pending)

    def submit(self, proposal: SceneProposal) -> None:
        self.pending[self.pool.submit(work, proposal)] = proposal

    def next_done(self) -> tuple[SceneProposal, Outcome]:
        done, _ = concurrent.futures.wait(self.pending, return_when=concurrent.futures.FIRST_COMPLETED)
        future = min(done, key=lambda f: (self.pending[f].index, self.pending[f].attempt))
        return self.pending.pop(future), future.result()

    def close(self) -> None:
        stop_pool(self.pool)


class _Ray:
    """Ray actors (executors.ray_actor_pool), outcomes taken as they finish."""

    def __init__(self, workers: int, initargs: tuple, backend: Backend):
        self.pool, self.close = ray_actor_pool(workers, init_worker, initargs, backend.address)
        self.in_flight = 0

    def submit(self, proposal: SceneProposal) -> None:
        self.pool.submit(lambda a, p: a.call.remote(_work_pair, p), proposal)
        self.in_flight += 1

    def next_done(self) -> tuple[SceneProposal, Outcome]:
        self.in_flight -= 1
        return self.pool.get_next_unordered()


def _work_pair(proposal: SceneProposal) -> tuple[SceneProposal, Outcome]:
    return proposal, work(proposal)
