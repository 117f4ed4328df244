"""A forked map of the diagnosis stopped early (rig.diagnosis.parallel.fork_map's ``stop``): real
helper processes, ended while they sleep."""

from __future__ import annotations

import threading
import time

import pytest

from rig.diagnosis import parallel


def _nap(s: float) -> float:
    time.sleep(s)
    return s


@pytest.mark.skipif(not parallel.can_fork(), reason="no fork here")
def test_fork_map_stopped_early_prints_no_thread_traceback(monkeypatch):
    """A map stopped at its first result with jobs still waiting: the helpers are ended, and the
    pool's own thread raises nothing (with the waiting jobs cancelled first, Python 3.11's pool set
    its error on them and printed an InvalidStateError traceback: velstep1 cropped, in `rig diagnose`)."""
    monkeypatch.setenv("RIG_JOBS", "2")
    errors = []
    monkeypatch.setattr(threading, "excepthook", lambda a: errors.append(a.exc_type.__name__))
    out = parallel.fork_map(_nap, [0.02, 1.0] + [0.3] * 12, True, stop=lambda i, r: i == 0)
    assert out == [0.02] and errors == []
