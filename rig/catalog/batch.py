"""The batch engine: run independent tasks (one per file or per trial) on Dask.

One function, :func:`run_tasks`, maps a **top-level** function over a list of
plain values (paths, numbers, dicts) and returns one :class:`TaskResult` per
item, in the input order. Nothing goes through shared globals: a task gets its
inputs as arguments and returns its outputs as a value, so the same call runs

- in this process (``jobs=1``, no Dask at all: the serial reference),
- in this process and ``jobs - 1`` worker *processes* of its own, one thread each, all
  taking tasks from one queue (``jobs=None``: every core of the machine; a
  ``ProcessPoolExecutor`` forked from a preloaded forkserver, no Dask), or
- on an existing Dask cluster (``scheduler="tcp://HOST:PORT"``): the workers must have
  ``rig`` importable and see the same paths (a shared file system).

A task that raises is caught on the worker and comes back as a failed
:class:`TaskResult` (``ok=False``, ``error`` one line naming the exception); the
other tasks go on. ``progress(done, total, result)`` is called in the caller's
process as each task finishes (in completion order), so a rich progress bar can
follow the work.

An :class:`Engine` holds one set of workers for several runs (``rig identify DIR`` indexes and
analyses on one; ``mapper`` wraps one for ``rig reproduce`` and ``rig stability``); the
commands' engines are this process's shared ones (:func:`shared_engine`): workers one
command started serve the next commands of the same process and stop at exit; it
orders the work longest first when given a ``cost``, starts its workers only for a batch
whose estimated work pays their start back, and computes in this process meanwhile
(docs/scaling.md).

Determinism: the tasks are pure functions of their arguments (seeds included),
so a run on a cluster is bit for bit the serial run (``tests/system/catalog/test_batch.py``).
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
import traceback
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator


@dataclass
class TaskResult:
    """The outcome of one task: ``value`` when ``ok``, else ``error`` (one line)."""

    item: Any
    ok: bool
    value: Any = None
    error: str | None = None
    seconds: float = 0.0
    worker: str = ""
    cpu_seconds: float = 0.0  # CPU time of the task's process while it ran (seconds < cpu: waiting for a core)
    detail: str = field(default="", repr=False)  # the traceback, for --verbose style reporting


def _guarded(fn: Callable, item: Any) -> TaskResult:
    """Run one task, never raising: the worker-side wrapper (top level, so it pickles by name)."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        value = fn(item)
        return TaskResult(item, True, value, None, time.perf_counter() - t0, _worker_name(),
                          cpu_seconds=time.process_time() - c0)
    except Exception as exc:  # noqa: BLE001 - a failed task is data, not a crash of the batch
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        return TaskResult(item, False, None, f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__,
                          time.perf_counter() - t0, _worker_name(), detail=traceback.format_exc(),
                          cpu_seconds=time.process_time() - c0)


_POOL_WORKER = False  # set in a worker process of this engine's own pool (_pool_worker_init)


def _worker_name() -> str:
    if _POOL_WORKER:
        return f"pool:{os.getpid()}"
    if "distributed" in sys.modules:  # never imported for it: a serial run would pay 0.3 s
        try:
            from distributed import get_worker

            return str(get_worker().address)
        except Exception:  # noqa: BLE001 - not on a worker: the local process
            pass
    return f"local:{os.getpid()}"


