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
after a process-limit trip, one tick after a device trip) -> end, where the
valve's ``safe_stop()`` confirms it. The end of the plan goes from ``RUN`` to
``SAFE`` for the last tick.

Trial time is the reference's: the reference index advances by one per
executed tick, so across a stall (skipped deadlines) the reference resumes
where it was instead of jumping; each stall is a ``stall`` event, a long one a
``loop_stall`` trip. The session talks to the loop through shared values:
``abort_flag`` (operator abort: hold then safe; session failure, e.g. its log:
safe at once), ``logger_ack`` (blocks logged: ``logger_stalled`` when they stop)
and ``logger_alive`` (the logger's heartbeat: ``logger_died`` when it stops;
PR_SET_PDEATHSIG -> SIGTERM with the parent gone is the same trip).
"""

from __future__ import annotations

import gc
import math
import signal
import time
import traceback
from enum import Enum

import numpy as np

from drivers.config import parse_hardware
from drivers.errors import DeviceError
from rig.control import apply_switches, controller_params_from_profile, controller_step_v, new_controller_state
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


# values of the shared ``abort_flag``: what the session asks for
ABORT_NONE, ABORT_OPERATOR, ABORT_FAIL = 0, 1, 2


def loop_main(hw_dict, profile, x_ref_um, out_q, abort_flag, options=None, logger_ack=None, logger_alive=None):
    """Entry point of the loop process. ``abort_flag``: a shared ``multiprocessing.Value('i')``
    (1: operator abort, hold then safe; 2: the session failed, e.g. its log: safe at once);
    ``logger_ack``: a shared ``Value('q')``, the number of blocks the session has logged;
    ``logger_alive``: a shared ``Value('d')``, the ``time.monotonic()`` of the logger's last heartbeat
    (0: not started)."""
    options = options or {}
    set_process_name("rig-rt-loop")
    set_pdeathsig(signal.SIGTERM)
    stop_req = {"why": None}

    def _term(signum, _frame):
        stop_req["why"] = f"signal {signal.Signals(signum).name}"

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it sets abort_flag
    try:
        _run(hw_dict, profile, np.asarray(x_ref_um, dtype=float), out_q, abort_flag, stop_req, options,
             logger_ack, logger_alive)
    except BaseException as exc:  # noqa: BLE001 - report, never die silently
        out_q.put(("done", {"status": "error", "message": f"{type(exc).__name__}: {exc}",
                            "traceback": traceback.format_exc()}))


def _process_exiting(pid: int) -> bool:
    """Is process ``pid`` gone or dying (PF_EXITING in /proc/PID/stat, zombie)? A killed process is
    marked exiting at once, while the kernel still tears down its memory (~80 ms for the logger)
    before its children get their PR_SET_PDEATHSIG; a merely slow logger is not exiting."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            rest = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return True
    return rest[0] in (b"Z", b"X") or bool(int(rest[6]) & 0x4)  # state, flags & PF_EXITING


def _device_counters(devices) -> dict:
    out = {}
    for d in devices:
        h = d.health()
        out[f"{d.name}_frames_ok"] = h.frames_ok
        out[f"{d.name}_frames_bad"] = h.frames_bad
        out[f"{d.name}_frames_lost"] = h.frames_lost
        out[f"{d.name}_errors"] = h.errors
        gain = getattr(d, "dither_gain_min", None)
        if gain is not None:
            out[f"{d.name}_dither_gain_min"] = gain  # the margin of the valve's dither check (trips < min)
    return out


