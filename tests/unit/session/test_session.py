"""The trial session over its Backend protocol: the stop state machine, statistics every
second, failures and aborts from any backend, and `simulate` (the analysis' way to run a
recipe on the simulated rig)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rig.config.profile import load_profile
from rig.config.recipe import load_recipe
from rig.session import (
    Anchored, Backend, Block, Ending, Event, FailStoppable, LoggerWatched, MemoryLog, Outcome, Pausable, Phase, StopMachine,
    TrialWriter, run_trial,
)
from rig.session.sim import SimBackend, simulate
from rig.config.recipe import compile_recipe


def test_stop_machine_order_and_first_reason_wins():
    sm = StopMachine()
    assert sm.request(Outcome.STOPPED, "operator abort (SIGINT)")
    assert not sm.request(Outcome.TRIPPED, "later")  # counted, the first reason stays
    assert sm.requests == 2 and sm.reason == "operator abort (SIGINT)" and sm.status == "interrupted"
    assert sm.cause == "operator"
    with pytest.raises(RuntimeError, match="stopping -> stopping|not allowed"):
        sm._go(Phase.STOPPING)
    sm.safe()
    with pytest.raises(RuntimeError, match="safe -> running"):
        sm._go(Phase.RUNNING)
    sm.done()
    assert [h[0] for h in sm.history] == [Phase.RUNNING, Phase.STOPPING, Phase.SAFE, Phase.DONE]
    with pytest.raises(RuntimeError):
        StopMachine().safe()  # SAFE only after STOPPING


def test_one_outcome_gives_the_logged_strings():
    """The log's status and cause and trial_failed's status are one Outcome's strings (they must
    not change: the MCAP metadata and the CLI's JSON show them)."""
    table = {o: (o.value, o.status, o.cause) for o in Outcome}
    assert table == {Outcome.COMPLETED: ("completed", "completed", "end_of_plan"),
                     Outcome.STOPPED: ("stopped", "interrupted", "operator"),
                     Outcome.TRIPPED: ("tripped", "failed", "trip"),
                     Outcome.FAILED: ("failed", "failed", "failure")}
    assert Ending("tripped").outcome is Outcome.TRIPPED
    with pytest.raises(ValueError):
        Ending("aborted")  # not an outcome


def test_stop_machine_is_overruled_only_by_a_trip_or_a_failure():
    sm = StopMachine()
    with pytest.raises(RuntimeError, match="nothing to overrule"):
        sm.overrule(Outcome.FAILED, "too early")
    sm.request(Outcome.STOPPED, "operator abort (SIGTERM)")
    with pytest.raises(ValueError, match="only a trip or a failure"):
        sm.overrule(Outcome.COMPLETED, "no")
    sm.overrule(Outcome.TRIPPED, "INTERLOCK stroke_limit")
    assert (sm.status, sm.cause, sm.reason) == ("failed", "trip", "INTERLOCK stroke_limit")
    sm.safe()
    sm.done()
    with pytest.raises(RuntimeError, match="nothing to overrule"):
        sm.overrule(Outcome.FAILED, "after the end")


def test_writers_and_backends_satisfy_their_protocols(tmp_path):
    """The writer contract is a Protocol: the MCAP writer and the memory log both satisfy it, and
    the backends' capabilities are the small protocols the session asks with isinstance."""
    from rig.log import TrialLogWriter
    from rig.session.hardware import HardwareBackend
    from rig.session.sim import SimBackend

    assert isinstance(MemoryLog(), TrialWriter) and not isinstance(MemoryLog(), Anchored)
    w = TrialLogWriter(tmp_path / "t.mcap", threaded=False, fsync=False)
    try:
        assert isinstance(w, TrialWriter) and isinstance(w, Anchored)
    finally:
        w.close("completed")
    assert not isinstance(object(), TrialWriter)
    for cls in (SimBackend, HardwareBackend):
        assert all(hasattr(cls, m) for m in ("describe", "start", "receive", "request_stop", "stats_window",
                                             "finish", "close"))
    # capabilities, read off the classes' members (an instance needs a rig or devices)
    assert {"pause", "resume"} <= set(dir(SimBackend)) and {"pause", "resume"} <= set(dir(HardwareBackend))
    assert {"block_logged", "heartbeat", "heartbeat_priority", "fail_stop"} <= set(dir(HardwareBackend))
    assert not isinstance(ScriptedBackend(1), (Pausable, LoggerWatched, FailStoppable))
    assert isinstance(ScriptedBackend(1), Backend)