def default_jobs() -> int:
    """Every core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


CONNECT_TIMEOUT_S = 10.0  # how long to try reaching --scheduler before giving up


# The LocalCluster's configuration (measured in docs/scaling.md, "Where the time went"):
# - workers are separate processes (the analyses hold the GIL), one thread each;
# - no spill to disk and no memory target: tasks are small and their data travels by path;
# - the worker environment is Dask's default *without* MALLOC_TRIM_THRESHOLD_=65536: with it,
#   glibc hands every freed block above 64 kB back to the kernel and the next numpy temporary
#   faults it in again; a reproduce trial then costs 22 % more CPU than in a plain process
#   (10.8 s against 8.8 s for 24 trials, the same in a serial run given that variable);
#   one BLAS/OpenMP/numba thread per worker is kept (N workers on N cores; rig has no parallel kernel);
# - no statistical profiler in the workers (it samples the task's stack every 10 ms, 3-4 %
#   of a task's CPU, for a dashboard that is off).
WORKER_CONFIG = {
    "distributed.worker.daemon": False,
    "distributed.admin.tick.limit": "60s",
    "distributed.worker.memory.spill": False,
    "distributed.worker.memory.target": False,
    "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1,
                                            "NUMBA_NUM_THREADS": 1},
    "distributed.worker.profile.enabled": False,
}


# A Nanny with Dask's default configuration writes its pre-spawn variables into *this*
# process's environment and leaves them there (distributed 2026.8, nanny.py), so one default
# LocalCluster in a process would hand MALLOC_TRIM_THRESHOLD_ to every later worker; the
# value this process started with is put back before each of ours starts.
_MALLOC_ENV = "MALLOC_TRIM_THRESHOLD_"
_MALLOC_ENV_AT_IMPORT = os.environ.get(_MALLOC_ENV)


def _restore_malloc_env() -> None:
    if _MALLOC_ENV_AT_IMPORT is None:
        os.environ.pop(_MALLOC_ENV, None)
    else:
        os.environ[_MALLOC_ENV] = _MALLOC_ENV_AT_IMPORT


# How worker processes start. "forkserver": one server process imports distributed and the
# task's module (numpy, scipy, numba, rig) once, and each worker is forked from it with all
# of that loaded, instead of every spawned worker importing it all again (docs/scaling.md).
START_METHOD = os.environ.get("RIG_BATCH_START_METHOD", "forkserver")
if START_METHOD not in multiprocessing.get_all_start_methods():  # e.g. no forkserver on Windows
    START_METHOD = "spawn"


#: imported by the forkserver last: numba's CPU target loaded once for all workers (rig.catalog.kernels_preload)
KERNELS_PRELOAD = "rig.catalog.kernels_preload"


def _forkserver_preload(modules: list[str]) -> None:
    """The modules the forkserver imports when it starts (the first cluster of this process;
    later calls change nothing once it runs)."""
    import dask
    from distributed.utils import get_mp_context

    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        ctx = get_mp_context()  # distributed sets its own preload list on the first call; ours replaces it
    ctx.set_forkserver_preload(list(dict.fromkeys(modules)))


class BatchError(RuntimeError):
    """The engine could not start (bad --jobs, unreachable scheduler, Dask missing)."""


@contextmanager
def dask_client(jobs: int | None = None, scheduler: str | None = None, preload: Iterable[str] = ()) -> Iterator[Any]:
    """A ``distributed.Client``: to ``scheduler`` when given, else to a new LocalCluster of
    ``jobs`` worker processes (default: every core), one thread each; closed on exit.
    ``preload``: modules each new worker imports before it joins (a task's module), so that
    a joined worker computes at once instead of importing numpy, scipy and rig first."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a dependency of rig
        raise BatchError(f"dask.distributed is not installed ({exc}); pip install 'dask[distributed]'") from exc
    if scheduler:
        if not scheduler.startswith(("tcp://", "tls://", "inproc://", "ws://", "wss://")):
            raise BatchError(f"--scheduler {scheduler!r}: expected an address like tcp://HOST:PORT")
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError) as exc:
            raise BatchError(f"--scheduler {scheduler}: cannot connect ({exc})") from exc
        try:
            yield client
        finally:
            client.close()
        return
    n = default_jobs() if jobs is None else int(jobs)
    if n < 1:
        raise BatchError(f"--jobs must be at least 1 (got {jobs})")
    import dask

    _restore_malloc_env()
    if START_METHOD == "forkserver":
        _forkserver_preload(["distributed", *preload, KERNELS_PRELOAD])
    with dask.config.set({**WORKER_CONFIG, "distributed.worker.multiprocessing-method": START_METHOD}):
        # no dashboard; the scheduler's own HTTP routes (health, metrics) on a free port rather
        # than 8787, which another cluster on the host may hold (a warning, and a wait)
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               scheduler_kwargs={"dashboard_address": ":0"}, silence_logs=40,
                               preload=list(preload))
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


def _pool_worker_init() -> None:
    """A pool worker's start: one BLAS/OpenMP thread (N processes on N cores; the numpy it inherited
    runs one thread per core), Ctrl-C left to the calling process (which stops the batch), and the
    worker's name in its results."""
    global _POOL_WORKER
    _POOL_WORKER = True
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if POOL_START == "fork":  # the streams' locks as a thread of the parent (a progress bar) may have held them
        for name, fd in (("stdout", 1), ("stderr", 2)):
            old = getattr(sys, name)
            try:
                setattr(sys, name, open(fd, "w", buffering=1, closefd=False, encoding=getattr(old, "encoding", None),
                                        errors="backslashreplace"))
            except (OSError, ValueError):  # no such descriptor: keep the inherited object
                pass
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[v] = "1"  # for the processes a task may start
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - a dependency of rig
        pass


