"""One cluster per process: the commands' engines are shared (rig.catalog.batch.shared_engine)."""

from __future__ import annotations

import threading

from rig.catalog import batch


def test_commands_of_one_process_share_one_engine_closed_at_exit(monkeypatch):
    monkeypatch.setattr(batch, "_SHARED", {})
    closed = []
    monkeypatch.setattr(batch.Engine, "close", lambda self: closed.append(self))
    with batch.engine(2) as first:
        pass
    assert not closed  # kept open after the first command's block
    with batch.engine(2) as second, batch.mapper(2):
        pass
    assert second is first and batch.shared_engine(2) is first
    with batch.engine(2, shared=False) as own:
        assert own is not first
    assert closed == [own]
    batch.close_shared()  # what atexit runs
    assert first in closed and not batch._SHARED


def test_an_engine_whose_cluster_failed_is_replaced(monkeypatch):
    monkeypatch.setattr(batch, "_SHARED", {})
    monkeypatch.setattr(batch.Engine, "close", lambda self: None)
    eng = batch.shared_engine(2)
    eng._error = RuntimeError("the cluster did not start")
    assert batch.shared_engine(2) is not eng
    eng = batch.shared_engine(2)

    class Closed:
        status = "closed"

    eng._client = Closed()
    assert batch.shared_engine(2) is not eng


def test_one_job_or_a_scheduler_is_never_shared(monkeypatch):
    monkeypatch.setattr(batch, "_SHARED", {})
    monkeypatch.setattr(batch.Engine, "close", lambda self: None)
    with batch.engine(1) as a, batch.engine(1) as b:
        assert a is not b and a.serial
    with batch.engine(2, "tcp://127.0.0.1:1") as c:
        assert c.scheduler and not batch._SHARED


def test_forked_workers_start_with_numbas_target_loaded(monkeypatch):
    """The forkserver imports the task's module, then the module that loads numba's CPU target, so a
    forked worker's first task does not pay it (a wrong name would be skipped silently by the server)."""
    import importlib

    import distributed
    import pytest

    seen: list[str] = []
    monkeypatch.setattr(batch, "START_METHOD", "forkserver")
    monkeypatch.setattr(batch, "_forkserver_preload", seen.extend)

    class Stop(Exception):
        pass

    def no_cluster(*a, **k):
        raise Stop

    monkeypatch.setattr(distributed, "LocalCluster", no_cluster)
    with pytest.raises(Stop), batch.dask_client(2, preload=["rig.catalog.tasks"]):
        pass
    assert seen[-1] == batch.KERNELS_PRELOAD and seen.index("rig.catalog.tasks") < len(seen) - 1
    importlib.import_module(batch.KERNELS_PRELOAD)
    from numba.core.registry import cpu_target

    assert cpu_target.target_context._registries  # loaded: what the forked workers inherit


class _ThreadPool:
    """batch._Pool's interface on threads: the engine's queue logic, in-process."""

    def __init__(self, workers, preload):
        from concurrent.futures import ThreadPoolExecutor

        self.workers, self.broken, self.preload = workers, False, preload
        self.executor = ThreadPoolExecutor(workers)

    def close(self):
        self.executor.shutdown()


def _square(x):
    return x * x


def test_this_process_and_its_workers_share_one_queue(monkeypatch):
    """Started workers and this process take tasks from one longest-first queue: every task runs once,
    the results come back in the input order, progress counts each once, and the workers are
    started with the task's module to preload."""
    monkeypatch.setattr(batch, "_Pool", _ThreadPool)
    eng = batch.Engine(3, start_cost_s=0.0)
    seen = []
    res = eng.run(_square, list(range(40)), cost=float, progress=lambda d, t, r: seen.append(d))
    assert [r.value for r in res] == [x * x for x in range(40)] and all(r.ok for r in res)
    assert sorted(seen) == list(range(1, 41))
    assert eng._pool.workers == 2 and eng._pool.preload == [__name__]
    eng.close()


def test_a_short_batch_starts_no_worker(monkeypatch):
    """The estimate: the tasks' measured CPU times per unit of cost, times the cost left; below
    PAYBACK x the start cost, every task runs here (--jobs N as fast as --jobs 1)."""
    monkeypatch.setattr(batch, "_Pool", _ThreadPool)
    eng = batch.Engine(2, start_cost_s=1e6)
    res = eng.run(_square, list(range(5)), cost=lambda x: 1.0)
    assert eng._pool is None and eng.local_tasks == 5 and [r.value for r in res] == [0, 1, 4, 9, 16]
    assert eng.estimate_s is not None and eng.estimate_s < batch.PAYBACK * eng.start_cost_s


_MAIN_TOOK_ONE = threading.Event()


def _interrupted_here(x):
    """Ctrl-C in this process on its first task after the workers started; a worker's task waits until
    then (else a fast worker thread could drain the queue before this process takes a task: a race the
    test lost under load)."""
    if threading.current_thread() is threading.main_thread():
        if x >= 3:
            _MAIN_TOOK_ONE.set()
            raise KeyboardInterrupt
    else:
        _MAIN_TOOK_ONE.wait(10.0)
    return x


def test_ctrl_c_in_this_process_stops_the_workers(monkeypatch):
    """Ctrl-C while this process computes its share: the workers are stopped, not waited for, and the
    interrupt reaches the caller."""
    import pytest

    killed = []
    monkeypatch.setattr(batch, "_Pool", _ThreadPool)
    monkeypatch.setattr(_ThreadPool, "kill", lambda self: killed.append(self), raising=False)
    _MAIN_TOOK_ONE.clear()
    eng = batch.Engine(2, start_cost_s=0.0)
    with pytest.raises(KeyboardInterrupt):
        eng.run(_interrupted_here, list(range(50)))
    assert killed == [eng._pool]
    eng.close()
