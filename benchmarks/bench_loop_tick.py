"""Where a tick of the 1 kHz loop goes: per-phase timings in-process (not a timed test).

    python benchmarks/bench_loop_tick.py [--seconds 10] [--profile] [--no-fifo]

Against the emulators of config/rigs/emulated.yaml (started in their own process, as
``rig loop-bench`` does). Two measurements:

* default: the loop's devices and checks driven tick by tick at 1 kHz (SCHED_FIFO 80 where
  permitted), each phase timed with ``perf_counter``: LVDT read, load-cell read (collect the
  answer, send the next request), valve read (drain the CAN frames), the three devices'
  health, the interlocks, the controller, the valve's write (RPDO + SYNC); p50 / p99 per phase
  and the whole tick. Less load-sensitive than ``loop-bench``'s percentiles (the phases are
  short), so a change can be judged on a shared machine.
* ``--profile``: ``rig.hardware.loop._run`` itself in this process under cProfile (the per-tick
  call counts and the functions' own time; cProfile inflates Python calls, so only the relative
  costs count), then the loop's own execution-time percentiles without the profiler.

Prints the load average beside the figures: on the shared 2-core machine they are noisy.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PHASES = ("lvdt_read", "loadcells_read", "valve_read", "health", "interlocks", "controller", "valve_write",
          "tick")



class _Value:
    def __init__(self, v):
        self.value = v


def _pct(a, q):
    import numpy as np

    return float(np.percentile(a, q)) if len(a) else math.nan


def phases(hw, profile, seconds: float, fifo: bool) -> dict:
    """Drive the loop's devices, interlocks and controller at 1 kHz and time each phase (µs)."""
    import gc

    import numpy as np

    from drivers.errors import DeviceError
    from rig.control import controller_params_from_profile, controller_step_v, new_controller_state
    from rig.hardware.devices import build_devices, wait_for_data
    from rig.hardware.interlocks import Interlocks
    from rig.hardware.timing import Pacer, setup_realtime

    rig = build_devices(hw)
    devs = rig.all
    lvdt, cells, valve = rig.position, rig.forces, rig.valve
    for d in devs:
        d.connect()
    wait_for_data(devs, 2.0, time.monotonic)
    il = Interlocks(hw.interlocks, float(profile.stroke.min_um), float(profile.stroke.max_um),
                    hw.valve.heartbeat_timeout_s, 1e-3)
    cpar = controller_params_from_profile(profile)
    cst = new_controller_state()
    x_home = float(profile.stroke.home_um)
    controller_step_v(cpar, cst, x_home, x_home, math.nan, 0.0)
    cst[:] = new_controller_state()
    rt = setup_realtime(fifo, 80, None)
    health = {d.name: d.health(time.monotonic()) for d in devs}
    valve.start()
    for d in devs:
        d.read(time.monotonic())
    n = int(seconds * 1000)
    t = np.zeros((len(PHASES), n))
    pacer = Pacer(1e-3, rt["sched"] == "SCHED_FIFO", 50e-6)
    perf = time.perf_counter
    gc.collect()
    gc.freeze()
    gc.disable()
    pacer.start()
    trips = []
    errors = 0
    try:
        for i in range(n):
            _, dl, wake = pacer.wait()
            c0 = perf()
            try:  # as the loop: a device error is counted (the interlocks judge it), the tick goes on
                lvdt.read(wake)
            except DeviceError:
                errors += 1
            c1 = perf()
            try:
                cells.read(wake)
            except DeviceError:
                errors += 1
            c2 = perf()
            try:
                valve.read(wake)
            except DeviceError:
                errors += 1
            c3 = perf()
            for d in devs:
                d.health(wake)
            c4 = perf()
            f, n1, n2 = cells.forces_N
            tr = il.check(i * 1e-3, wake, x_home, lvdt.position_um, f, n1, n2, health, wake - dl, 0.0)
            if tr is not None:
                trips.append(tr)
            c5 = perf()
            cmd, *_ = controller_step_v(cpar, cst, x_home, lvdt.position_um, math.nan, 0.0)
            c6 = perf()
            valve.command, valve.enable = cmd, True
            valve.write(wake)
            c7 = perf()
            t[:, i] = (c1 - c0, c2 - c1, c3 - c2, c4 - c3, c5 - c4, c6 - c5, c7 - c6, c7 - c0)
            pacer.advance()
    finally:
        gc.enable()
        valve.safe_stop()
        for d in devs:
            d.close()
        if rt["sched"] == "SCHED_FIFO":
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    t *= 1e6
    out = {name: {"p50_us": _pct(t[k], 50), "p99_us": _pct(t[k], 99)} for k, name in enumerate(PHASES)}
    out["sched"] = rt["sched"]
    out["skipped"] = pacer.skipped
    out["trips"] = [tr.name for tr in trips[:5]]
    out["device_errors"] = errors
    return out


