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