class ScriptedBackend:
    """A backend that plays ``n_blocks`` blocks of a 1 kHz hold, then ends as told."""

    name = "scripted"

    def __init__(self, n_blocks, ending=None, fail_at=None, stop_after_request=0, safe=True):
        self.n, self.i = n_blocks, 0
        self.ending, self.fail_at, self.safe = ending, fail_at, safe
        self.stop_after_request = stop_after_request  # blocks still sent after a stop request
        self.stop_reason = None
        self.closed = False
        self.insisted = False

    def describe(self):
        return {"scripted": True}

    def start(self, plan):
        pass

    def receive(self):
        if self.stop_reason is not None:
            if self.stop_after_request <= 0:
                return None
            self.stop_after_request -= 1
        if self.i >= self.n:
            return None
        if self.fail_at is not None and self.i == self.fail_at:
            raise OSError("link down")
        t = (self.i * 100 + np.arange(100)) / 1000.0
        self.i += 1
        return Block({"t_s": t, "position_ref_um": np.full(100, 500.0), "position_um": np.full(100, 499.0),
                      "friction_N": np.full(100, 20.0), "normal_1_N": np.full(100, 100.0),
                      "normal_2_N": np.full(100, 100.0), "valve_cmd": np.zeros(100)})

    def request_stop(self, reason, insist=False):
        self.stop_reason = reason
        self.insisted |= insist

    def stats_window(self):
        return {"scripted_window": 1.0}

    def finish(self):
        if self.ending is not None:
            return self.ending
        return Ending("stopped" if self.stop_reason else "completed", self.stop_reason or "", safe=self.safe)

    def close(self):
        self.closed = True


def _plan(n_ticks, events=()):
    return SimpleNamespace(x_ref_um=np.full(n_ticks, 500.0), loop_rate_hz=1000.0, n_ticks=n_ticks,
                           duration_s=(n_ticks - 1) / 1000.0, events=list(events))


def test_completed_run_logs_blocks_events_and_stats_every_second():
    log = MemoryLog()
    be = ScriptedBackend(35)
    res = run_trial(_plan(3500, [{"t_s": 1.5, "kind": "marker"}, {"t_s": 9.0, "kind": "never"}]), be, log,
                    handle_signals=False)
    assert res.status == "completed" and res.cause == "end_of_plan" and log.status == "completed"
    assert res.ticks == 3500 and log.ticks == 3500 and be.closed
    assert [t for t, _ in log.stats] == pytest.approx([1.099, 2.099, 3.099])  # every second of trial time
    st = log.stats[0][1]
    assert st["tracking_error_rms_um"] == pytest.approx(1.0) and st["scripted_window"] == 1.0
    kinds = [e["kind"] for e in log.events]
    assert kinds[0] == "trial_start" and "marker" in kinds and "never" not in kinds  # only events reached
    assert [e["state"] for e in log.events if e["kind"] == "stop_state"] == ["stopping", "safe"]
    assert res.figures.mean_mu == pytest.approx(0.1)
    assert log.summary["tracking_error_rms_um"] == pytest.approx(1.0)


def test_ctrl_c_is_a_controlled_stop_and_the_backend_finishes():
    log = MemoryLog()
    be = ScriptedBackend(50, stop_after_request=3)  # the backend still sends 3 blocks (holding) after the request

    def progress(t_s):
        if 0.45 < t_s < 0.55:
            raise KeyboardInterrupt

    res = run_trial(_plan(5000), be, log, progress=progress, handle_signals=False)
    assert res.status == "interrupted" and res.cause == "operator" and log.status == "interrupted"
    assert be.stop_reason == "operator abort (Ctrl-C)" and not be.insisted
    assert res.ticks == 800  # 5 blocks, then 3 more while stopping
    assert [h[0] for h in res.history] == [Phase.RUNNING, Phase.STOPPING, Phase.SAFE, Phase.DONE]
    assert any(e["kind"] == "interrupted" for e in log.events)


