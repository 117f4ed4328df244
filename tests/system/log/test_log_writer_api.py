"""The log writer's public API the session relies on: failure(), warm_up(), close(timeout_s=...).

A real full device (/dev/full: every write fails with ENOSPC); a hung disk injected into the writer
thread's fsync (a real one needs a dead NFS server)."""

from __future__ import annotations

import errno
import os
import time

import pytest

from rig.log import TrialLogWriter


def test_failure_names_the_write_error_of_a_full_disk():
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    w = TrialLogWriter("/dev/full", fsync=False)  # the header's flush already fails, in the writer thread
    t_end = time.monotonic() + 10
    while w.failure() is None and time.monotonic() < t_end:
        time.sleep(0.005)
    exc = w.failure()
    assert isinstance(exc, OSError) and exc.errno == errno.ENOSPC, exc
    with pytest.raises(RuntimeError, match="No space left"):
        w.close("failed", timeout_s=5)