def run_loop(hw_dict, profile, seconds: float, profiled: bool):
    """``rig.hardware.loop._run`` in this process (optionally under cProfile); its blocks' execution
    times (µs) and, profiled, the pstats text."""
    import cProfile
    import pstats

    import numpy as np

    from rig.hardware import loop as L

    x = np.full(int(seconds * 1000), float(profile.stroke.home_um))
    from rig.hardware.fake import ListQueue

    q = ListQueue()
    args = (hw_dict, profile, x, q, _Value(0), {"why": None}, {"period_s": 1e-3}, None, None)
    text = ""
    if profiled:
        pr = cProfile.Profile()
        pr.enable()
        L._run(*args)
        pr.disable()
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(30)
        text = s.getvalue()
    else:
        L._run(*args)
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    blocks = [m for m in q.items if m[0] == "block"]
    ex = np.concatenate([m[2]["exec_s"] for m in blocks]) * 1e6 if blocks else np.empty(0)
    rd = np.concatenate([m[2]["read_s"] for m in blocks]) * 1e6 if blocks else np.empty(0)
    done = next((m[1] for m in q.items if m[0] == "done"), {})
    return {"status": done.get("status"), "message": done.get("message"), "exec_p50_us": _pct(ex, 50),
            "exec_p99_us": _pct(ex, 99), "read_p50_us": _pct(rd, 50), "read_p99_us": _pct(rd, 99),
            "skipped": done.get("skipped")}, text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--profile", action="store_true", help="cProfile the loop's _run in-process")
    ap.add_argument("--no-fifo", action="store_true", help="SCHED_OTHER (sleep then spin)")
    ap.add_argument("--hardware", type=Path, default=REPO / "config/rigs/emulated.yaml")
    a = ap.parse_args(argv)

    from drivers.config import hardware_of_profile
    from rig.config.profile import load_profile
    from rig.hardware.emulated import start_emulator_process

    profile = load_profile(a.hardware)
    hw = hardware_of_profile(profile)
    emu = start_emulator_process(hw, profile, lubricant="boundary")
    load0 = os.getloadavg()
    try:
        emu.reset_plant(float(profile.stroke.home_um), 0.0)
        if a.profile:
            res, text = run_loop(emu.hw.model_dump(), profile, a.seconds, True)
            print(text)
            print(f"profiled loop: {res}")
            emu.reset_plant(float(profile.stroke.home_um), 0.0)
            res, _ = run_loop(emu.hw.model_dump(), profile, a.seconds, False)
            print(f"loop without the profiler ({a.seconds:g} s): execution p50 {res['exec_p50_us']:.1f} µs, "
                  f"p99 {res['exec_p99_us']:.1f} µs; device reads p50 {res['read_p50_us']:.1f} µs, "
                  f"p99 {res['read_p99_us']:.1f} µs; skipped {res['skipped']}; {res['status']} "
                  f"{res['message'] or ''}")
        else:
            res = phases(emu.hw, profile, a.seconds, not a.no_fifo)
            print(f"per phase of a tick, {a.seconds:g} s at 1 kHz, {res['sched']}, skipped {res['skipped']}, "
                  f"trips {res['trips'] or 'none'}, device errors {res['device_errors']}:")
            for name in PHASES:
                print(f"  {name:15s} p50 {res[name]['p50_us']:7.1f} µs   p99 {res[name]['p99_us']:7.1f} µs")
    finally:
        emu.stop()
    load1 = os.getloadavg()
    print(f"load average before {load0[0]:.2f}, after {load1[0]:.2f} on {os.cpu_count()} CPUs "
          f"(a shared machine: noisy)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
