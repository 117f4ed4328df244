"""One cluster per process: the commands' engines are shared (rig.catalog.batch.shared_engine)."""

from __future__ import annotations

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
