"""Where the per-item work runs: this process, a local spawn pool, or Ray actors.

:func:`ordered_map` hands items to workers and yields the results in the items' order whatever the
backend, so its caller stays the only writer and commits in order. :func:`ordered_outcomes` is it
for proposals (``run_batch``, the reference builder, the sweep): a worker there ran
:func:`~scenegen.runner.process.init_worker` once (recipe, catalog, one GL context). The expert
labels (scenegen/policy/labels.py) map primitive executions the same way. With Ray a worker is an
actor holding one CPU. Closing the generator stops the workers.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import socket
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

from scenegen.runner.config import PipelineConfig
from scenegen.runner.process import Outcome, init_worker, shared_state, work
from scenegen.schema.scene import SceneProposal

BACKENDS = ("local", "ray")
RAY_PIN = "ray==2.60.0"  # measured with numpy<2 (shared/PITFALLS.md); the `ray` extra in pyproject.toml
IN_FLIGHT_PER_WORKER = 4  # items submitted ahead of the one the coordinator waits for
T = TypeVar("T")
R = TypeVar("R")


class BackendError(RuntimeError):
    """A backend that cannot run here (Ray missing, a cluster that cannot be reached)."""


@dataclass(frozen=True)
class Backend:
    """``kind`` "local" (this process for one worker, else a spawn pool) or "ray" (one actor per
    worker, 1 CPU each); ``address`` joins an existing Ray cluster ("auto", "ray://HOST:10001",
    "HOST:6379"), and without one ``ray.init`` starts a local cluster with ``workers`` CPUs.
    ``recycle_after``: a local pool's worker is replaced by a fresh one after this many items (its
    memory returned; the new one runs the initializer again); None: never. Items are pure functions of
    their inputs, so recycling changes no result, only what a long run holds."""

    kind: str = "local"
    address: str | None = None
    recycle_after: int | None = None

    def __post_init__(self):
        if self.kind not in BACKENDS:
            raise BackendError(f"backend {self.kind!r}: choose one of {', '.join(BACKENDS)}")
        if self.address is not None and self.kind != "ray":
            raise BackendError("--address names a Ray cluster: use it with --backend ray")
        if self.recycle_after is not None and (self.kind != "local" or self.recycle_after < 1):
            raise BackendError("--recycle-after: a positive number of items, with --backend local")


LOCAL = Backend()


def start_workers(
    config: PipelineConfig, workers: int, backend: Backend = LOCAL, export: bool = True
) -> ProcessPoolExecutor | None:
    """The local pool that :func:`ordered_outcomes` or ``repaired_outcomes`` would start for
    ``config``, started now, so that its workers load the recipe, the catalog and their GL context
    while the caller loads its proposer; they take it over (and stop it). None where they start no
    pool (one worker, or Ray, whose actors start with the map)."""
    if backend.kind != "local" or workers <= 1:
        return None
    initargs = (config.model_dump_json(), True, export, shared_state(config))
    return start_pool(workers, init_worker, initargs, backend.recycle_after)


def ordered_outcomes(
    proposals: Iterator[SceneProposal],
    config: PipelineConfig,
    workers: int,
    export: bool = True,
    backend: Backend = LOCAL,
    pool: ProcessPoolExecutor | None = None,
) -> Iterator[Outcome]:
    """Outcomes of ``proposals`` in their order, computed by ``workers`` workers of ``backend``
    (``pool``: the workers :func:`start_workers` started for them; stopped at the end)."""
    threads = _torch_threads(1)  # the proposer shares the cores; its sums as beside workers (repairing.py)
    if backend.kind == "local" and workers <= 1:
        try:
            init_worker(config.model_dump_json(), False, export)
            yield from map(work, proposals)
        finally:
            _torch_threads(threads)
        return
    try:
        initargs = () if pool else (config.model_dump_json(), True, export, shared_state(config))
        with one_blas_thread():
            yield from ordered_map(work, proposals, workers, init_worker, initargs, backend, pool)
    finally:
        _torch_threads(threads)


def one_blas_thread():
    """A context in which numpy's BLAS runs on one thread (threadpoolctl).

    numpy's OpenBLAS starts a thread per core; the proposer's and the checks' small products (the
    separating-axis tests' (V, 3) x (3, A)) then cost more CPU in thread hand-offs than in
    arithmetic: the diffusion proposer took 105 ms of CPU per proposal ("retrieve the can
    clutter") with the default threads and 62 ms with one (benchmarks/proposer_cpu.py). Where a
    process shares the cores with workers, those spare threads only take them from the workers."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def ordered_map(
    fn: Callable[[T], R],
    items: Iterable[T],
    workers: int,
    initializer: Callable[..., None] | None = None,
    initargs: tuple = (),
    backend: Backend = LOCAL,
    pool: ProcessPoolExecutor | None = None,
) -> Iterator[R]:
    """``fn(item)`` for each item, in the items' order, on ``workers`` workers of ``backend`` that
    each ran ``initializer(*initargs)`` once. ``fn`` and ``initializer`` are module-level functions
    (pickled by reference); at most IN_FLIGHT_PER_WORKER x workers items are out at a time, so
    ``items`` may be a lazy stream. ``pool``: a local pool already started with that initializer
    (:func:`start_pool`), used instead of a new one. Closing the generator stops the workers."""
    if pool is not None:
        yield from _pool_map(fn, items, workers, pool=pool)
    elif backend.kind == "ray":
        yield from _ray_map(fn, items, workers, initializer, initargs, backend.address)
    elif workers <= 1:
        if initializer is not None:
            initializer(*initargs)
        yield from map(fn, items)
    else:
        yield from _pool_map(fn, items, workers, initializer, initargs, backend.recycle_after)