#: how this process's own workers start (``RIG_BATCH_POOL_START``): "fork" (Linux' default here): a copy of
#: this process, made in milliseconds, with everything the batch's first tasks imported and loaded
#: (numpy, scipy, numba's target and kernels, rig), forked from the main thread before any thread of the
#: batch starts; "forkserver": from a server that imports the task's module first (1.2-1.5 s here, on the
#: other core; the start for a platform without fork, or a process whose other threads make a fork unsafe)
POOL_START = os.environ.get("RIG_BATCH_POOL_START", "fork")
if POOL_START not in multiprocessing.get_all_start_methods():
    POOL_START = START_METHOD


def _pool_context(preload: list[str]) -> Any:
    """The multiprocessing context of the pool's workers (``POOL_START``); a forkserver imports ``preload``
    (the task's module) and numba's CPU target once, when it is the first of this process."""
    ctx = multiprocessing.get_context(POOL_START)
    if POOL_START == "forkserver":
        ctx.set_forkserver_preload(list(dict.fromkeys([*preload, KERNELS_PRELOAD])))
    return ctx


class _Pool:
    """This process's own workers: ``workers`` processes (a ``ProcessPoolExecutor``, one task at a time
    each), fed by a thread of this process from the batch's shared queue, while this process takes
    tasks from the same queue itself (:func:`_share`). A worker that dies fails its task only; the
    queue's other tasks are then run here (the pool is marked ``broken``)."""

    def __init__(self, workers: int, preload: list[str]):
        from concurrent.futures import ProcessPoolExecutor

        self.workers = int(workers)
        self.broken = False
        self.executor = ProcessPoolExecutor(self.workers, mp_context=_pool_context(preload),
                                            initializer=_pool_worker_init)

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)

    def kill(self) -> None:
        """Stop the workers now (their running tasks are lost); the pool is broken from here on."""
        self.broken = True
        for proc in list((getattr(self.executor, "_processes", None) or {}).values()):
            proc.terminate()
        self.executor.shutdown(wait=False, cancel_futures=True)


def _share(pool: _Pool, fn: Callable, items: list, order: list[int], record: Callable[[int, TaskResult], None],
           local: Callable[[int], None]) -> None:
    """Run ``items[order]`` (longest first) on the pool's workers and in this process together: each
    takes the next task of the queue when it is free (list scheduling, so the batch ends within one
    task of even); a feeder thread keeps every worker busy while this process computes."""
    from concurrent.futures import FIRST_COMPLETED, wait
    from concurrent.futures.process import BrokenProcessPool

    todo = list(order)
    lock = threading.Lock()

    def take() -> int | None:
        with lock:
            return todo.pop(0) if todo else None

    running: dict = {}

    def fill() -> None:
        while not pool.broken and len(running) < pool.workers and (i := take()) is not None:
            try:
                running[pool.executor.submit(_guarded, fn, items[i])] = i
            except (BrokenProcessPool, RuntimeError):  # the pool is gone: the caller runs the rest
                pool.broken = True
                with lock:
                    todo.insert(0, i)

    def feed() -> None:
        while True:
            fill()
            if not running:
                return
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                i = running.pop(fut)
                try:
                    r = fut.result()
                except Exception as exc:  # noqa: BLE001 - the worker died (BrokenProcessPool) or could not unpickle
                    pool.broken = pool.broken or isinstance(exc, BrokenProcessPool)
                    r = TaskResult(items[i], False, None, f"{type(exc).__name__}: {exc}".splitlines()[0],
                                   worker="pool")
                record(i, r)

    fill()  # the first tasks from this thread: a forking pool makes its workers now, before the feeder exists
    feeder = threading.Thread(target=feed, name="rig-batch-feeder", daemon=True)
    feeder.start()
    try:
        with _one_blas_thread():  # this process is one of the N workers now
            while (i := take()) is not None:
                local(i)
    except BaseException:  # Ctrl-C (or an error) here: the workers' tasks are abandoned, not waited for
        with lock:
            todo.clear()
        pool.kill()
        raise
    finally:
        feeder.join()


@contextmanager
def _one_blas_thread() -> Iterator[None]:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency of rig
        yield
        return
    with threadpool_limits(1):
        yield


