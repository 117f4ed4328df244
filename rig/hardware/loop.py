"""The 1 kHz real-time loop, in its own process (the GIL: logging and the CLI live elsewhere).

Each tick, in the manner of ros2_control's controller manager (Dupont &
Dunlap 1995, section 3 and Fig. 4):

1. **read**: every device's ``read(now)`` (LVDT frames, the load-cell
   request, the valve's status frames; :mod:`rig.hardware.devices`);
2. **update**: the interlocks over the process values and each device's
   :class:`drivers.device.DeviceHealth`, then the controller
   (:func:`rig.control.controller_step`: PID on x_ref - x + 500 Hz dither,
   command = demand / full-scale force);
3. **write**: every device's ``write(now)`` (the valve's setpoint; its enable).

Samples go to the parent in blocks (``BLOCK_KEYS``) on a multiprocessing
queue, with the per-tick lateness, period, execution time and device read
time; the parent (:class:`rig.session.hardware.HardwareBackend`) logs them.

The loop's own stop states (:class:`Mode`): ``RUN`` -> ``HOLD`` (operator
abort: the reference frozen where it was, for ``stop_hold_s``) -> ``SAFE``
(valve nulled and disabled; the sensors are still logged for ``stop_hold_s``
after a process-limit trip, one tick after a device trip) -> end. The end of
the plan goes from ``RUN`` to ``SAFE`` for the last tick. Parent death
(PR_SET_PDEATHSIG -> SIGTERM) is an abort.
"""

from __future__ import annotations

import gc
import signal
import time
import traceback
from enum import Enum

import numpy as np

from drivers.config import parse_hardware
from drivers.errors import DeviceError
from rig.control import controller_params_from_profile, controller_step, new_controller_state
from rig.hardware.devices import build_devices, wait_for_data
from rig.hardware.interlocks import DEVICE_TRIPS, Interlocks, Trip
from rig.hardware.timing import Pacer, set_pdeathsig, set_process_name, setup_realtime

BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N",
              "valve_cmd", "pid_p", "pid_i", "pid_d", "dither")
N_KEYS = len(BLOCK_KEYS)


class Mode(Enum):
    RUN = 0
    HOLD = 1   # operator abort: reference frozen, still under control
    SAFE = 2   # valve nulled and disabled


class _Block:
    """Rows of one block, preallocated: ``rows[:, i]`` is tick i in the order of BLOCK_KEYS."""

    def __init__(self, n: int):
        self.n = n
        self.rows = np.empty((N_KEYS, n))
        self.late = np.empty(n)
        self.period = np.empty(n)
        self.exec = np.empty(n)
        self.read = np.empty(n)
        self.i = 0
        self.skipped = 0

    def take(self):
        i = self.i
        blk = {k: self.rows[r, :i].copy() for r, k in enumerate(BLOCK_KEYS)}
        tim = {"late_s": self.late[:i].copy(), "period_s": self.period[:i].copy(),
               "exec_s": self.exec[:i].copy(), "read_s": self.read[:i].copy(), "skipped": self.skipped}
        self.i = 0
        self.skipped = 0
        return blk, tim


def loop_main(hw_dict, profile, x_ref_um, out_q, abort_flag, options=None):
    """Entry point of the loop process. ``abort_flag``: a shared ``multiprocessing.Value('i')``."""
    options = options or {}
    set_process_name("rig-rt-loop")
    set_pdeathsig(signal.SIGTERM)
    stop_req = {"why": None}

    def _term(signum, _frame):
        stop_req["why"] = f"signal {signal.Signals(signum).name}"

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it sets abort_flag
    try:
        _run(hw_dict, profile, np.asarray(x_ref_um, dtype=float), out_q, abort_flag, stop_req, options)
    except BaseException as exc:  # noqa: BLE001 - report, never die silently
        out_q.put(("done", {"status": "error", "message": f"{type(exc).__name__}: {exc}",
                            "traceback": traceback.format_exc()}))


