"""Where the per-proposal work runs: this process, a local spawn pool, or Ray actors.

Every backend yields :class:`~scenegen.runner.process.Outcome` objects in proposal order, so the
coordinator (``run_batch``, the reference builder, the sweep) stays the only writer and commits in
proposal-index order whatever runs the work. A worker is a process that ran
:func:`~scenegen.runner.process.init_worker` once (recipe, catalog, one GL context); with Ray it is an
actor holding one CPU. Closing the generator stops the workers.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from scenegen.runner.config import PipelineConfig
from scenegen.runner.process import Outcome, init_worker, shared_state, work
from scenegen.schema.scene import SceneProposal

BACKENDS = ("local", "ray")
RAY_PIN = "ray==2.60.0"  # measured with numpy<2 (shared/PITFALLS.md); the `ray` extra in pyproject.toml
IN_FLIGHT_PER_WORKER = 4  # proposals submitted ahead of the one the coordinator waits for


class BackendError(RuntimeError):
    """A backend that cannot run here (Ray missing, a cluster that cannot be reached)."""


@dataclass(frozen=True)
class Backend:
    """``kind`` "local" (this process for one worker, else a spawn pool) or "ray" (one actor per
    worker, 1 CPU each); ``address`` joins an existing Ray cluster ("auto", "ray://HOST:10001",
    "HOST:6379"), and without one ``ray.init`` starts a local cluster with ``workers`` CPUs."""

    kind: str = "local"
    address: str | None = None

    def __post_init__(self):
        if self.kind not in BACKENDS:
            raise BackendError(f"backend {self.kind!r}: choose one of {', '.join(BACKENDS)}")
        if self.address is not None and self.kind != "ray":
            raise BackendError("--address names a Ray cluster: use it with --backend ray")


LOCAL = Backend()


def ordered_outcomes(
    proposals: Iterator[SceneProposal],
    config: PipelineConfig,
    workers: int,
    export: bool = True,
    backend: Backend = LOCAL,
) -> Iterator[Outcome]:
    """Outcomes of ``proposals`` in their order, computed by ``workers`` workers of ``backend``."""
    if backend.kind == "local" and workers <= 1:
        init_worker(config.model_dump_json(), False, export)
        yield from map(work, proposals)
        return
    threads = _torch_threads(1)  # the proposer (this process) shares the cores with the workers
    try:
        if backend.kind == "ray":
            yield from _ray_outcomes(proposals, config, workers, export, backend.address)
        else:
            yield from _pool_outcomes(proposals, config, workers, export)
    finally:
        _torch_threads(threads)


def _torch_threads(n: int) -> int | None:
    """Set torch's intra-op threads in this process to ``n`` (if torch is loaded); the previous count.

    With one worker per core a second proposer thread only spins: the diffusion proposer took 0.53 s
    per proposal with 2 threads beside 2 busy workers and 0.07 s with 1, the proposals bit-identical
    (measured on 2 cores, benchmarks/pipeline_throughput.py). Restored afterwards, so what the caller
    does next (training, say) runs as it did before.
    """
    torch = sys.modules.get("torch")
    if torch is None or n is None:
        return None
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    return before


def _pool_outcomes(proposals, config: PipelineConfig, workers: int, export: bool) -> Iterator[Outcome]:
    # concurrent.futures rather than multiprocessing.Pool: a worker that dies (or whose initializer
    # fails) breaks the pool with an error instead of being respawned forever.
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=init_worker,
        initargs=(config.model_dump_json(), True, export, shared_state(config)),
    )
    try:
        pending: deque = deque()
        for proposal in proposals:
            pending.append(pool.submit(work, proposal))
            if len(pending) >= IN_FLIGHT_PER_WORKER * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


# ------------------------------------------------------------------------------------------- Ray


def import_ray():
    """The ``ray`` module, or a one-line error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise BackendError(
            f"--backend ray needs Ray, which is not installed: pip install 'scenegen[ray]' ({RAY_PIN})"
        ) from None
    return ray


def connect_ray(address: str | None, num_cpus: int) -> bool:
    """Join the cluster at ``address``, or start a local one with ``num_cpus`` CPUs; nothing when
    Ray is already initialized in this process. True when this call connected (the caller shuts down)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    # Workers on other nodes do not inherit this shell: pass what the renderer reads.
    env = {k: os.environ[k] for k in ("MUJOCO_GL", "PYOPENGL_PLATFORM") if k in os.environ}
    env["LP_NUM_THREADS"] = "1"  # llvmpipe on one core per worker, as in the local pool
    options = dict(
        include_dashboard=False,
        log_to_driver=False,
        logging_level=logging.ERROR,
        runtime_env={"env_vars": env},
    )
    try:
        if address:
            ray.init(address=address, **options)
        else:
            # Ray runs its workers at niceness 15 by default; ours are the job, as in the local pool.
            # "local": a new cluster even if another one runs here (ray.init() would join the latest).
            ray.init("local", num_cpus=num_cpus, _system_config={"worker_niceness": 0}, **options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {address!r}" if address else "a local Ray cluster"
        raise BackendError(f"could not connect to {where}: {str(exc).splitlines()[0][:200]}") from None
    return True


class RayWorker:
    """A Ray actor (1 CPU) that loads the recipe, the catalog and one GL context once."""

    def __init__(self, config_json: str, export: bool, scorer=None):
        init_worker(config_json, True, export, scorer)

    def work(self, proposal: SceneProposal) -> Outcome:
        return work(proposal)


def _ray_outcomes(
    proposals, config: PipelineConfig, workers: int, export: bool, address: str | None
) -> Iterator[Outcome]:
    ray = import_ray()
    from ray.util import ActorPool

    started = connect_ray(address, workers)
    actor = ray.remote(num_cpus=1)(RayWorker)
    shared = ray.put(shared_state(config))  # one copy in the object store for every actor
    actors = [actor.remote(config.model_dump_json(), export, shared) for _ in range(workers)]
    pool = ActorPool(actors)  # hands each proposal to an idle actor; get_next() keeps submission order
    try:
        in_flight = 0
        for proposal in proposals:
            pool.submit(lambda a, p: a.work.remote(p), proposal)
            in_flight += 1
            if in_flight >= IN_FLIGHT_PER_WORKER * workers:
                in_flight -= 1
                yield pool.get_next()
        while pool.has_next():
            yield pool.get_next()
    finally:
        for a in actors:
            ray.kill(a)
        if started:
            ray.shutdown()