#: what starting this process's own workers costs a batch, in seconds of wall time during which the
#: batch has one worker fewer: a fork of this process (milliseconds, then its copy-on-write page faults:
#: 0.3 s is generous), or with a forkserver its imports (numpy, scipy, numba, rig, numba's CPU target:
#: 1.2-1.5 s here, on a core this process does not use). The work left must exceed ``PAYBACK x`` this
#: for the workers to start (docs/scaling.md).
START_COST_S = 0.3 if POOL_START == "fork" else 1.5
PAYBACK = 2.0


class Engine:
    """Where a batch's tasks run, for one or more :meth:`run` calls (one set of workers for all).

    - ``jobs=1``, no ``scheduler``: serially in this process (no Dask, no worker);
    - ``scheduler`` (or a ``distributed.Client``): on that Dask cluster, connected at the first run;
    - otherwise this process and ``jobs - 1`` worker processes of its own (default ``jobs``: every
      core): a ``ProcessPoolExecutor`` whose workers are forks of this process with everything loaded
      (``POOL_START``), one thread each. This process computes too: it and
      the workers take the next task of one longest-first queue whenever they are free. No Dask
      scheduler, nanny or worker here: the calling process spends milliseconds, not 0.4 s of CPU,
      on starting them, and 0.15 ms per task instead of Dask's 4-14 ms (docs/scaling.md).

    A batch never pays for workers it cannot use: with none started yet, this process runs the
    batch's cheapest tasks first and, from their measured CPU times and the tasks' ``cost`` (seconds
    per unit of cost; per task without one), estimates the rest; only when the work left exceeds
    ``PAYBACK`` x ``start_cost_s`` do the workers start (this process going on meanwhile). A short
    batch therefore runs as ``--jobs 1`` does; a long one grows onto the workers.

    The results do not depend on where a task ran (pure tasks: ``tests/system/catalog/test_batch.py``).
    """

    def __init__(self, jobs: int | None = None, scheduler: str | None = None, client: Any = None,
                 start_cost_s: float = START_COST_S):
        if jobs is not None and int(jobs) < 1:
            raise BatchError(f"--jobs must be at least 1 (got {jobs})")
        if jobs is None and scheduler is None and client is None and default_jobs() == 1:
            jobs = 1  # one core: a worker process would only add its start
        self.jobs, self.scheduler = jobs, scheduler
        self._client = client
        self._pool: _Pool | None = None
        self._stack = ExitStack()
        self._error: BaseException | None = None
        self.local_tasks = 0  # tasks this process ran in the last parallel run (a figure for benchmarks)
        self.start_cost_s = float(start_cost_s)
        self.estimate_s: float | None = None  # the last estimate of the work left when the decision was made

    @property
    def serial(self) -> bool:
        return self._client is None and self.scheduler is None and self.jobs == 1

    def client(self) -> Any:
        """The Dask client of ``scheduler`` (connected at the first call)."""
        if self._client is None:
            self._client = self._stack.enter_context(dask_client(self.jobs, self.scheduler))
        return self._client

    def run(self, fn: Callable[[Any], Any], items: Iterable[Any], *,
            progress: Callable[[int, int, TaskResult], None] | None = None,
            cost: Callable[[Any], float] | None = None) -> list[TaskResult]:
        """:func:`run_tasks` on this engine. ``progress`` is called under a lock, from this process's
        thread or its feeder thread, as each task finishes."""
        items = list(items)
        n = len(items)
        out: list[TaskResult | None] = [None] * n
        order = lpt_order(items, cost)
        done = 0
        lock = threading.Lock()

        def _record(i, r):
            nonlocal done
            with lock:
                out[i] = r
                done += 1
                if progress:
                    progress(done, n, r)

        def _local(i):
            _record(i, _guarded(fn, items[i]))
            self.local_tasks += 1

        self.local_tasks = 0
        if self.scheduler is not None or self._client is not None:
            for i, r in zip(order, _run_on(self.client(), fn, [items[i] for i in order],
                                           (lambda d, t, r: progress(d, n, r)) if progress else None)):
                out[i] = r
            return out  # type: ignore[return-value]
        workers = (self.jobs or default_jobs()) - 1
        rest = order
        if workers >= 1 and n > 1 and (self._pool is None or self._pool.broken):
            rest = self._in_process_until_long(items, rest, cost, _local)
            if rest:
                if self._pool is not None:  # a worker died in an earlier run: a new pool
                    self._pool.close()
                self._pool = _Pool(workers, [fn.__module__] if fn.__module__ not in ("__main__", "__mp_main__")
                                   else [])
        if workers >= 1 and len(rest) > 1 and self._pool is not None and not self._pool.broken:
            _share(self._pool, fn, items, rest, _record, _local)
        for i in rest:  # serially: --jobs 1, one task, or what a broken pool left
            if out[i] is None:
                _local(i)
        return out  # type: ignore[return-value]

    def _in_process_until_long(self, items: list, rest: list[int], cost, run_local) -> list[int]:
        """Run the cheapest tasks here while the work left is too short for the workers to pay back their
        start; return the tasks left for them (empty: all done here). With this process computing
        throughout, N processes finish work W (serial seconds) started after the workers' start s in
        about s + (W - s) / N: they save (W - s)(1 - 1/N), nothing unless W > s; ``PAYBACK`` x s leaves
        room for the estimate's error and for a loaded machine, where the start competes for a core."""
        costs = {i: max(0.0, float(cost(items[i]))) if cost is not None else 1.0 for i in rest}
        rates: list[float] = []
        while rest:
            if len(rates) >= 2:
                # not the first task's rate: in a fresh process it pays the imports and numba's loads the
                # others reuse (a 12-trial reproduce, 0.6 s a trial, started a cluster on it: 0.77x)
                later = sorted(rates[1:])
                rate = later[len(later) // 2]
                left = sum(costs[i] for i in rest) * rate
                self.estimate_s = left
                if left > PAYBACK * self.start_cost_s:
                    return rest
            if self.start_cost_s <= 0 and len(rest) > 1:
                return rest  # asked to always use the workers
            i = rest[-1]
            # the task's CPU time, not its wall time: on a busy machine the wall time of a task grows with
            # the others' load, and a cluster on the same busy cores would not escape that load (the
            # batch's tasks compute: identify, diagnose, index, simulate); measured: 12 files at load 18
            # started a cluster on their inflated wall times and took 0.76x of --jobs 1 (docs/scaling.md)
            c0 = time.process_time()
            run_local(i)
            dt = time.process_time() - c0
            c = costs[i] if costs[i] > 0 else (sum(costs.values()) / len(costs) or 1.0)
            rates.append(dt / c)
            rest = rest[:-1]
        return rest

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        self._stack.close()


#: the engines of this process's own workers, by (jobs, start cost): the workers one command
#: started serve the next commands of the same process (closed at exit, :func:`close_shared`)
_SHARED: dict[tuple, Engine] = {}
_ATEXIT: list = []


def _alive(eng: Engine) -> bool:
    """False when the engine's workers died or its Dask client is no longer running."""
    if eng._error is not None or (eng._pool is not None and eng._pool.broken):
        return False
    client = eng._client
    return client is None or getattr(client, "status", "running") == "running"


def shared_engine(jobs: int | None = None, start_cost_s: float = START_COST_S) -> Engine:
    """This process's :class:`Engine` for ``jobs`` processes of its own: made at the first
    call, kept for the later ones (``rig identify``, ``diagnose``, ``reproduce``, ``stability`` called
    one after another in one process pay the workers' start once), closed when the process exits.
    One whose worker died is replaced."""
    key = (jobs, float(start_cost_s))
    eng = _SHARED.get(key)
    if eng is not None and not _alive(eng):
        _SHARED.pop(key)
        try:
            eng.close()
        except Exception:  # noqa: BLE001 - a dead cluster's close may fail; it is dropped either way
            pass
        eng = None
    if eng is None:
        if not _ATEXIT:
            _ATEXIT.append(atexit.register(close_shared))
        eng = _SHARED[key] = Engine(jobs, None, start_cost_s=start_cost_s)
    return eng


def close_shared() -> None:
    """Close every shared engine (their clusters); registered with ``atexit``."""
    while _SHARED:
        _, eng = _SHARED.popitem()
        try:
            eng.close()
        except Exception:  # noqa: BLE001 - at exit: nothing left to report to
            pass


@contextmanager
def engine(jobs: int | None = None, scheduler: str | None = None,
           start_cost_s: float = START_COST_S, *, shared: bool = True) -> Iterator[Engine]:
    """An :class:`Engine` for several runs (one cluster); pass it as ``run_tasks(..., client=engine)``.
    ``shared`` (and no ``scheduler``): this process's engine (:func:`shared_engine`), kept open after
    the block for the process's next commands; else one of its own, closed on exit."""
    if shared and scheduler is None and jobs != 1:
        yield shared_engine(jobs, start_cost_s)
        return
    eng = Engine(jobs, scheduler, start_cost_s=start_cost_s)
    try:
        yield eng
    finally:
        eng.close()


def run_tasks(fn: Callable[[Any], Any], items: Iterable[Any], *, jobs: int | None = None,
              scheduler: str | None = None, progress: Callable[[int, int, TaskResult], None] | None = None,
              client: Any = None, cost: Callable[[Any], float] | None = None,
              start_cost_s: float = START_COST_S) -> list[TaskResult]:
    """Map ``fn`` (a top-level function of one plain argument) over ``items``.

    ``jobs=1`` and no ``scheduler``/``client``: serial, in this process. Otherwise in parallel
    (see the module docstring): ``client`` a ``distributed.Client`` or an :class:`Engine`;
    without one, an engine for this call alone (its workers start while this process
    works, see :class:`Engine`). The results are in the order of ``items``; a failed task
    is a ``TaskResult`` with ``ok=False``; ``progress`` sees each one as it finishes.

    ``cost(item)``, an estimate of a task's run time in any unit, orders the work:
    longest first (LPT), so that the batch does not end with one worker finishing a long task
    while the others are idle. It changes no result, only the order of completion. With an
    engine of its own, the work is estimated from it and measured CPU times, and a batch too short to
    pay back ``start_cost_s`` runs in this process (:class:`Engine`).
    """
    items = list(items)
    if not items:
        return []
    if isinstance(client, Engine):
        return client.run(fn, items, progress=progress, cost=cost)
    if client is not None:
        return _run_on(client, fn, items, progress, cost)
    with engine(jobs, scheduler, start_cost_s, shared=False) as eng:
        return eng.run(fn, items, progress=progress, cost=cost)


def lpt_order(items: list, cost: Callable[[Any], float] | None) -> list[int]:
    """Indices of ``items``, longest estimated ``cost`` first (ties: input order); the input
    order when ``cost`` is None."""
    if cost is None:
        return list(range(len(items)))
    c = [float(cost(it)) for it in items]
    return sorted(range(len(items)), key=lambda i: (-c[i], i))


def _run_on(client, fn, items, progress, cost=None) -> list[TaskResult]:
    from distributed import as_completed

    order = lpt_order(items, cost)
    # pure=False: every item is its own task, even equal ones; the key maps a result back to
    # its item; the priority (higher first) makes the scheduler hand them out in LPT order
    stamp = f"{os.getpid()}-{time.time_ns()}"
    futures = [client.submit(_guarded, fn, items[i], pure=False, key=f"rig-task-{i}-{stamp}",
                             priority=len(order) - rank)
               for rank, i in enumerate(order)]
    index = {f.key: i for f, i in zip(futures, order)}
    out: list[TaskResult | None] = [None] * len(items)
    done = 0
    for fut in as_completed(futures):
        i = index[fut.key]
        try:
            r = fut.result()
        except Exception as exc:  # noqa: BLE001 - the worker died (KilledWorker) or could not unpickle
            r = TaskResult(items[i], False, None, f"{type(exc).__name__}: {exc}".splitlines()[0])
        out[i] = r
        done += 1
        if progress:
            progress(done, len(items), r)
        fut.release()
    return out  # type: ignore[return-value]


@contextmanager
def mapper(jobs: int | None = None, scheduler: str | None = None, progress: Callable[[], None] | None = None):
    """A ``map(fn, items, cost=None) -> list`` for code that takes a mapper (``rig reproduce``,
    ``rig stability``), as a context manager holding one :class:`Engine` for all its calls:
    results in order; a failed task raises ``RuntimeError`` naming it (those runs have no
    per-item failure to record). ``progress()`` is called per finished task."""
    cb = (lambda d, t, r: progress()) if progress else None

    def _check(res):
        for r in res:
            if not r.ok:
                raise RuntimeError(f"task {repr(r.item)[:160]} failed: {r.error}")
        return [r.value for r in res]

    with engine(jobs, scheduler) as eng:
        yield lambda fn, items, cost=None: _check(eng.run(fn, items, progress=cb, cost=cost))


__all__ = ["TaskResult", "BatchError", "run_tasks", "dask_client", "mapper", "default_jobs", "lpt_order", "Engine", "engine",
           "shared_engine", "close_shared"]
