"""Where the diagnosis's independent fits run: in this process, or in forked helpers on the other
cores, within the cores an outer batch leaves it.

The diagnosis has independent work inside one record (a round's candidates, the re-splits, the
final models beside the residual's search for unexplained structure). :func:`fork_map` runs such
work on the cores this process may use: :func:`inner_workers` of them. A batch that already runs
one record per core (``rig diagnose DIR --jobs N``: this process and N - 1 workers of its own)
says so with :func:`inner_jobs`, and each record's work then stays in its own process: before,
the calling process's records forked two helpers each, and three processes shared two cores.

BLAS runs on one thread throughout (:func:`one_blas_thread`): the fits' matrices are small (a
Jacobian of a few columns, an SVD per least-squares step), and the threads of a per-core pool
only wait for one another on a machine whose other core is busy (velstep2 at load 3-5: 26 s of
CPU instead of 32 s, the same report byte for byte).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Callable, Iterator

# the helpers one record may use, set by an outer batch (inner_jobs); None: the machine's cores
_INNER_JOBS: int | None = None
MAX_WORKERS = 2  # a record's work splits well onto two processes (two cores here); RIG_JOBS=N overrides


def inner_workers(outer_processes: int | None = None, cores: int | None = None) -> int:
    """The processes one record's work may use: ``RIG_JOBS`` when set, else the cores that each of
    ``outer_processes`` (the batch's processes, this one included; default: the budget
    :func:`inner_jobs` set, or none) leaves it, at least 1, at most :data:`MAX_WORKERS`."""
    env = int(os.environ.get("RIG_JOBS", "0") or 0)
    if env > 0:
        return env
    cores = cores or os.cpu_count() or 1
    if outer_processes is None:
        if _INNER_JOBS is not None:
            return max(1, _INNER_JOBS)
        outer_processes = 1
    return max(1, min(MAX_WORKERS, cores // max(1, outer_processes)))


@contextmanager
def inner_jobs(outer_processes: int | None) -> Iterator[int]:
    """While a batch runs ``outer_processes`` records at once (this process among them; None: one
    per core), each record's own work uses :func:`inner_workers` of the cores they leave (one
    process: no forked helpers). Yields that number."""
    global _INNER_JOBS
    before = _INNER_JOBS
    n = inner_workers(outer_processes if outer_processes is not None else (os.cpu_count() or 1))
    _INNER_JOBS = n
    try:
        yield n
    finally:
        _INNER_JOBS = before


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS (numpy's, scipy's) on one thread while the diagnosis runs (this module's docstring)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


def _worker_init() -> None:
    """A forked helper's BLAS on one thread: the parent's pool of one thread per core, inherited by
    every helper, oversubscribed both cores (velstep2's two-state candidate: 9.3 s alone, 17.3 s
    beside another helper)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


def can_fork() -> bool:
    """Helpers may be forked here: the main thread of a main process (a batch's worker, with its own
    threads or as a daemon, and a helper of :func:`fork_map` run their work in-process)."""
    import multiprocessing as mp
    import threading

    return ("fork" in mp.get_all_start_methods() and threading.current_thread() is threading.main_thread()
            and mp.current_process().name == "MainProcess")


def _end_helpers(ex) -> None:
    """End the helpers of ``ex`` still computing or waiting for a job no one will read (pure fits, no
    files or locks of this process), not waited for. Their futures are left to the broken pool, which
    fails them (cancelled first, the pool's own thread raised on each: a traceback on the terminal),
    and the queue's feeder thread is not joined at exit: it may be blocked writing a job (a grid of
    megabytes) into a pipe no helper reads any more, and the process then never ended (velstep1
    trimmed, where the start's fit changes the model: the report written, the command hung)."""
    for p in list((getattr(ex, "_processes", None) or {}).values()):
        p.terminate()
    q = getattr(ex, "_call_queue", None)
    if q is not None:
        q.cancel_join_thread()


def fork_map(fn: Callable, jobs: list, parallel: bool, progress=None, what=None, stop=None) -> list:
    """``[fn(j) for j in jobs]``, in order; on :func:`inner_workers` processes when ``parallel``
    (forked helpers: they start at once with the compiled kernels, where spawn would re-import
    everything), in this process otherwise or where :func:`can_fork` says no. Jobs are handed out
    in the order given (costliest first keeps every helper busy to the end). ``progress`` is called
    in this process, ``what(job)`` its message. ``stop(i, result)``, called in this process as each
    result comes in order: True ends the map there (the jobs not yet begun are cancelled, the helpers
    still computing are ended; the list returned is shorter)."""
    n = min(len(jobs), inner_workers()) if parallel else 1
    if n > 1 and can_fork():
        import concurrent.futures as cf
        import multiprocessing as mp

        try:
            with cf.ProcessPoolExecutor(n, mp_context=mp.get_context("fork"), initializer=_worker_init) as ex:
                futures = [ex.submit(fn, j) for j in jobs]
                out = []
                for i, (j, f) in enumerate(zip(jobs, futures)):
                    out.append(f.result())
                    if progress:
                        progress(what(j))
                    if stop is not None and stop(i, out[-1]):
                        _end_helpers(ex)
                        break
                return out
        except (OSError, AssertionError, cf.process.BrokenProcessPool):
            pass  # no processes here (a daemon worker may not fork its own): in-process
    out = []
    for i, j in enumerate(jobs):
        if progress:
            progress(what(j))
        out.append(fn(j))
        if stop is not None and stop(i, out[-1]):
            break
    return out


__all__ = ["fork_map", "inner_jobs", "inner_workers", "one_blas_thread", "can_fork", "MAX_WORKERS"]
