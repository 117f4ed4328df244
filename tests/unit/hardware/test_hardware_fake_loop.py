"""Each trip of the real-time loop, deterministic: the loop object (rig.hardware.loop.RtLoop) over the
in-process fake rig (rig.hardware.fake: values and DeviceHealth set directly) on a simulated clock. No
emulator, no real time: every test runs a few hundred ticks in milliseconds."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import rig
from drivers.config import hardware_of_profile
from drivers.errors import DeviceError
from rig.config.profile import load_profile
from rig.hardware.fake import FakeClock, ListQueue, fake_rig
from rig.hardware.interlocks import ABORT_FAIL, ABORT_OPERATOR
from rig.hardware.loop import RtLoop
from rig.hardware.safety import latch_path


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

PROFILE = load_profile(REPO / "config/rigs/emulated.yaml")
HW = hardware_of_profile(PROFILE)
HOLD_TICKS = round(HW.interlocks.stop_hold_s / 1e-3)


def run(n_ticks=400, at=100, act=None, x_ref=None, ack=None, abort=None, hw=HW, safety=False):
    """Run the loop over the fake rig; ``act(loop, rig, clock)`` once before tick ``at``."""
    rig, clock, q = fake_rig(500.0, safety), FakeClock(), ListQueue()
    x = np.full(n_ticks, 500.0) if x_ref is None else np.asarray(x_ref, float)
    flag = abort or SimpleNamespace(value=0)
    loop = RtLoop(hw, PROFILE, x, q, flag, {"why": None}, {"period_s": 1e-3}, logger_ack=ack, devices=rig,
                  clock=clock)
    assert loop.connect()
    loop.start()
    while True:
        if act is not None and loop.kr == at:
            act(loop, rig, clock)
            act = None
        if not loop.tick():
            break
    loop.finish()
    events = [m for m in q.items if m[0] == "event"]
    trips = [m[3] for m in events if m[2] == "interlock"]
    done = next(m[1] for m in q.items if m[0] == "done")
    rows = np.concatenate([m[1]["valve_cmd"] for m in q.items if m[0] == "block"])
    return SimpleNamespace(loop=loop, rig=rig, trips=trips, done=done, events=events, valve_cmd=rows)


def _safe_after_trip(r, name, extra_ticks, judged_after_write=False):
    """The trip tick's write is nulled and disabled (the next one's for a check made after the write,
    e.g. the skipped cycles counted when the tick ends), and every one after it."""
    assert r.trips and r.trips[0]["name"] == name, r.trips
    t_trip = r.trips[0]["t_s"]
    k = round(t_trip * 1000) + judged_after_write
    writes = r.rig.valve.writes
    # the trip tick's own write is already nulled and disabled, and so is every write after it
    assert all(w == (0.0, False) for w in writes[k:]), writes[k - 2:k + 3]
    assert writes[k - 1][1] is True  # it was enabled before
    assert r.rig.valve.stopped and r.done["status"] == "tripped" and r.done["valve_final"]["confirmed"]
    assert r.done["ticks"] == k + extra_ticks
    assert r.valve_cmd[k:].tolist() == [0.0] * (len(r.valve_cmd) - k)


def test_a_clean_run_ends_at_the_plan_and_safe():
    r = run(300)
    assert r.trips == [] and r.done["status"] == "completed" and r.done["ticks"] == 300
    assert r.rig.valve.writes[-1] == (0.0, False) and r.rig.valve.started
    assert r.done["wall_ns_tick0"] > 1.6e18  # tick 0's wall clock is handed on


@pytest.mark.parametrize("name,act,extra", [
    ("stroke_limit", lambda lp, rig, c: setattr(rig.position, "position_um", 5000.5), HOLD_TICKS),
    ("friction_limit", lambda lp, rig, c: setattr(rig.forces, "forces_N", (151.0, 100.0, 100.0)), HOLD_TICKS),
    ("normal_force_band", lambda lp, rig, c: setattr(rig.forces, "forces_N", (0.0, 40.0, 100.0)), HOLD_TICKS),
    ("following_error", lambda lp, rig, c: setattr(rig.position, "position_um", 560.0), HOLD_TICKS),
    ("non_finite", lambda lp, rig, c: setattr(rig.forces, "forces_N", (float("nan"), 100.0, 100.0)), 1),
    ("loadcell_fault", lambda lp, rig, c: setattr(rig.forces.health_, "fault", True), HOLD_TICKS),
    ("valve_dither", lambda lp, rig, c: rig.valve.health_.problems.append(("valve_dither", "no dither")),
     HOLD_TICKS),
    ("device_lost", lambda lp, rig, c: setattr(rig.position, "fail_read", DeviceError("LVDT", "x", "gone",
                                                                                      kind="lost")), 1),
    ("loop_stall", lambda lp, rig, c: c.stall(0.3), 1),
])
def test_each_trip_ends_nulled_and_disabled(name, act, extra):
    _safe_after_trip(run(act=act), name, extra)


def test_stale_data_needs_age_and_ticks():
    def act(lp, rig, c):
        rig.position.health_.age_s = 1.0
        rig.position.health_.polls_since_new = 10_000
    _safe_after_trip(run(act=act), "stale_position", 1)


def test_modbus_errors_trip_at_their_consecutive_limit():
    def act(lp, rig, c):
        rig.forces.fail_read = DeviceError("load-cell conditioner", "x", "timeout")
    r = run(act=act)
    _safe_after_trip(r, "modbus_errors", 1)
    assert round(r.trips[0]["t_s"] * 1000) == 100 + HW.interlocks.max_modbus_errors - 1


def test_a_short_stall_is_an_event_and_the_reference_is_held():
    r = run(act=lambda lp, rig, c: c.stall(0.1))
    assert r.trips == [] and r.done["status"] == "completed"
    stalls = [m[3] for m in r.events if m[2] == "stall"]
    assert len(stalls) == 1 and stalls[0]["gap_s"] == pytest.approx(0.1, abs=1e-3)
    assert stalls[0]["skipped"] == r.done["skipped"] == pytest.approx(100, abs=1)  # attributed to the stall
    assert r.done["ticks"] == 400  # every reference tick executed: the reference was held, not jumped


def test_skipped_cycles_trip():
    def act(lp, rig, c):
        lp.timing.trip_s = 10.0  # not a stall trip: the skips are what trips
        c.stall(0.22)
    _safe_after_trip(run(act=act), "skipped_cycles", 1, judged_after_write=True)


def test_logger_stalled_and_session_failure():
    ack = SimpleNamespace(value=0)  # the logger never takes a block
    r = run(n_ticks=2000, ack=ack)
    assert r.trips[0]["name"] == "logger_stalled"
    flag = SimpleNamespace(value=0)
    _safe_after_trip(run(act=lambda lp, rig, c: setattr(flag, "value", ABORT_FAIL), abort=flag), "logger_failed", 1)


def test_operator_abort_holds_then_goes_safe():
    flag = SimpleNamespace(value=0)
    x = np.linspace(500.0, 520.0, 400)
    r = run(act=lambda lp, rig, c: setattr(flag, "value", ABORT_OPERATOR), abort=flag, x_ref=x)
    assert r.trips == [] and r.done["status"] == "aborted"
    assert [m[2] for m in r.events if m[2] == "abort"] == ["abort"]
    writes = r.rig.valve.writes
    assert all(w[1] for w in writes[100:100 + HOLD_TICKS])  # held under control ...
    assert writes[100 + HOLD_TICKS] == (0.0, False)       # ... then nulled and disabled


@pytest.mark.parametrize("name", ["estop", "hydraulic_pressure"])
def test_the_safety_chain_trips_within_the_tick_and_latches(tmp_path, name):
    hw = HW.model_copy(update={"safety": HW.safety.model_copy(update={"latch_dir": str(tmp_path)})})
    r = run(act=lambda lp, rig, c: rig.safety.health_.problems.append((name, "pressed")), hw=hw, safety=True)
    _safe_after_trip(r, name, HOLD_TICKS)
    k = round(r.trips[0]["t_s"] * 1000)
    assert r.rig.safety.writes[k - 1] is True and not any(r.rig.safety.writes[k:])  # the amplifier's enable too
    assert latch_path(hw.safety).exists() and r.done["safety_final"]["enable_output_off"]
    # latched: the next run does not start, naming the chain
    q = ListQueue()
    loop = RtLoop(hw, PROFILE, np.full(10, 500.0), q, SimpleNamespace(value=0), {"why": None}, {}, devices=fake_rig(
        500.0, True), clock=FakeClock())
    assert not loop.connect()
    assert "safety chain" in q.items[-1][1]["message"] and name in q.items[-1][1]["message"]


def test_a_pause_holds_at_the_safe_point_resumes_with_a_run_up_and_times_out():
    x = 500.0 + np.arange(3000) * 0.01  # 10 µm/s; safe point at tick 1000
    pause = SimpleNamespace(value=0)
    rig, clock, q = fake_rig(500.0), FakeClock(), ListQueue()
    loop = RtLoop(HW, PROFILE, x, q, SimpleNamespace(value=0), {"why": None},
                  {"period_s": 1e-3, "safe_ticks": [1000], "runup_um": 20.0}, devices=rig, clock=clock,
                  pause_req=pause)
    assert loop.connect()
    loop.start()
    refs = []
    while True:
        if loop.kr == 500:
            pause.value = 1
        if loop.kr == 1500:
            pause.value = 0
        rig.position.position_um = loop.xr  # a perfect actuator
        if not loop.tick():
            break
        refs.append(loop.xr)
    loop.finish()
    kinds = [(m[2], round(m[1] * 1000)) for m in q.items if m[0] == "event" and m[2] in ("pause", "resume", "runup_done")]
    assert kinds == [("pause", 1000), ("resume", 1500), ("runup_done", 3500)]
    refs = np.array(refs)
    assert np.all(refs[1000:1500] == x[999]) and np.allclose(np.diff(refs[1500:3500]), 0.01)
    done = next(m[1] for m in q.items if m[0] == "done")
    assert done["status"] == "completed" and done["ticks"] == 3000 + 500 + 2000
    # a pause held longer than max_pause_s trips to the safe state
    hw = HW.model_copy(update={"interlocks": HW.interlocks.model_copy(update={"max_pause_s": 0.2})})
    rig, q = fake_rig(500.0), ListQueue()
    loop = RtLoop(hw, PROFILE, x, q, SimpleNamespace(value=0), {"why": None},
                  {"period_s": 1e-3, "safe_ticks": [1000], "runup_um": 20.0}, devices=rig, clock=FakeClock(),
                  pause_req=SimpleNamespace(value=1))
    assert loop.connect()
    loop.start()
    while loop.tick():
        rig.position.position_um = loop.xr
    loop.finish()
    trips = [m[3] for m in q.items if m[0] == "event" and m[2] == "interlock"]
    assert trips[0]["name"] == "pause_timeout" and round(trips[0]["t_s"] * 1000) == 1000 + 200
    assert rig.valve.writes[-1] == (0.0, False)


def test_a_valve_that_does_not_enable_trips_before_the_first_tick():
    rig, q = fake_rig(500.0), ListQueue()

    def refuse():
        raise DeviceError("servovalve controller", "fake-can:0 node 1", "did not enable within 1 s")

    rig.valve.start = refuse
    loop = RtLoop(HW, PROFILE, np.full(100, 500.0), q, SimpleNamespace(value=0), {"why": None}, {}, devices=rig,
                  clock=FakeClock())
    assert loop.connect()
    loop.start()
    while loop.tick():
        pass
    loop.finish()
    done = q.items[-1][1]
    assert done["trip"]["name"] == "valve_enable" and done["ticks"] == 0 and rig.valve.writes[-1] == (0.0, False)
