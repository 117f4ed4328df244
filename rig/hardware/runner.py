"""``rig run --hardware PROFILE``: the trial on the real (or emulated) rig.

:func:`run_hardware_trial` starts the emulators when the profile says
``hardware.emulators.autostart`` (``config/rigs/emulated.yaml``), starts the
1 kHz loop process (:mod:`rig.hardware.loop`), and in this process logs what
the loop sends: blocks to ``writer.write_block``, events, loop timing
statistics every second (``writer.loop_stats``), and at the end prints the
timing report. Ctrl-C / SIGTERM set the loop's abort flag: controlled stop
(position held, valve nulled and disabled), the log keeps everything so far,
and :class:`HardwareTrialAborted` (a KeyboardInterrupt, so ``rig run`` exits
130) is raised. An interlock trip or a lost device raises
:class:`HardwareTrialFailed` (exit 1) after logging it. If the loop process
dies (kill -9), the trial ends with what was received (at most one block,
0.1 s, is lost) and the valve controller's watchdog nulls the valve.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_mod
import signal
import sys
import time

import numpy as np

from drivers.config import hardware_of_profile
from rig.hardware.timing import TimingStats, format_stats


class HardwareTrialFailed(RuntimeError):
    """The hardware trial stopped on an interlock or a device error (already logged)."""

    def __init__(self, message: str, summary: dict | None = None):
        super().__init__(message)
        self.summary = summary or {}


class HardwareTrialAborted(KeyboardInterrupt):
    """Operator abort (Ctrl-C / SIGTERM): controlled stop done, log kept."""


def _v_init(x_ref: np.ndarray, rate_hz: float, creep: float) -> float:
    # the same initial friction state as rig.sim.SimRig.run_blocks
    k = min(x_ref.size - 1, int(round(0.1 * rate_hz)))
    v0 = abs(x_ref[k] - x_ref[0]) / (k / rate_hz) if k > 0 else 0.0
    return v0 if v0 > creep else creep


def start_loop_process(hw, profile, x_ref_um, options=None):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    abort = ctx.Value("i", 0, lock=False)
    from rig.hardware.loop import loop_main

    proc = ctx.Process(target=loop_main, name="rig-rt-loop", daemon=True,
                       args=(hw.model_dump(), profile, np.asarray(x_ref_um, dtype=float), q, abort,
                             options or {}))
    proc.start()
    return proc, q, abort


def run_hardware_trial(plan, recipe, profile, writer, progress=None, *, emulator=None,
                       echo=print, stats_every_s: float = 1.0) -> dict:
    """Run ``plan`` on the rig described by ``profile.hardware``; log to ``writer``.

    ``emulator``: an already started :class:`drivers.emulators.rig.EmulatorHandle`
    (tests); otherwise the emulators are started here when the profile's
    ``hardware.emulators.autostart`` is true. Returns a summary dict.
    """
    hw = hardware_of_profile(profile)
    rate_hz = float(plan.loop_rate_hz)
    x_ref = np.asarray(plan.x_ref_um, dtype=float)
    own_emulator = None
    if emulator is None and hw.emulators.autostart:
        from drivers.emulators.rig import start_emulator_process

        own_emulator = emulator = start_emulator_process(
            hw, profile, lubricant=getattr(recipe, "lubricant", None),
            normal_force_N=getattr(recipe, "normal_force_N", None),
            seed=getattr(recipe, "seed", None))
    if emulator is not None:
        creep = getattr(getattr(profile, "sim", None), "initial_creep_um_s", 0.01)
        emulator.reset_plant(float(x_ref[0]), _v_init(x_ref, rate_hz, creep))

    writer.schedule_events(plan.events)
    writer.event(0.0, "trial_start", recipe=getattr(recipe, "name", ""), backend="hardware",
                 duration_s=float(plan.duration_s), n_ticks=int(x_ref.size),
                 loadcells=hw.loadcells.address_text, lvdt=hw.lvdt.address_text,
                 valve=hw.valve.address_text, emulated=emulator is not None)
    proc, q, abort = start_loop_process(hw, profile, x_ref, {"period_s": 1.0 / rate_hz})
    stats = TimingStats(1.0 / rate_hz)
    summary: dict = {}
    signals = {"n": 0, "name": None}

    def _on_signal(signum, _frame):
        signals["n"] += 1
        signals["name"] = signal.Signals(signum).name
        abort.value = 1  # controlled stop: the loop holds, nulls, disables
        if signals["n"] >= 3 and proc.is_alive():
            proc.terminate()  # insisted: the loop stops now (the valve watchdog nulls the valve)

    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, _on_signal)
        except ValueError:  # not the main thread
            pass
    t_last = 0.0
    next_stats = stats_every_s
    info = {}
    try:
        while True:
            try:
                msg = q.get(timeout=0.25)
            except queue_mod.Empty:
                if not proc.is_alive():
                    # drain what is left, then report the death
                    try:
                        msg = q.get(timeout=0.5)
                    except queue_mod.Empty:
                        summary = {"status": "loop_died", "exitcode": proc.exitcode,
                                   "message": f"the loop process died (exit code {proc.exitcode}); "
                                              f"log kept up to t={t_last:.3f} s"}
                        writer.event(t_last, "loop_died", exitcode=proc.exitcode)
                        break
                else:
                    continue
            kind = msg[0]
            if kind == "block":
                blk, tim = msg[1], msg[2]
                writer.write_block(blk)
                stats.add(tim["late_s"], tim["period_s"], tim["exec_s"], tim["skipped"])
                if "modbus_s" in tim and tim["modbus_s"].size:
                    stats.modbus_max_s = max(getattr(stats, "modbus_max_s", 0.0), float(tim["modbus_s"].max()))
                    stats.modbus_slow = getattr(stats, "modbus_slow", 0) + int((tim["modbus_s"] > 1e-3).sum())
                t_last = float(blk["t_s"][-1])
                if t_last >= next_stats - 0.5 / rate_hz:
                    w = stats.window()
                    w.pop("late_hist_edges_us", None)
                    w.update(tim.get("devices", {}))  # cumulative device error counters
                    writer.loop_stats(t_last, w)
                    next_stats += stats_every_s
                if progress is not None:
                    progress(t_last)
            elif kind == "event":
                _, t_s, ev, data = msg
                writer.event(float(t_s), ev, **{k: v for k, v in data.items() if k not in ("t_s", "kind")})
                if ev == "interlock":
                    echo(f"INTERLOCK {data['name']} at t={data['t_s']:.3f} s: {data['message']}",
                         file=sys.stderr)
            elif kind == "info":
                info = msg[1]
                writer.event(0.0, "realtime", **{k: v for k, v in info["realtime"].items()})
            elif kind == "done":
                summary = msg[1]
                break
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        proc.join(3)
        if proc.is_alive():
            proc.terminate()
            proc.join(2)
        if own_emulator is not None:
            own_emulator.stop()
    final = stats.final()
    final["modbus_max_us"] = getattr(stats, "modbus_max_s", 0.0) * 1e6
    final["modbus_over_1ms"] = getattr(stats, "modbus_slow", 0)
    summary["timing"] = final
    summary["realtime"] = info.get("realtime")
    if final.get("n"):
        final_log = dict(final)
        final_log["final"] = True
        writer.loop_stats(t_last, final_log)
        echo(format_stats(final, "loop timing (whole trial)"), file=sys.stderr)
    summary["ticks"] = writer.ticks
    summary["duration_s"] = t_last
    status = summary.get("status")
    if status == "aborted" or signals["n"]:
        writer.event(t_last, "interrupted", reason=f"operator abort ({signals['name'] or 'abort'})")
        raise HardwareTrialAborted(f"aborted by {signals['name']}")
    if status != "completed":
        msg = summary.get("message") or status
        writer.event(t_last, "trial_failed", status=status, message=msg)
        raise HardwareTrialFailed(msg, summary)
    return summary


__all__ = ["run_hardware_trial", "HardwareTrialFailed", "HardwareTrialAborted", "start_loop_process"]
