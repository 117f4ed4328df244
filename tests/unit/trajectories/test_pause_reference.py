"""The pausable reference (trajectories.pause): a pause holds at the next safe point, the resume runs up
>= 5 L at the segment's velocity, then the plan goes on shifted by the run-up; no jump anywhere."""

from __future__ import annotations

import numpy as np

from trajectories.pause import PausableReference


def _plan():
    # 1 kHz: 1 s at 10 µm/s, then 1 s at 1 µm/s (the step at tick 1000: a safe point)
    v = np.r_[np.full(1000, 10.0), np.full(1000, 1.0)] * 1e-3
    return 500.0 + np.cumsum(v) - v[0]


def test_no_pause_is_the_plan():
    x = _plan()
    r = PausableReference(x, 1e-3, [1000], runup_um=50.0)
    y, kp = r.take(5000)
    assert np.array_equal(y, x) and np.array_equal(kp, np.arange(x.size)) and r.done and r.events == []


def test_pause_holds_at_the_safe_point_and_runs_up_before_the_plan_goes_on():
    x = _plan()
    r = PausableReference(x, 1e-3, [1000], runup_um=50.0)
    a, _ = r.take(300)
    r.request_pause()  # mid-segment: takes effect at tick 1000
    b, kb = r.take(700 + 2000)  # 2 s of hold
    assert r.paused and r.hold_s == 2.0
    assert np.all(kb[700:] == 999)  # the plan's inputs held with the reference
    r.toggle()  # resume (SIGUSR1)
    c, _ = r.take(20000)
    y = np.r_[a, b, c]
    assert np.array_equal(y[:1000], x[:1000])
    assert np.all(y[1000:3000] == x[999])  # held where the segment ended
    v = np.diff(y[3000:8000]) * 1e3
    assert np.allclose(v[:4999], 10.0)  # the run-up at the segment's 10 µm/s, 50 µm = 5000 ticks
    assert np.allclose(np.diff(y[8001:]) * 1e3, 1.0)  # then the plan's next segment, shifted by 50 µm
    assert abs(y[-1] - (x[-1] + 50.0)) < 1e-9 and np.max(np.abs(np.diff(y))) <= 0.0100001
    kinds = [e[1] for e in r.events]
    assert kinds == ["pause", "resume", "runup_done"]
    assert [e[0] for e in r.events] == [1000, 3000, 8000] and abs(r.events[0][2]["runup_v_um_s"] - 10.0) < 1e-6


def test_a_pause_that_would_leave_the_stroke_is_refused():
    x = _plan()
    r = PausableReference(x, 1e-3, [1000], runup_um=50.0, stroke_um=(0.0, x[-1] + 10.0))
    r.request_pause()
    y, _ = r.take(5000)
    assert np.array_equal(y, x) and [e[1] for e in r.events] == ["pause_refused"]


def test_a_pause_after_a_ramp_to_rest_has_no_run_up():
    # 1 s at 10 µm/s, a ramp down to rest over 0.5 s, then a hold: the hold's start (tick 1500) is the safe
    # point; the segment before ended at rest, so the resume goes straight on (its last tick's speed, a few
    # nm/s, is no velocity to run up 5 L at)
    v = np.r_[np.full(1000, 10.0), np.linspace(10.0, 0.0, 500, endpoint=False), np.zeros(1000)] * 1e-3
    x = 500.0 + np.cumsum(v) - v[0]
    r = PausableReference(x, 1e-3, [1500], runup_um=50.0)
    r.request_pause()
    y, _ = r.take(1500 + 500)
    assert r.paused
    r.toggle()
    y2, _ = r.take(5000)
    assert r.done and [e[1] for e in r.events] == ["pause", "resume", "runup_done"]
    assert r.events[0][2]["runup_um"] == 0.0 and y2.size == 1000  # the plan's 1000 ticks left, no more
    assert np.allclose(np.r_[y, y2][-1], x[-1])