def _pool_map(
    fn, items, workers: int, initializer=None, initargs=(), recycle_after: int | None = None, pool=None
) -> Iterator:
    pool = pool or start_pool(workers, initializer, initargs, recycle_after)
    try:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= IN_FLIGHT_PER_WORKER * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        stop_pool(pool)


def start_pool(
    workers: int, initializer, initargs: tuple, recycle_after: int | None = None
) -> ProcessPoolExecutor:
    """A spawn pool of ``workers`` processes that each ran ``initializer(*initargs)``, started now;
    each replaced after ``recycle_after`` items (None: kept)."""
    # concurrent.futures rather than multiprocessing.Pool: a worker that dies (or whose initializer
    # fails) breaks the pool with an error instead of being respawned forever.
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_pool_worker_start,
        initargs=(os.getpid(), initializer, initargs),
        max_tasks_per_child=recycle_after,
    )
    for _ in range(workers):  # start every worker now: their start-up overlaps the first items' making
        pool.submit(int)
    return pool


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """End the pool's workers now. Items still running when the caller stops early (a batch that has
    its n scenes) are not wanted: no waiting up to a proposal's time for them.

    The workers are ended before the pool is shut down, never after a ``shutdown(wait=False)``: that
    empties the pool's process table while its manager thread still runs, and a worker retired by
    ``max_tasks_per_child`` (--recycle-after) then makes the thread fail on it (CPython 3.11,
    concurrent/futures/process.py ``_adjust_process_count``). Ended workers break the pool: the
    manager thread fails the items left (nobody waits on them), ends any worker it had just started
    in a retired one's place, and returns."""
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def _pool_worker_start(coordinator: int, initializer, initargs: tuple) -> None:
    """A pool worker's first act: die with its coordinator, then the caller's initializer."""
    die_with_parent(coordinator)
    return_freed_memory()
    if initializer is not None:
        initializer(*initargs)


def die_with_parent(parent: int) -> None:
    """Have the kernel SIGKILL this process when its parent dies (Linux ``PR_SET_PDEATHSIG``), so a
    coordinator killed with SIGKILL leaves no worker behind; exit now if ``parent`` is already gone.
    Elsewhere, nothing (the pool's own broken-pipe handling ends idle workers)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before the call above took effect
        os._exit(1)


def return_freed_memory() -> None:
    """Have glibc's allocator give freed memory back to the kernel instead of keeping it (Linux).

    A worker builds and frees a MuJoCo model, fcl objects and images for every proposal. By default
    glibc raises its mmap threshold to the largest block freed so far (up to 32 MB), so those blocks
    move into its heap and their freed pages stay resident: a worker grew ~60 % over 3,000 scenes while
    its Python objects stayed constant. A fixed 256 kB mmap threshold (blocks above it are returned when
    freed) and a 1 MB trim threshold keep it flat: 432 -> 435 MB over 200 proposals in one process,
    against 489 -> 524 MB (+7 %) by default (docs/robustness.md, benchmarks/soak.py)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt(m_mmap_threshold, 256 * 1024)
        libc.mallopt(m_trim_threshold, 1024 * 1024)
    except AttributeError:  # not glibc
        pass


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


@contextlib.contextmanager
def backend_session(backend: Backend, workers: int):
    """Connect a Ray backend before any work starts (so an unreachable cluster is an error before a
    file is written) and shut down at the end what this started; nothing for the local backend."""
    if backend.kind != "ray":
        yield
        return
    started = connect_ray(backend.address, workers)
    try:
        yield
    finally:
        if started:
            import_ray().shutdown()


def _check_reachable(address: str) -> None:
    """A one-line error now, rather than Ray's minutes of retries, when nothing listens at HOST:PORT."""
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not host or not port.isdigit():
        return  # "auto" and the like: Ray resolves them itself
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise BackendError(
            f"--address {address}: no Ray cluster answers there ({reason}); start one with "
            "`ray start --head` or check HOST:PORT"
        ) from None


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
    if address:
        _check_reachable(address)
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
    """A Ray actor (1 CPU) that runs an initializer once, then one function call at a time."""

    def __init__(self, initializer, initargs: tuple):
        return_freed_memory()
        if initializer is not None:
            initializer(*initargs)

    def call(self, fn, item):
        return fn(item)


def _ray_map(fn, items, workers: int, initializer, initargs: tuple, address: str | None) -> Iterator:
    pool, stop = ray_actor_pool(workers, initializer, initargs, address)
    try:
        in_flight = 0
        for item in items:
            pool.submit(lambda a, x: a.call.remote(fn, x), item)
            in_flight += 1
            if in_flight >= IN_FLIGHT_PER_WORKER * workers:
                in_flight -= 1
                yield pool.get_next()
        while pool.has_next():
            yield pool.get_next()
    finally:
        stop()


def ray_actor_pool(workers: int, initializer, initargs: tuple, address: str | None):
    """A Ray ``ActorPool`` of ``workers`` :class:`RayWorker` actors (1 CPU each) that ran
    ``initializer(*initargs)``, and the function that ends them (and the cluster, if this started it)."""
    ray = import_ray()
    from ray.util import ActorPool

    started = connect_ray(address, workers)
    actor = ray.remote(num_cpus=1)(RayWorker)
    shared = ray.put(initargs)  # one copy in the object store for every actor
    actors = [actor.remote(initializer, shared) for _ in range(workers)]

    def stop() -> None:
        for a in actors:
            ray.kill(a)
        if started:
            ray.shutdown()

    return ActorPool(actors), stop  # ActorPool hands each item to an idle actor
