"""The log writer's public API the session relies on: failure(), warm_up(), close(timeout_s=...).

A real full device (/dev/full: every write fails with ENOSPC); a hung disk injected into the writer
thread's fsync (a real one needs a dead NFS server)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from rig.log import TrialLogWriter


def _block(t0: float, n: int = 100) -> dict:
    t = t0 + np.arange(n) * 1e-3
    return {"t_s": t, "position_ref_um": np.full(n, 500.0), "position_um": np.full(n, 500.1),
            "friction_N": np.full(n, 1.0), "normal_1_N": np.full(n, 100.0), "normal_2_N": np.full(n, 100.0),
            "valve_cmd": np.zeros(n)}


def test_a_healthy_writer_has_no_failure(tmp_path):
    w = TrialLogWriter(tmp_path / "ok.mcap")
    w.write_block(_block(0.0))
    assert w.failure() is None
    w.close("completed", timeout_s=5)
    assert w.failure() is None  # a finished thread is no failure


def test_close_never_hangs_on_a_write_that_hangs(tmp_path):
    """A flush that never returns (a dead disk; injected: the writer thread's fsync waits on an event
    nobody sets until the test ends): close(timeout_s) gives up with TimeoutError."""
    w = TrialLogWriter(tmp_path / "hang.mcap")
    release = threading.Event()
    sink = w._sink._sink  # the injection point: the threaded sink's file side
    try:
        # the first block registers its channels (write_block waits for the writer thread once for
        # that); the disk dies after it, so the hang is the flush's, as the docstring says (injected
        # before, the test waited the whole 60 s inside write_block)
        w.write_block(_block(0.0))
        sink._sync = lambda: release.wait(60)
        w.flush()
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match="did not"):
            w.close("completed", timeout_s=1.0)
        assert time.monotonic() - t0 < 10  # gave up (1 s asked; generous for a loaded machine)
        assert w.failure() is None  # hanging is not failing: the session's monitor times the write instead
    finally:
        release.set()


def test_warm_up_compiles_what_the_first_block_needs(tmp_path):
    w = TrialLogWriter(tmp_path / "w.mcap")
    w.warm_up()
    from rig.log import loopblock

    assert loopblock._PACK.get("quant") is not None and loopblock._PACK["quant"].signatures
    w.close(timeout_s=5)