def _run(hw_dict, profile, x_ref, out_q, abort_flag, stop_req, options, logger_ack=None, logger_alive=None):
    import logging
    import os
    import sys

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported as DeviceError
    sys.setswitchinterval(1e-4)
    hw = parse_hardware(hw_dict)
    rt, ilc = hw.realtime, hw.interlocks
    period = float(options.get("period_s") or profile.loop.dt_s)
    use_ctl = options.get("controller", True)
    cpar = apply_switches(controller_params_from_profile(profile), options.get("switches"))
    ff_N = np.ascontiguousarray(options.get("ff_N", np.empty(0)), dtype=np.float64)  # friction feed-forward per tick
    if ff_N.size and ff_N.size != len(x_ref):
        raise ValueError(f"friction feed-forward has {ff_N.size} ticks, the reference {len(x_ref)}")
    n_ff = int(ff_N.size)
    cst = new_controller_state()
    rig = build_devices(hw)
    devices = rig.all
    pos, forces, valve = rig.position, rig.forces, rig.valve
    il = Interlocks(ilc, float(profile.stroke.min_um), float(profile.stroke.max_um),
                    hw.valve.heartbeat_timeout_s, period)
    mono = time.monotonic
    parent = os.getppid()
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
    # everything compiled and imported before the first tick
    controller_step_v(cpar, cst, float(x_ref[0]), float(x_ref[0]), math.nan, 0.0)
    cst[:] = new_controller_state()
    il.command(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    n_ticks = len(x_ref)
    hold_ticks = max(1, int(round(ilc.stop_hold_s / period)))
    blk = _Block(rt.block_ticks)
    pacer = Pacer(period, rt_info["sched"] == "SCHED_FIFO", rt.spin_s)
    status = "completed"
    trip: Trip | None = None
    mode = Mode.RUN
    hold_ref = 0.0
    hold_ff_k = 0
    hold_end_k = 0
    stop_k = n_ticks

    # the explicit start (NMT start, fault reset, enable; verified by the valve's status PDO); only here,
    # never after a trip
    try:
        valve.start()
    except DeviceError as exc:
        trip = Trip("valve_enable", f"{exc}", 0.0, {"status_bits": valve.final_state()["status_bits"]})
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
    # issue 21 (the log's clock): the wall-clock time of the loop's monotonic clock, taken once at tick 0;
    # every block carries the wall-clock time of its last tick (tim["wall_ns"])
    wall0_ns, mono0 = time.time_ns(), mono()
    perf = time.perf_counter
    if trip is not None:
        status, mode, stop_k = "tripped", Mode.SAFE, 0
        out_q.put(("event", 0.0, "interlock", trip.as_dict()))
    x = pos.position_um
    cmd = p = i_ = d_ = dz = 0.0
    # timing health: a gap between two ticks over stall_event_s is an event, over stall_trip_s a trip;
    # skipped cycles above max_skipped_fraction of the last second trip. The reference index `kr`
    # advances by one per executed tick, so after a stall the reference resumes where it was
    # (no jump): trial time t_s = kr * period is the reference's time.
    stall_ev, stall_trip = ilc.stall_event_s, ilc.stall_trip_s
    win_skip0, win_t = 0, None
    max_skip_per_s = ilc.max_skipped_fraction / period
    last_wake = float("nan")
    prev_skipped = carry_skip = stall_due = 0
    stall_gap = None  # this tick's gap when it is a stall
    # the logger: blocks sent and when; the session acknowledges each block it has logged
    sent_t: list[float] = []
    log_timeout = ilc.logger_timeout_s
    log_hb = ilc.logger_heartbeat_s
    kr = 0
    read_max = [0.0] * len(devices)  # the longest read of each device (s): where a slow tick went
    xr_prev = float(x_ref[0])
    inv_dt = 1.0 / period
    while True:
        k, dl, wake = pacer.wait()
        if kr >= stop_k:
            break
        c0 = perf()
        t_s = kr * period
        # -- read ------------------------------------------------------------------
        dev_trip = None
        ca = c0
        for di, dev in enumerate(devices):
            try:
                dev.read(wake)
            except DeviceError as exc:
                dev_trip = dev_trip or il.device_error(t_s, dev.name, exc, dev.health(wake))
            cb = perf()
            if cb - ca > read_max[di]:
                read_max[di] = cb - ca
            ca = cb
        c1 = ca
        x = pos.position_um
        f, n1, n2 = forces.forces_N
        for dev in devices:
            dev.health(wake)
        # -- update: reference, stop states, interlocks, controller -------------------
        if mode is Mode.HOLD:
            xr = hold_ref
        else:
            xr = float(x_ref[kr]) if kr < n_ticks else float(x_ref[-1])
        v_ref = (xr - xr_prev) * inv_dt if kr else 0.0
        xr_prev = xr
        gap = wake - last_wake
        last_wake = wake
        if mode is not Mode.SAFE:
            tr = dev_trip
            if gap > stall_ev:  # a stall (NaN on the first tick: no); its event goes out after advance()
                stall_due = pacer.due_skips(wake)
                stall_gap = gap
                if tr is None and not (gap <= stall_trip):
                    tr = Trip("loop_stall", f"no tick for {gap * 1e3:.0f} ms (limit {stall_trip * 1e3:g} ms)",
                              t_s, {"gap_s": gap, "skipped": carry_skip + stall_due})
            if tr is None:
                tr = il.check(t_s, wake, xr, x, f, n1, n2, health, wake - dl, v_ref)
            if tr is None and sent_t and logger_ack is not None:
                ack = logger_ack.value
                if ack < len(sent_t) and not (wake - sent_t[ack] <= log_timeout):
                    tr = Trip("logger_stalled", f"the logger has not taken block {ack + 1} for "
                              f"{(wake - sent_t[ack]) * 1e3:.0f} ms", t_s,
                              {"blocks_sent": len(sent_t), "blocks_logged": ack, "timeout_s": log_timeout})
            if tr is None and logger_alive is not None:
                hb = logger_alive.value
                if hb > 0.0 and not (wake - hb <= log_hb) and _process_exiting(parent):
                    tr = Trip("logger_died", f"no heartbeat from the logger for {(wake - hb) * 1e3:.0f} ms "
                              f"(limit {log_hb * 1e3:g} ms)", t_s, {"age_s": wake - hb, "limit_s": log_hb})
            if tr is None:
                if abort_flag.value == ABORT_FAIL:
                    tr = Trip("logger_failed", "the session failed (its log): stop at once", t_s,
                              {"abort_flag": ABORT_FAIL})
                elif stop_req["why"] and os.getppid() != parent:
                    tr = Trip("logger_died", "the logger (the parent process) died", t_s,
                              {"signal": stop_req["why"]})
            if tr is not None:
                trip, status, mode = tr, "tripped", Mode.SAFE
                stop_k = kr + (1 if tr.name in DEVICE_TRIPS else hold_ticks)
                out_q.put(("event", t_s, "interlock", tr.as_dict()))
            elif mode is Mode.RUN and (abort_flag.value or stop_req["why"]):
                status, mode, hold_ref = "aborted", Mode.HOLD, xr
                hold_ff_k = kr  # the feed-forward holds with the reference
                hold_end_k = kr + hold_ticks
                stop_k = hold_end_k + 1
                out_q.put(("event", t_s, "abort", {"reason": "operator abort" if abort_flag.value
                                                   else stop_req["why"], "hold_um": xr}))
            elif mode is Mode.HOLD and kr >= hold_end_k:
                mode = Mode.SAFE
        if mode is Mode.SAFE or not use_ctl:
            cmd = p = i_ = d_ = dz = 0.0
        else:
            ffk = 0.0
            if n_ff:  # held with the reference (hold, stall): the force of the tick the reference is at
                kf = hold_ff_k if mode is Mode.HOLD else kr
                ffk = float(ff_N[kf if kf < n_ff else n_ff - 1])
            cmd, p, i_, d_, dz = controller_step_v(cpar, cst, xr, x, math.nan, ffk)
            s_ = cmd + p + i_ + d_ + dz
            if s_ - s_ != 0.0:  # a non-finite controller output: never sent (the driver would null it)
                tr = il.command(t_s, cmd, p, i_, d_, dz)
                trip, status, mode, stop_k = tr, "tripped", Mode.SAFE, kr + 1
                out_q.put(("event", t_s, "interlock", tr.as_dict()))
                cmd = p = i_ = d_ = dz = 0.0
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
                        trip, status, mode, stop_k = tr, "tripped", Mode.SAFE, kr + 1
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
        blk.period[j] = gap if prev_skipped == 0 else float("nan")
        blk.read[j] = c1 - c0
        blk.i = j + 1
        blk.exec[j] = perf() - c0
        if blk.i >= blk.n:
            b, tim = blk.take()
            tim["wall_ns"] = wall0_ns + int((wake - mono0) * 1e9)  # issue 21: wall clock of its last tick
            tim["devices"] = _device_counters(devices)
            out_q.put(("block", b, tim))
            sent_t.append(mono())
        kr += 1
        now = mono()
        prev_skipped = pacer.advance(now)
        if prev_skipped:
            blk.skipped += prev_skipped
        # the cycles a stall cost: those the previous tick's overrun skipped (they made this gap) and,
        # for a late wake, those already due when this tick woke (skipped by this tick's advance)
        if stall_gap is not None:
            due = min(prev_skipped, stall_due)
            out_q.put(("event", t_s, "stall", {"gap_s": stall_gap, "skipped": carry_skip + due,
                                               "reference_held": True, "wake_monotonic_s": wake}))
            carry_skip = prev_skipped - due
            stall_gap = None
        else:
            carry_skip = prev_skipped
        # skipped cycles within the last second
        if win_t is None or not (now - win_t < 1.0):
            win_t, win_skip0 = now, pacer.skipped
        elif mode is not Mode.SAFE and not (pacer.skipped - win_skip0 <= max_skip_per_s):
            ds = pacer.skipped - win_skip0
            trip, status, mode, stop_k = (Trip("skipped_cycles", f"{ds} cycles skipped within "
                                               f"{now - win_t:.2f} s (limit {max_skip_per_s:.0f} per second)",
                                               t_s, {"skipped": ds, "limit": max_skip_per_s}),
                                          "tripped", Mode.SAFE, kr + 1)
            out_q.put(("event", t_s, "interlock", trip.as_dict()))
        if kr == n_ticks and mode is Mode.RUN:
            mode, stop_k = Mode.SAFE, kr  # end of the plan
    # -- safe state ----------------------------------------------------------------------
    valve.command, valve.enable = 0.0, False
    try:
        valve.write(mono())
    except DeviceError:
        pass
    if trip is not None and trip.name == "logger_died" and os.getppid() != parent:
        # nobody reads the queue any more: never wait for it at exit (only then: cancelling can leave a
        # half-written message in the pipe, which would block a reader that is still there)
        out_q.cancel_join_thread()
    confirmed = False
    try:
        confirmed = valve.safe_stop()
    except DeviceError:
        pass
    if blk.i:
        b, tim = blk.take()
        tim["wall_ns"] = wall0_ns + int((wake - mono0) * 1e9)  # issue 21: wall clock of its last tick
        tim["devices"] = _device_counters(devices)
        out_q.put(("block", b, tim))
    summary = {"status": status, "ticks": int(kr), "skipped": int(pacer.skipped),
               "devices": {d.name: d.health(mono()).as_dict() for d in devices}, "realtime": rt_info,
               "read_max_us_by_device": {d.name: round(m * 1e6, 1) for d, m in zip(devices, read_max)}}
    if trip is not None:
        summary["trip"] = trip.as_dict()
        summary["message"] = str(trip)
    try:
        valve.read(mono())
    except DeviceError:
        pass
    summary["valve_final"] = {**valve.final_state(), "confirmed": confirmed}
    for dev in devices:
        dev.close()
    out_q.put(("done", summary))
