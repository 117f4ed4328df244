"""End to end through the CLI: `rig run --hardware` on the emulated rig vs `--sim`,
operator abort, kill -9 of the loop and of the logger (then `rig recover`)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

from rig.log import read_trial

SMOKE = REPO / "config/recipes/smoke.yaml"
pytestmark = pytest.mark.slow


def _rig(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "rig.cli", *map(str, args)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def _wait_for_ticks(path: Path, proc, t_min_s: float, find_child, timeout_s: float = 30.0):
    """Wait until the loop has been running for ``t_min_s`` (the log is flushed every second)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            raise AssertionError(f"rig exited early ({proc.returncode}):\n{proc.stdout.read()}")
        if find_child(proc.pid, "rig-rt-loop") and path.exists() and path.stat().st_size > 20000:
            time.sleep(t_min_s)
            return
        time.sleep(0.05)
    raise AssertionError("the loop did not start")


def test_smoke_hardware_matches_sim(tmp_path, private_profile):
    """The reference time is held across the stalls a loaded machine causes, so the hardware's trial
    time, reference and lock-stepped plant stay in step with the simulation's (no gaps, no jumps)."""
    prof = private_profile(tmp_path)
    hw_out, sim_out = tmp_path / "hw.mcap", tmp_path / "sim.mcap"
    p = _rig("run", SMOKE, "--hardware", prof, "--out", hw_out, "-q")
    out = p.communicate(timeout=90)[0]
    assert p.returncode == 0, out
    assert "loop timing (whole trial)" in out and "lateness" in out
    q = _rig("run", SMOKE, "--sim", "--profile", prof, "--out", sim_out, "-q")
    assert q.wait(60) == 0, q.stdout.read()
    a = read_trial(hw_out, channel="25hz")
    b = read_trial(sim_out, channel="25hz")
    assert a.time_s[-1] == pytest.approx(b.time_s[-1], abs=0.5)
    t = b.time_s
    dx = np.interp(t, a.time_s, a.position_um) - b.position_um
    fa = np.interp(t, a.time_s, a.friction_N)
    df = fa - b.friction_N
    # sensor noise: LVDT 0.125 µm, friction 0.125 N (1 sigma); seeds differ between the two
    assert np.sqrt(np.mean(dx ** 2)) < 1.0, np.sqrt(np.mean(dx ** 2))
    assert np.sqrt(np.mean(df ** 2)) < 1.0, np.sqrt(np.mean(df ** 2))
    for lo, hi in ((2, 5), (5, 8), (12, 16)):  # run-in pull, push, the faster level
        m = (t > lo) & (t < hi)
        assert fa[m].mean() == pytest.approx(b.friction_N[m].mean(), abs=0.3)
    kinds = {e["kind"] for e in a.events}
    assert {"trial_start", "loop_start", "realtime"} <= kinds
    raw = read_trial(hw_out, channel="raw")
    assert np.allclose(np.diff(raw.time_s), 1e-3, atol=1e-9)  # no gaps: the reference time was held
    assert np.max(np.abs(np.diff(raw.position_ref_um))) < 0.1  # and the reference never jumped


def test_operator_abort_controlled_stop(tmp_path, private_profile, find_child):
    prof = private_profile(tmp_path)
    out = tmp_path / "abort.mcap"
    p = _rig("run", SMOKE, "--hardware", prof, "--out", out, "-q", start_new_session=True)
    _wait_for_ticks(out, p, 1.5, find_child)
    os.killpg(p.pid, signal.SIGINT)  # Ctrl-C at a terminal: the whole process group
    text = p.communicate(timeout=30)[0]
    assert p.returncode == 130, text
    tr = read_trial(out, channel="raw")  # finished MCAP: readable without recovery
    kinds = [e["kind"] for e in tr.events]
    assert "abort" in kinds and "interrupted" in kinds
    assert tr.time_s[-1] > 1.5
    assert tr.valve_cmd[-1] == 0.0  # ended nulled
    ab = next(e for e in tr.events if e["kind"] == "abort")
    held = tr.time_s > ab["t_s"]
    assert np.all(tr.position_ref_um[held] == pytest.approx(ab["hold_um"]))  # position held


def test_kill9_loop_keeps_log(tmp_path, private_profile, find_child):
    prof = private_profile(tmp_path)
    out = tmp_path / "kill-loop.mcap"
    p = _rig("run", SMOKE, "--hardware", prof, "--out", out, "-q")
    _wait_for_ticks(out, p, 2.0, find_child)
    loop_pid = find_child(p.pid, "rig-rt-loop")
    t_kill = time.monotonic()
    os.kill(loop_pid, signal.SIGKILL)
    text = p.communicate(timeout=30)[0]
    assert p.returncode == 1, text
    assert "loop process died" in text
    tr = read_trial(out, channel="raw")
    assert any(e["kind"] == "loop_died" for e in tr.events)
    assert tr.time_s[-1] > 1.5
    del t_kill


def test_kill9_logger_then_recover(tmp_path, private_profile, find_child):
    from drivers.config import hardware_of_profile
    from rig.hardware.emulated import start_emulator_process
    from rig.config.profile import load_profile

    prof = private_profile(tmp_path, autostart=False)
    profile = load_profile(prof)
    emu = start_emulator_process(hardware_of_profile(profile), profile, lubricant="boundary", private=False)
    try:
        out = tmp_path / "kill-logger.mcap"
        p = _rig("run", SMOKE, "--hardware", prof, "--out", out, "-q")
        _wait_for_ticks(out, p, 2.5, find_child)
        t_run = None
        st = emu.stats()
        assert st["valve_enabled"]
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
        # the orphaned loop gets SIGTERM (PR_SET_PDEATHSIG): controlled stop, valve nulled
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            st = emu.stats()
            if not st["valve_enabled"] and st["valve_output"] == 0.0:
                break
            time.sleep(0.05)
        assert not st["valve_enabled"] and st["valve_output"] == 0.0, st
        rec = tmp_path / "recovered.mcap"
        r = _rig("recover", out, "--out", rec)
        assert r.wait(60) == 0, r.stdout.read()
        tr = read_trial(rec, channel="raw")
        assert tr.time_s[-1] > 1.5  # at most the last second lost
        del t_run
    finally:
        emu.stop()
