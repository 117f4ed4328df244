"""The 1 kHz real-time loop, in its own process (the GIL: logging and the CLI live elsewhere).

Each tick (Dupont & Dunlap 1995, section 3 and Fig. 4): read sensors (LVDT
frames, one Modbus request for the three load cells, CAN status) -> PID on
position error x_ref - x (``rig.control.Controller``: PID + 500 Hz dither,
command = demand / full-scale force) -> valve setpoint on CAN -> interlocks.
Samples go to the parent in blocks (the block-dict keys of TEAM-CONTRACTS.md)
on a multiprocessing queue, with the per-tick lateness, period and execution
time; the parent logs and computes statistics.

Stops: end of plan (null + disable), an interlock trip (null + disable at
once, sensors logged for ``stop_hold_s``), operator abort (the abort flag:
hold the position for ``stop_hold_s`` with the reference frozen, then null +
disable), parent death (PR_SET_PDEATHSIG -> SIGTERM -> same as abort).
"""

from __future__ import annotations

import gc
import signal
import time
import traceback

import numpy as np

from drivers.config import parse_hardware
from drivers.errors import DeviceError
from drivers.loadcells import LoadCellReader
from drivers.lvdt import LvdtReader
from drivers.valve import ValveController
from rig.hardware.interlocks import Interlocks, Trip
from rig.hardware.timing import Pacer, set_pdeathsig, set_process_name, setup_realtime

DEVICE_TRIPS = ("device_lost", "modbus_errors", "can_bus_errors", "stale_forces", "stale_position",
                "valve_heartbeat")
BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N",
              "valve_cmd", "pid_p", "pid_i", "pid_d", "dither")


class _Block:
    def __init__(self, n: int):
        self.n = n
        self.a = {k: np.empty(n) for k in BLOCK_KEYS}
        self.late = np.empty(n)
        self.period = np.empty(n)
        self.exec = np.empty(n)
        self.t_modbus = np.empty(n)
        self.i = 0
        self.skipped = 0

    def take(self):
        i = self.i
        blk = {k: v[:i].copy() for k, v in self.a.items()}
        tim = {"late_s": self.late[:i].copy(), "period_s": self.period[:i].copy(),
               "exec_s": self.exec[:i].copy(), "modbus_s": self.t_modbus[:i].copy(),
               "skipped": self.skipped}
        self.i = 0
        self.skipped = 0
        return blk, tim


def _stroke_of(profile) -> tuple[float, float]:
    try:
        return float(profile.stroke.min_um), float(profile.stroke.max_um)
    except AttributeError:
        return 0.0, 5000.0


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


