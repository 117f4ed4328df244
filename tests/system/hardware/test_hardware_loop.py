"""The trial session on the hardware backend against the emulated rig: a clean run, and
interlock trips that end in the safe state (valve nulled and disabled, seen from the valve
emulator), with the session's stop state machine reaching SAFE then DONE."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from drivers.config import hardware_of_profile
from rig.hardware.emulated import start_emulator_process
from rig.hardware.loop import BLOCK_KEYS
from rig.config.profile import load_profile
from rig.session import Phase, run_trial
from rig.session.hardware import HardwareBackend


class MemWriter:
    def __init__(self, at_t_s=None, action=None):
        self.blocks, self.events, self.stats = [], [], []
        self.ticks = 0
        self.at_t_s, self.action = at_t_s, action  # run action() once the loop reaches at_t_s

    def schedule_events(self, events):
        pass

    def write_block(self, block):
        self.blocks.append(block)
        self.ticks += len(block["t_s"])
        if self.action is not None and block["t_s"][-1] >= self.at_t_s:
            act, self.action = self.action, None
            act()

    def event(self, t_s, kind, **data):
        self.events.append({"t_s": t_s, "kind": kind, **data})

    def loop_stats(self, t_s, stats):
        self.stats.append((t_s, stats))

    def warm_up(self):
        pass

    def failure(self):
        return None

    def close(self, status, timeout_s=None, **summary):
        self.status = status

    def col(self, key):
        return np.concatenate([b[key] for b in self.blocks])


@pytest.fixture(scope="module")
def rig_env(tmp_path_factory, private_profile):
    tmp = tmp_path_factory.mktemp("hwloop")
    path = private_profile(tmp, autostart=False, interlocks={"stroke_max_um": 530.0, "stale_s": 0.05})
    profile = load_profile(path)
    hw = hardware_of_profile(profile)
    h = start_emulator_process(hw, profile, lubricant="boundary", normal_force_N=100.0, seed=2)
    yield SimpleNamespace(profile=profile, hw=hw, emu=h)
    h.stop()


def _plan(x):
    x = np.asarray(x, dtype=float)
    return SimpleNamespace(x_ref_um=x, loop_rate_hz=1000.0, duration_s=(x.size - 1) / 1000.0, n_ticks=x.size,
                           events=[])


def _run(rig_env, x, w):
    return run_trial(_plan(x), HardwareBackend(rig_env.hw, rig_env.profile, emulator=rig_env.emu), w,
                     handle_signals=False)


def _clear(emu):
    for dev, fault in (("valve", "fault"), ("valve", "silent"), ("loadcells", "exception"), ("loadcells", "slow_s"),
                       ("loadcells", "silent"), ("lvdt", "silent"), ("lvdt", "corrupt_every"),
                       ("lvdt", "drop_every"), ("lvdt", "garbage_every"), ("loadcells", "nan_friction"),
                       ("valve", "ignore_setpoints"), ("valve", "stuck")):
        emu.inject(dev, fault, None)


def _safe_state(emu, timeout_s=1.0):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = emu.stats()
        if not st["valve_enabled"] and st["valve_output"] == 0.0:
            return st
        time.sleep(0.02)
    raise AssertionError(f"valve not in the safe state: {st}")


def test_clean_run_blocks_stats_and_tracking(rig_env):
    _clear(rig_env.emu)
    n = 1500
    t = np.arange(n) / 1000.0
    x = 500.0 + np.clip(t - 0.3, 0, None) * 10.0  # hold, then 10 µm/s
    w = MemWriter()
    res = _run(rig_env, x, w)
    s = res.summary
    assert res.status == "completed" and w.status == "completed" and s["status"] == "completed", res.reason
    assert [h[0] for h in res.history] == [Phase.RUNNING, Phase.STOPPING, Phase.SAFE, Phase.DONE]
    assert set(s["devices"]) == {"lvdt", "loadcells", "valve", "safety"} and s["devices"]["lvdt"]["frames_ok"] > 1000
    assert set(BLOCK_KEYS) <= set(w.blocks[0])
    ts = w.col("t_s")
    assert np.all(np.diff(ts) > 0) and ts[-1] == pytest.approx(1.499)
    assert w.ticks + s["timing"]["skipped"] >= n - 1
    err = w.col("position_ref_um") - w.col("position_um")
    assert np.sqrt(np.mean(err[500:] ** 2)) < 15.0  # follows the ramp (the sim tracks likewise)
    assert np.all(np.isfinite(w.col("friction_N")))
    assert w.stats and "late_p99_us" in w.stats[0][1]  # a statistics message every second
    assert s["timing"]["n"] == w.ticks
    assert any(e["kind"] == "realtime" for e in w.events)
    _safe_state(rig_env.emu)  # a completed trial also ends nulled and disabled


@pytest.mark.parametrize("switches", [{"ff1": False, "friction_ff": True}, {"ff1": True, "friction_ff": False}])
def test_recipe_controller_switches_reach_the_hardware_loop(rig_env, switches):
    """The recipe's ``controller: {ff1, friction_ff}`` switches act on the real loop as on the
    simulated rig: the valve command less the logged P, I, D and dither terms is FF1 x v_ref
    (0 with ff1 off) plus the friction feed-forward of the profile's boundary law along the
    reference (rig.model.feedforward; empty with friction_ff off)."""
    from rig.model.feedforward import friction_feedforward_for_plan, initial_velocity_um_s

    _clear(rig_env.emu)
    n = 1500
    t = np.arange(n) / 1000.0
    x = 500.0 + np.clip(t - 0.3, 0, None) * 10.0
    plan = _plan(x)
    plan.controller = switches
    w = MemWriter()
    res = run_trial(plan, HardwareBackend(rig_env.hw, rig_env.profile, emulator=rig_env.emu, lubricant="boundary",
                                          normal_force_N=100.0), w, handle_signals=False)
    assert res.status == "completed", res.reason
    c = rig_env.profile.controller
    fs = rig_env.profile.actuator.full_scale_force_N
    out = w.col("valve_cmd") * fs - (w.col("pid_p") + w.col("pid_i") + w.col("pid_d") + w.col("dither"))
    k = np.rint(w.col("t_s") * 1000.0).astype(int)
    ok = np.abs(w.col("valve_cmd")) < 0.99  # not clipped at full scale
    v_ref = np.gradient(x) * 1000.0
    ff = friction_feedforward_for_plan(switches, x, 1e-3, rig_env.profile.friction_model("boundary"), 200.0,
                                       initial_velocity_um_s(x, 1000.0, rig_env.profile.sim.initial_creep_um_s))
    expect = (c.ff1_N_s_per_um * v_ref[k] if switches["ff1"] else 0.0) + (ff[k] if ff.size else 0.0)
    moving = ok & (k > 400) & (k < n - 2)
    if switches["friction_ff"]:
        assert np.max(np.abs(ff[k][moving])) > 0.05  # the law's force along the ramp is there to be seen
    if switches["ff1"]:
        assert c.ff1_N_s_per_um * 10.0 > 0.05
    assert np.allclose(out[moving], expect[moving], atol=0.02 + 1e-3 * fs / 16384), \
        np.max(np.abs(out[moving] - expect[moving]))


def _run_with_fault(rig_env, x, inject, after_s=0.3, confirmed_safe=True):
    _clear(rig_env.emu)
    w = MemWriter(after_s, (lambda: inject(rig_env.emu)) if inject else None)
    res = _run(rig_env, x, w)
    assert res.status == "failed" and res.cause == "trip" and w.status == "failed", res
    # SAFE only when the valve confirms it (a silent valve cannot: STOPPING -> DONE)
    assert res.safe == confirmed_safe and (res.history[-2][0] is Phase.SAFE) == confirmed_safe
    st = _safe_state(rig_env.emu)
    trips = [e for e in w.events if e["kind"] == "interlock"]
    assert len(trips) == 1 and trips[0]["message"], (w.events, res.summary)
    assert w.col("valve_cmd")[-1] == 0.0  # the last logged ticks are nulled
    assert any(e["kind"] == "trial_failed" for e in w.events)
    _clear(rig_env.emu)
    return res, trips[0], w, st


@pytest.mark.parametrize("dev,fault,value,expect", [
    ("valve", "fault", True, "valve_fault"),
    ("valve", "silent", True, "valve_heartbeat"),
    ("lvdt", "silent", True, "stale_position"),
    ("lvdt", "corrupt_every", 2, "serial_checksum_errors"),
    ("loadcells", "exception", True, "modbus_errors"),
    ("loadcells", "slow_s", 0.01, "modbus_errors|frame_loss"),  # slower than the 2 ms timeout
    ("loadcells", "slow_s", 0.0015, "frame_loss"),  # answers within the timeout, but every other tick
    ("lvdt", "drop_every", 2, "frame_loss"),
    ("lvdt", "garbage_every", 2, "stream_garbage"),
    ("loadcells", "nan_friction", True, "non_finite"),
])
def test_device_fault_trips_to_safe_state(rig_env, dev, fault, value, expect):
    x = np.full(3000, 500.0)
    res, trip, w, _ = _run_with_fault(rig_env, x, lambda emu: emu.inject(dev, fault, value),
                                      confirmed_safe=(dev, fault) != ("valve", "silent"))
    assert res.summary["trip"]["name"] == trip["name"] and trip["name"] in expect.split("|")
    assert trip["t_s"] > 0.2 and trip["message"] in res.reason


def test_stroke_limit_trips_and_holds(rig_env):
    # profile limit here: stroke_max_um 530; the reference runs on to 560 µm at 50 µm/s
    t = np.arange(2000) / 1000.0
    x = 500.0 + 50.0 * np.clip(t - 0.1, 0, None) * (t < 1.5) + 50.0 * 1.4 * (t >= 1.5)
    res, trip, w, st = _run_with_fault(rig_env, x, None)
    assert res.summary["trip"]["name"] == "stroke_limit"
    assert trip["values"]["position_um"] > 530.0 and trip["name"] == "stroke_limit"
    pos = w.col("position_um")
    assert pos.max() < 545.0  # stopped within a few hundred ms of travel


def test_a_hung_log_writer_trips_logger_stalled(rig_env):
    """The writer blocks (a dead disk): the loop stops taking the session's word for it after
    logger_timeout_s (1 s) of unacknowledged blocks and goes to the safe state by itself."""
    _clear(rig_env.emu)
    w = MemWriter(0.3, lambda: time.sleep(1.6))
    res = _run(rig_env, np.full(4000, 500.0), w)
    assert res.status == "failed" and res.summary["trip"]["name"] == "logger_stalled", res.reason
    _safe_state(rig_env.emu)


def test_a_failed_log_writer_stops_the_loop_at_once(rig_env):
    """The writer reports a failure (its thread hit a full disk): the session's monitor sets the fail
    flag and the loop goes to the safe state without the operator-abort hold."""
    _clear(rig_env.emu)
    w = MemWriter()
    w.failure = lambda: OSError(28, "No space left on device") if w.ticks >= 500 else None
    res = _run(rig_env, np.full(4000, 500.0), w)
    assert res.status == "failed" and res.summary["trip"]["name"] == "logger_failed", res.reason
    assert w.ticks < 1500  # stopped soon after, not at the end of the plan
    assert not any(e["kind"] == "abort" for e in w.events)  # no hold
    _safe_state(rig_env.emu)


def test_port_vanishes_mid_run_trips_device_lost(rig_env):
    # last test of the module: the emulator's LVDT is gone afterwards
    x = np.full(3000, 500.0)
    res, trip, w, _ = _run_with_fault(rig_env, x, lambda emu: emu.inject("lvdt", "vanish", True))
    assert res.summary["trip"]["name"] == "device_lost"
    assert "LVDT conditioner at serial:" in trip["message"]
    assert trip["values"]["address"].startswith("serial:")
