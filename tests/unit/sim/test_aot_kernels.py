"""The run path's kernels compiled ahead of time (rig.jitstart, numba.pycc) are numba's JIT kernels: the same
Python functions, the same numbers to the bit; a call the exported signature does not take goes to numba."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from rig import jitstart
from rig.log import TrialLogWriter, figures, kernels as log_kernels, loopblock
from rig.log.reader import read_trial
from rig.sim import plant as pl
from rig.sim.rig import SimRig


@pytest.fixture(scope="module")
def aot():
    """The built module of the current sources: built here when absent (once per change of the kernels'
    sources, as ``rig warmup`` and the first ``rig run --sim`` do; about 6 s of CPU)."""
    if not jitstart.aot_path().is_file():
        jitstart.build_aot()
    return jitstart.load_aot()


def _fn(mod, module: str, name: str):
    return getattr(mod, jitstart.aot_symbol(module, name))


def _reference(rig: SimRig, n: int) -> np.ndarray:
    """A hold, then a 20 µm/s ramp of n ticks: sticking, break-away and sliding in one short block."""
    x = np.full(n, rig.profile.stroke.home_um)
    x[n // 4:] += 20.0 * rig.dt_s * np.arange(n - n // 4)
    return x


def test_closed_loop_is_the_jit_one_to_the_bit(aot, monkeypatch):
    jit = SimRig(seed=7, friction_model="dry")
    x = _reference(jit, 3000)
    want = jit.run(x, block_ticks=700)
    monkeypatch.setattr(pl, "run_closed_loop", _fn(aot, "rig.sim.plant", "run_closed_loop"))
    monkeypatch.setattr(pl, "normal_forces", _fn(aot, "rig.sim.plant", "normal_forces"))
    got = SimRig(seed=7, friction_model="dry").run(x, block_ticks=700)
    assert set(got) == set(want)
    for k in want:
        assert np.array_equal(got[k], want[k], equal_nan=True), k
    assert np.ptp(want["friction_N"]) > 1.0  # the block exercised the friction law, not a flat line


def _write(path, blocks) -> None:
    w = TrialLogWriter(path, threaded=False, fsync=False)
    for b in blocks:
        w.write_block(b)
    w.close()


def test_log_kernels_write_the_jit_log(aot, monkeypatch, tmp_path):
    blocks = list(SimRig(seed=3).run_blocks(_reference(SimRig(seed=3), 2500), block_ticks=1000))
    _write(tmp_path / "jit.mcap", blocks)
    monkeypatch.setitem(loopblock._PACK, "quant", _fn(aot, "rig.log.loopblock", "_quant_pack_py"))
    monkeypatch.setitem(figures._JIT, "stats", _fn(aot, "rig.log.figures", "_block_stats_py"))
    monkeypatch.setattr(log_kernels, "block_means", _fn(aot, "rig.log.kernels", "block_means"))
    monkeypatch.setattr(log_kernels, "flush_means", _fn(aot, "rig.log.kernels", "flush_means"))
    _write(tmp_path / "aot.mcap", blocks)
    for channel in ("raw", "25hz"):
        a, b = read_trial(tmp_path / "jit.mcap", channel), read_trial(tmp_path / "aot.mcap", channel)
        ca, cb = {**a.columns(), **a.extra}, {**b.columns(), **b.extra}
        assert len(a) > 0 and set(ca) == set(cb), channel
        for k in ca:
            assert np.array_equal(ca[k], cb[k], equal_nan=True), (channel, k)


def test_a_call_the_signature_does_not_take_goes_to_numba(monkeypatch):
    calls = []

    def f(a, n):
        return "python"

    monkeypatch.setattr(jitstart._State, "aot",
                        {f"{f.__module__}:f": (lambda a, n: calls.append("aot") or "aot",) + jitstart._checks(("f1", "i"))})
    k = jitstart.LazyKernel(f, {})

    def jit_all():
        k._jit = lambda *a: calls.append("jit") or "jit"

    monkeypatch.setattr(jitstart, "_jit_all", jit_all)
    x = np.zeros(8)
    assert k(x, 3) == "aot"
    for args in [(x.astype(np.float32), 3), (x[::2], 3), (x.reshape(2, 4), 3), ([0.0] * 8, 3), (x,)]:
        assert k(*args) == "jit"  # float32, strided, 2-d, a list, one argument short: never the AOT function
    assert k(x, 3) == "aot"  # which stays in use for the calls it takes
    assert calls == ["aot"] + ["jit"] * 5 + ["aot"]


def test_prefer_aot_says_why_not(monkeypatch, tmp_path):
    monkeypatch.setattr(jitstart._State, "lazy", False)
    monkeypatch.setattr(jitstart._State, "aot", {})
    monkeypatch.setenv("RIG_AOT", "0")
    assert jitstart.prefer_aot() == "RIG_AOT=0"
    monkeypatch.delenv("RIG_AOT")
    assert jitstart.prefer_aot() == "numba is loaded"  # this process's kernels are numba's already
    monkeypatch.delitem(sys.modules, "numba")
    monkeypatch.setenv("RIG_AOT_DIR", str(tmp_path))
    assert jitstart.prefer_aot() == "not built yet"
    jitstart._failed_path(jitstart.aot_key()).write_text("gcc: not found")
    assert "build failed" in jitstart.prefer_aot()
    assert not jitstart._State.lazy and not jitstart.aot_in_use()


def test_one_background_build_at_a_time(monkeypatch, tmp_path):
    """Of several `rig run --sim` processes that find the kernels unbuilt, one starts the build: the lock is
    taken atomically; a build's lock older than AOT_LOCK_STALE_S (a build that died) is taken over; a
    failed start leaves no lock behind."""
    import os
    import subprocess

    monkeypatch.setenv("RIG_AOT_DIR", str(tmp_path))
    started = []

    class Build:  # the detached build: this process stands for it (alive)
        pid = os.getpid()

        def __init__(self, *a, **kw):
            started.append(a)
    monkeypatch.setattr(subprocess, "Popen", Build)
    assert jitstart.start_aot_build() and not jitstart.start_aot_build() and len(started) == 1
    lock = tmp_path / f"{jitstart._module_name(jitstart.aot_key())}.lock"
    assert lock.read_text() == str(os.getpid())
    old = lock.stat().st_mtime - jitstart.AOT_LOCK_STALE_S - 1
    os.utime(lock, (old, old))
    assert jitstart.start_aot_build() and len(started) == 2
    lock.write_text("2147483646")  # a build that was killed: no such process
    assert jitstart.start_aot_build() and len(started) == 3
    lock.unlink()

    def no_fork(*a, **kw):
        raise OSError("fork failed")
    monkeypatch.setattr(subprocess, "Popen", no_fork)
    assert not jitstart.start_aot_build() and not lock.exists()


def test_the_test_session_starts_no_background_build():
    """tests/conftest.py: the suite's `rig run --sim` processes never leave a detached build behind."""
    import os

    assert os.environ.get("RIG_AOT") == "0"


def test_warmup_waits_for_a_build_in_the_background_instead_of_building_twice(monkeypatch, tmp_path):
    """rig.jitstart.build_aot_once: while another live process holds the build's lock, it waits; when that
    build has written the module, it returns it without building; with no lock, it builds (once)."""
    import os

    monkeypatch.setenv("RIG_AOT_DIR", str(tmp_path))
    key = jitstart.aot_key()
    lock = tmp_path / f"{jitstart._module_name(key)}.lock"
    lock.write_text(str(os.getpid()))  # a live build
    built = []
    monkeypatch.setattr(jitstart, "build_aot", lambda: built.append(1) or jitstart.aot_path(key))
    sleeps = []

    def sleep(s):  # the other build finishes while this one waits
        sleeps.append(s)
        jitstart.aot_path(key).write_bytes(b"")
        lock.unlink()
    monkeypatch.setattr("time.sleep", sleep)
    assert jitstart.build_aot_once() == jitstart.aot_path(key) and built == [] and len(sleeps) == 1
    jitstart.aot_path(key).unlink()
    assert jitstart.build_aot_once() == jitstart.aot_path(key) and built == [1] and not lock.exists()