def _run(hw_dict, profile, x_ref, out_q, abort_flag, stop_req, options):
    import logging
    import sys

    from rig.control import Controller

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported as DeviceError
    sys.setswitchinterval(1e-4)
    hw = parse_hardware(hw_dict)
    rt = hw.realtime
    period = float(options.get("period_s") or getattr(getattr(profile, "loop", None), "dt_s", 1e-3))
    ctl = Controller.from_profile(profile) if options.get("controller", True) else None
    lc = LoadCellReader(hw.loadcells)
    lv = LvdtReader(hw.lvdt)
    va = ValveController(hw.valve)
    smin, smax = _stroke_of(profile)
    il = Interlocks(hw.interlocks, smin, smax, hw.valve.heartbeat_timeout_s, period)
    devices = []
    try:
        for dev in (lc, lv, va):
            dev.connect()
            devices.append(dev)
        va.wait_status(max(0.2, 4 * hw.valve.heartbeat_timeout_s))
        lv.wait_frame(0.5)
        first_forces = lc.read()
    except DeviceError as exc:
        for d in devices:
            d.close()
        out_q.put(("done", {"status": "error", "message": str(exc), "device": exc.device,
                            "address": exc.address}))
        return
    rt_info = setup_realtime(rt.sched_fifo, rt.priority, rt.cpu)
    out_q.put(("info", {"realtime": rt_info, "period_s": period,
                        "devices": {"loadcells": lc.address, "lvdt": lv.address, "valve": va.address}}))
    ctl_warm = ctl.step(float(x_ref[0]), float(x_ref[0])) if ctl is not None else None  # compile
    if ctl is not None:
        ctl.reset()
    del ctl_warm

    n_ticks = len(x_ref)
    blk = _Block(rt.block_ticks)
    pacer = Pacer(period, rt_info["sched"] == "SCHED_FIFO", rt.spin_s)
    status = "completed"
    trip: Trip | None = None
    hold_until_k = None
    hold_ref = None
    stopping = False  # null + disabled (trip / end)
    err_counts = {"modbus": 0, "can": 0}
    x = lv.position_um
    f, n1, n2 = first_forces
    send_pending = False

    va.enable()
    t_en = time.monotonic()
    while not va.enabled and time.monotonic() - t_en < 0.2:
        va.write(0.0)
        time.sleep(0.001)
        va.poll()
    if not va.enabled:
        trip = Trip("valve_enable", f"servovalve controller at {va.address} did not enable", 0.0,
                    {"status_bits": va.status_bits})
    out_q.put(("event", 0.0, "loop_start", {"sched": rt_info["sched"], "note": rt_info["note"]}))

    stop_k = n_ticks
    try:
        lv.poll()
        va.poll()
    except DeviceError:
        pass
    lv.polls_since_frame = 0
    lc.reads_since_new = 0
    va.polls_since_status = 0
    # the cyclic GC would scan every object numba/numpy/pydantic created (tens of ms):
    # freeze what exists and switch it off; the loop makes (almost) no reference cycles
    gc.collect()
    gc.freeze()
    gc.disable()
    pacer.start()
    prev_wake = float("nan")
    mono = time.monotonic
    perf = time.perf_counter
    if trip is not None:
        status = "tripped"
        stopping = True
        stop_k = 0
        out_q.put(("event", 0.0, "interlock", trip.as_dict()))
    while True:
        k, dl, wake = pacer.wait()
        if k >= stop_k:
            break
        c0 = perf()
        late = wake - dl
        t_s = k * period
        # -- read ---------------------------------------------------------------
        dev_trip = None
        try:
            lv.poll(wake)
            x = lv.position_um
        except DeviceError as exc:
            dev_trip = il.device_error(t_s, exc, err_counts)
        c1 = perf()
        try:
            f, n1, n2 = lc.read(wake)
            err_counts["modbus"] = 0
        except DeviceError as exc:
            err_counts["modbus"] += 1
            dev_trip = dev_trip or il.device_error(t_s, exc, err_counts)
        blk.t_modbus[blk.i] = perf() - c1
        try:
            va.poll(wake)
        except DeviceError as exc:
            dev_trip = dev_trip or il.device_error(t_s, exc, err_counts)
        # -- reference ------------------------------------------------------------
        if hold_ref is not None:
            xr = hold_ref
        else:
            xr = float(x_ref[k]) if k < n_ticks else float(x_ref[-1])
        # -- interlocks -------------------------------------------------------------
        if not stopping:
            tr = dev_trip or il.check(t_s, wake, xr, x, f, n1, n2, lv, lc, va, late)
            if tr is not None:
                trip = tr
                status = "tripped"
                stopping = True
                stop_k = k + (1 if tr.name in DEVICE_TRIPS else
                              max(1, int(round(hw.interlocks.stop_hold_s / period))))
                out_q.put(("event", t_s, "interlock", tr.as_dict()))
            elif hold_ref is None and (abort_flag.value or stop_req["why"]):
                why = "operator abort" if abort_flag.value else stop_req["why"]
                status = "aborted"
                hold_ref = xr
                hold_until_k = k + max(1, int(round(hw.interlocks.stop_hold_s / period)))
                stop_k = hold_until_k + 1
                out_q.put(("event", t_s, "abort", {"reason": why, "hold_um": xr}))
            elif hold_until_k is not None and k >= hold_until_k:
                stopping = True
        # -- control + write -----------------------------------------------------------
        if stopping or ctl is None:
            cmd = p = i_ = d = dz = 0.0
        else:
            cmd, p, i_, d, dz = _ctl(ctl, xr, x)
        try:
            if stopping:
                va.write(0.0, enable=False)
            else:
                va.write(cmd)
            err_counts["can"] = 0
        except DeviceError as exc:
            err_counts["can"] += 1
            if not stopping:
                tr = il.device_error(t_s, exc, err_counts)
                if tr is not None:
                    trip, status, stopping = tr, "tripped", True
                    stop_k = k + 1
                    out_q.put(("event", t_s, "interlock", tr.as_dict()))
        if stopping and not send_pending:
            send_pending = True
            try:
                va.disable()
            except DeviceError:
                pass
        # -- record -------------------------------------------------------------------
        i = blk.i
        a = blk.a
        a["t_s"][i] = t_s
        a["position_ref_um"][i] = xr
        a["position_um"][i] = x
        a["friction_N"][i] = f
        a["normal_1_N"][i] = n1
        a["normal_2_N"][i] = n2
        a["valve_cmd"][i] = cmd
        a["pid_p"][i] = p
        a["pid_i"][i] = i_
        a["pid_d"][i] = d
        a["dither"][i] = dz
        blk.late[i] = late
        blk.period[i] = wake - prev_wake
        prev_wake = wake
        blk.i = i + 1
        blk.exec[i] = perf() - c0
        if blk.i >= blk.n:
            b, tim = blk.take()
            tim["devices"] = {"lvdt_bad_crc": lv.parser.bad_frames, "lvdt_garbage_bytes": lv.parser.garbage_bytes,
                              "lvdt_lost": lv.parser.lost_frames, "modbus_errors": lc.n_errors,
                              "can_status_frames": va.n_status, "can_send_errors": va.send_errors}
            out_q.put(("block", b, tim))
        skipped = pacer.advance()
        if skipped:
            blk.skipped += skipped
            prev_wake = float("nan")
        if k == n_ticks - 1 and status == "completed":
            stopping = True
            stop_k = k + 1
    # -- safe state -----------------------------------------------------------------------
    try:
        va.write(0.0, enable=False)
        va.disable()
    except DeviceError:
        pass
    if blk.i:
        out_q.put(("block",) + blk.take())
    summary = {"status": status, "ticks": int(pacer.k), "skipped": int(pacer.skipped),
               "lvdt": {"good": lv.parser.good_frames, "bad_crc": lv.parser.bad_frames,
                        "garbage_bytes": lv.parser.garbage_bytes, "lost": lv.parser.lost_frames},
               "modbus": {"reads": lc.n_reads, "errors": lc.n_errors},
               "can": {"status_frames": va.n_status, "send_errors": va.send_errors,
                       "error_frames": va.bus_error_frames},
               "realtime": rt_info}
    if trip is not None:
        summary["trip"] = trip.as_dict()
        summary["message"] = str(trip)
    time.sleep(0.005)
    try:
        va.poll()
    except DeviceError:
        pass
    summary["valve_final"] = {"status_bits": va.status_bits, "enabled": va.enabled,
                              "output": va.output}
    for dev in (lc, lv, va):
        dev.close()
    out_q.put(("done", summary))


def _ctl(ctl, xr, x):
    r = ctl.step(xr, x)
    return r["valve_cmd"], r["pid_p"], r["pid_i"], r["pid_d"], r["dither"]