def _device_counters(devices) -> dict:
    out = {}
    for d in devices:
        h = d.health()
        out[f"{d.name}_frames_ok"] = h.frames_ok
        out[f"{d.name}_frames_bad"] = h.frames_bad
        out[f"{d.name}_frames_lost"] = h.frames_lost
        out[f"{d.name}_errors"] = h.errors
    return out


def _run(hw_dict, profile, x_ref, out_q, abort_flag, stop_req, options):
    import logging
    import sys

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported as DeviceError
    sys.setswitchinterval(1e-4)
    hw = parse_hardware(hw_dict)
    rt, ilc = hw.realtime, hw.interlocks
    period = float(options.get("period_s") or profile.loop.dt_s)
    use_ctl = options.get("controller", True)
    cpar = controller_params_from_profile(profile)
    cst = new_controller_state()
    rig = build_devices(hw)
    devices = rig.all
    pos, forces, valve = rig.position, rig.forces, rig.valve
    il = Interlocks(ilc, float(profile.stroke.min_um), float(profile.stroke.max_um),
                    hw.valve.heartbeat_timeout_s, period)
    mono = time.monotonic
    failed: list[DeviceError] = []
    for dev in devices:  # every device that does not answer is named, not just the first
        try:
            dev.connect()
        except DeviceError as exc:
            failed.append(exc)
    if not failed:
        try:
            wait_for_data(devices, max(0.5, 4 * hw.valve.heartbeat_timeout_s), mono)
        except DeviceError as exc:
            failed.append(exc)
    if failed:
        for d in devices:
            d.close()
        out_q.put(("done", {"status": "error", "message": "; ".join(map(str, failed)),
                            "devices_failed": [{"device": e.device, "address": e.address} for e in failed]}))
        return
    health = {d.name: d.health(mono()) for d in devices}  # updated in place by d.health(now)
    rt_info = setup_realtime(rt.sched_fifo, rt.priority, rt.cpu)
    out_q.put(("info", {"realtime": rt_info, "period_s": period,
                        "devices": {d.name: d.address for d in devices}}))
    controller_step(cpar, cst, float(x_ref[0]), float(x_ref[0]))  # compiled before the first tick
    cst[:] = new_controller_state()

    n_ticks = len(x_ref)
    hold_ticks = max(1, int(round(ilc.stop_hold_s / period)))
    blk = _Block(rt.block_ticks)
    pacer = Pacer(period, rt_info["sched"] == "SCHED_FIFO", rt.spin_s)
    status = "completed"
    trip: Trip | None = None
    mode = Mode.RUN
    hold_ref = 0.0
    hold_end_k = 0
    stop_k = n_ticks

    # enable the valve (its controller answers with the enabled bit), nulled
    valve.command, valve.enable = 0.0, True
    t_en = mono()
    try:
        while not valve.enabled and mono() - t_en < 0.2:
            valve.write(mono())
            time.sleep(0.001)
            valve.read(mono())
    except DeviceError:
        pass
    if not valve.enabled:
        trip = Trip("valve_enable", f"servovalve controller at {valve.address} did not enable", 0.0,
                    {"status_bits": valve.final_state()["status_bits"]})
    out_q.put(("event", 0.0, "loop_start", {"sched": rt_info["sched"], "note": rt_info["note"]}))
    for d in devices:  # drain what arrived while enabling; staleness counts from here
        try:
            d.read(mono())
        except DeviceError:
            pass
    # the cyclic GC would scan every object numba/numpy/pydantic created (tens of ms):
    # freeze what exists and switch it off; the loop makes (almost) no reference cycles
    gc.collect()
    gc.freeze()
    gc.disable()
    pacer.start()
    prev_wake = float("nan")
    perf = time.perf_counter
    if trip is not None:
        status, mode, stop_k = "tripped", Mode.SAFE, 0
        out_q.put(("event", 0.0, "interlock", trip.as_dict()))
    x = pos.position_um
    cmd = p = i_ = d_ = dz = 0.0
    while True:
        k, dl, wake = pacer.wait()
        if k >= stop_k:
            break
        c0 = perf()
        t_s = k * period
        # -- read ------------------------------------------------------------------
        dev_trip = None
        for dev in devices:
            try:
                dev.read(wake)
            except DeviceError as exc:
                dev_trip = dev_trip or il.device_error(t_s, dev.name, exc, dev.health(wake))
        c1 = perf()
        x = pos.position_um
        f, n1, n2 = forces.forces_N
        for dev in devices:
            dev.health(wake)
        # -- update: reference, stop states, interlocks, controller -------------------
        xr = hold_ref if mode is Mode.HOLD else float(x_ref[k]) if k < n_ticks else float(x_ref[-1])
        if mode is not Mode.SAFE:
            tr = dev_trip or il.check(t_s, wake, xr, x, f, n1, n2, health, wake - dl)
            if tr is not None:
                trip, status, mode = tr, "tripped", Mode.SAFE
                stop_k = k + (1 if tr.name in DEVICE_TRIPS else hold_ticks)
                out_q.put(("event", t_s, "interlock", tr.as_dict()))
            elif mode is Mode.RUN and (abort_flag.value or stop_req["why"]):
                status, mode, hold_ref = "aborted", Mode.HOLD, xr
                hold_end_k = k + hold_ticks
                stop_k = hold_end_k + 1
                out_q.put(("event", t_s, "abort", {"reason": "operator abort" if abort_flag.value
                                                   else stop_req["why"], "hold_um": xr}))
            elif mode is Mode.HOLD and k >= hold_end_k:
                mode = Mode.SAFE
        if mode is Mode.SAFE or not use_ctl:
            cmd = p = i_ = d_ = dz = 0.0
        else:
            cmd, p, i_, d_, dz = controller_step(cpar, cst, xr, x)
        # -- write -------------------------------------------------------------------
        valve.command = cmd
        valve.enable = mode is not Mode.SAFE
        for dev in devices:
            try:
                dev.write(wake)
            except DeviceError as exc:
                if mode is not Mode.SAFE:
                    tr = il.device_error(t_s, dev.name, exc, dev.health(wake))
                    if tr is not None:
                        trip, status, mode, stop_k = tr, "tripped", Mode.SAFE, k + 1
                        out_q.put(("event", t_s, "interlock", tr.as_dict()))
        # -- record ------------------------------------------------------------------
        j = blk.i
        r = blk.rows
        r[0, j] = t_s
        r[1, j] = xr
        r[2, j] = x
        r[3, j] = f
        r[4, j] = n1
        r[5, j] = n2
        r[6, j] = cmd
        r[7, j] = p
        r[8, j] = i_
        r[9, j] = d_
        r[10, j] = dz
        blk.late[j] = wake - dl
        blk.period[j] = wake - prev_wake
        blk.read[j] = c1 - c0
        prev_wake = wake
        blk.i = j + 1
        blk.exec[j] = perf() - c0
        if blk.i >= blk.n:
            b, tim = blk.take()
            tim["devices"] = _device_counters(devices)
            out_q.put(("block", b, tim))
        skipped = pacer.advance()
        if skipped:
            blk.skipped += skipped
            prev_wake = float("nan")
        if k == n_ticks - 1 and mode is Mode.RUN:
            mode, stop_k = Mode.SAFE, k + 1  # end of the plan
    # -- safe state ----------------------------------------------------------------------
    valve.command, valve.enable = 0.0, False
    try:
        valve.write(mono())
    except DeviceError:
        pass
    if blk.i:
        b, tim = blk.take()
        tim["devices"] = _device_counters(devices)
        out_q.put(("block", b, tim))
    summary = {"status": status, "ticks": int(pacer.k), "skipped": int(pacer.skipped),
               "devices": {d.name: d.health(mono()).as_dict() for d in devices}, "realtime": rt_info}
    if trip is not None:
        summary["trip"] = trip.as_dict()
        summary["message"] = str(trip)
    time.sleep(0.005)
    try:
        valve.read(mono())
    except DeviceError:
        pass
    summary["valve_final"] = valve.final_state()
    for dev in devices:
        dev.close()
    out_q.put(("done", summary))