def test_backend_failure_mid_run_keeps_the_log_and_says_why():
    log = MemoryLog()
    be = ScriptedBackend(50, fail_at=7, safe=False)
    res = run_trial(_plan(5000), be, log, handle_signals=False)
    assert res.status == "failed" and res.cause == "failure" and "OSError: link down" in res.reason
    assert be.stop_reason == res.reason  # asked to stop
    assert res.ticks == 700 and log.status == "failed"
    assert not res.safe and res.history[-2][0] is Phase.STOPPING  # the backend did not report safe
    assert any(e["kind"] == "trial_failed" and "link down" in e["message"] for e in log.events)


def test_a_failing_log_stops_the_backend():
    class DiskFull(MemoryLog):
        def write_block(self, block):
            if self.ticks >= 500:
                raise OSError(28, "No space left on device")
            super().write_block(block)

    log = DiskFull()
    be = ScriptedBackend(50, stop_after_request=2)
    res = run_trial(_plan(5000), be, log, handle_signals=False)
    assert be.stop_reason and "No space left on device" in be.stop_reason  # the backend was told to stop
    assert res.status == "failed" and res.cause == "failure" and "No space left" in res.reason
    assert res.ticks == 500 and res.safe  # the backend drained to its end and reported safe


def test_trip_reported_by_the_backend_fails_the_trial():
    log = MemoryLog()
    be = ScriptedBackend(4, ending=Ending("tripped", "INTERLOCK stroke_limit at t=0.3 s", safe=True))
    res = run_trial(_plan(5000), be, log, handle_signals=False)
    assert res.status == "failed" and res.cause == "trip" and res.reason.startswith("INTERLOCK stroke_limit")
    assert res.safe


def test_interlock_events_are_echoed():
    class Tripping(ScriptedBackend):
        def receive(self):
            if self.i == 2 and not getattr(self, "sent", False):
                self.sent = True
                return Event(0.2, "interlock", {"name": "friction_limit", "message": "|friction| 300 N"})
            return super().receive()

    said = []
    log = MemoryLog()
    run_trial(_plan(500), Tripping(5), log, echo=said.append, handle_signals=False)
    assert said == ["INTERLOCK friction_limit at t=0.200 s: |friction| 300 N"]
    assert any(e["kind"] == "interlock" for e in log.events)


def test_simulate_a_recipe_in_memory(repo_root):
    profile = load_profile(repo_root / "config/rigs/sim.yaml")
    recipe = load_recipe(repo_root / "config/recipes/smoke.yaml")
    log, res = simulate(recipe, profile, seed=3)
    assert res.status == "completed" and log.status == "completed"
    raw = log.columns()
    assert raw["t_s"].size == res.ticks and np.allclose(np.diff(raw["t_s"]), 1e-3)
    tr = log.trial_data(25.0)
    # block means of 40 ticks (rig.log.decimate), time-stamped at the interval's centre
    assert len(tr) == int(np.ceil(res.ticks / 40))
    assert tr.time_s[1] == pytest.approx(raw["t_s"][40:80].mean())
    assert tr.position_um[1] == pytest.approx(raw["position_um"][40:80].mean())
    assert tr.metadata["lubricant"] == recipe.lubricant and "true_mu" in tr.extra
    assert {"segment_start", "segment_end"} <= {e["kind"] for e in tr.events}
    # the same as the backend alone, bit for bit (a fixed seed)
    be = SimBackend(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, 3, block_ticks=777)
    log2 = MemoryLog()
    run_trial(compile_recipe(recipe, profile), be, log2, handle_signals=False)
    assert np.array_equal(log2.column("friction_N"), raw["friction_N"])
