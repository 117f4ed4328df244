"""The batch engine: run independent tasks (one per file or per trial) on Dask.

One function, :func:`run_tasks`, maps a **top-level** function over a list of
plain values (paths, numbers, dicts) and returns one :class:`TaskResult` per
item, in the input order. Nothing goes through shared globals: a task gets its
inputs as arguments and returns its outputs as a value, so the same call runs

- in this process (``jobs=1``, no Dask at all: the serial reference),
- on a ``dask.distributed.LocalCluster`` of ``jobs`` worker *processes* with one
  thread each (``jobs=None``: every core of the machine), or
- on an existing cluster (``scheduler="tcp://HOST:PORT"``): the workers must have
  ``rig`` importable and see the same paths (a shared file system).

A task that raises is caught on the worker and comes back as a failed
:class:`TaskResult` (``ok=False``, ``error`` one line naming the exception); the
other tasks go on. ``progress(done, total, result)`` is called in the caller's
process as each task finishes (in completion order), so a rich progress bar can
follow the work.

Determinism: the tasks are pure functions of their arguments (seeds included),
so a run on a cluster is bit for bit the serial run (``tests/test_batch.py``).
"""

from __future__ import annotations

import os
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


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except Exception:  # noqa: BLE001 - not on a worker: the local process
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
#   one BLAS/OpenMP thread per worker is kept (N workers on N cores);
# - no statistical profiler in the workers (it samples the task's stack every 10 ms, 3-4 %
#   of a task's CPU, for a dashboard that is off).
WORKER_CONFIG = {
    "distributed.worker.daemon": False,
    "distributed.admin.tick.limit": "60s",
    "distributed.worker.memory.spill": False,
    "distributed.worker.memory.target": False,
    "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1},
    "distributed.worker.profile.enabled": False,
}


class BatchError(RuntimeError):
    """The engine could not start (bad --jobs, unreachable scheduler, Dask missing)."""


@contextmanager
def dask_client(jobs: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client``: to ``scheduler`` when given, else to a new LocalCluster of
    ``jobs`` worker processes (default: every core), one thread each; closed on exit."""
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

    with dask.config.set(WORKER_CONFIG):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=40)
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


def run_tasks(fn: Callable[[Any], Any], items: Iterable[Any], *, jobs: int | None = None,
              scheduler: str | None = None, progress: Callable[[int, int, TaskResult], None] | None = None,
              client: Any = None, cost: Callable[[Any], float] | None = None) -> list[TaskResult]:
    """Map ``fn`` (a top-level function of one plain argument) over ``items``.

    ``jobs=1`` and no ``scheduler``/``client``: serial, in this process. Otherwise on Dask
    (see the module docstring). The results are in the order of ``items``; a failed task
    is a ``TaskResult`` with ``ok=False``; ``progress`` sees each one as it finishes.

    ``cost(item)``, an estimate of a task's run time in any unit, orders the work on Dask:
    longest first (LPT), so that the batch does not end with one worker finishing a long task
    while the others are idle. It changes no result, only the order of completion.
    """
    items = list(items)
    total = len(items)
    if not items:
        return []
    if client is None and scheduler is None and (jobs == 1 or total == 1):  # serial; one task: no cluster
        out = []
        for i, it in enumerate(items):
            r = _guarded(fn, it)
            out.append(r)
            if progress:
                progress(i + 1, total, r)
        return out
    if client is not None:
        return _run_on(client, fn, items, progress, cost)
    with dask_client(jobs, scheduler) as c:
        return _run_on(c, fn, items, progress, cost)


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
    """A ``map(fn, items, cost=None) -> list`` for code that takes a mapper (``rig reproduce``, ``rig
    stability``), as a context manager holding one Dask client for all its calls (none when
    ``jobs=1``): results in order; a failed task raises ``RuntimeError`` naming it (those
    runs have no per-item failure to record). ``progress()`` is called per finished task."""
    cb = (lambda d, t, r: progress()) if progress else None

    def _check(res):
        for r in res:
            if not r.ok:
                raise RuntimeError(f"task {repr(r.item)[:160]} failed: {r.error}")
        return [r.value for r in res]

    if jobs == 1 and scheduler is None:
        yield lambda fn, items, cost=None: _check(run_tasks(fn, items, jobs=1, progress=cb))
        return
    with ExitStack() as stack:
        clients: list = []

        def _map(fn, items, cost=None):
            items = list(items)
            if len(items) <= 1 and scheduler is None and not clients:  # one task: no cluster to start
                return _check(run_tasks(fn, items, jobs=1, progress=cb))
            if not clients:  # started on first use, kept for the later calls
                clients.append(stack.enter_context(dask_client(jobs, scheduler)))
            return _check(run_tasks(fn, items, client=clients[0], progress=cb, cost=cost))

        yield _map


__all__ = ["TaskResult", "BatchError", "run_tasks", "dask_client", "mapper", "default_jobs", "lpt_order"]
