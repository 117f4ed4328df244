"""The 1 kHz real-time loop, in its own process (the GIL: logging and the CLI live elsewhere).

Each tick, in the manner of ros2_control's controller manager (Dupont &
Dunlap 1995, section 3 and Fig. 4):

1. **read**: every device's ``read(now)`` (LVDT frames, the load-cell
   request, the valve's status frames; :mod:`rig.hardware.devices`);
2. **update**: the interlocks over the process values and each device's
   :class:`drivers.device.DeviceHealth`, then the controller
   (:func:`rig.control.controller_step_v`: PID on x_ref - x + 500 Hz dither,
   command = demand / full-scale force);
3. **write**: every device's ``write(now)`` (the valve's setpoint; its enable; the safety chain's
   amplifier enable and tick count);
4. **record**: the tick's row into the block; a full block to the logger.

These are the methods of :class:`RtLoop` (``tick()`` calls them, then ``advance()``); every
trip is defined in :mod:`rig.hardware.interlocks` and goes through ``RtLoop.trip()``, the one
trip path. Tick 0's wall clock (``RtLoop.wall_ns_tick0``, ``time.time_ns()`` at tick 0's
deadline) is taken in ``RtLoop.start()`` and handed to the session in ``loop_start``.

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
PR_SET_PDEATHSIG -> SIGTERM with the parent gone is the same trip) and
``pause_req`` (the operator's pause: the reference comes from
:class:`trajectories.pause.PausableReference`, held at the plan's next safe point,
run up 5 L on resume; ``pause_timeout`` after ``max_pause_s``).
"""

from __future__ import annotations

import gc
import math
import os
import signal
import time
import traceback
from enum import Enum

import numpy as np

from drivers.config import parse_hardware
from drivers.device import DitherChecked
from drivers.errors import DeviceError
from rig.control import apply_switches, controller_params_from_profile, controller_step_v, new_controller_state
from rig.hardware.devices import build_devices, wait_for_data
from rig.hardware.interlocks import (
    ABORT_FAIL, ABORT_NONE, ABORT_OPERATOR, DEVICE_TRIPS, SAFETY_TRIPS, Interlocks, LoggerWatch, TimingWatch, Trip,
    pause_trip, session_trip, valve_enable_trip,
)
from rig.hardware.safety import latched_message, write_latch
from rig.hardware.timing import Pacer, set_pdeathsig, set_process_name, setup_realtime
from trajectories.pause import PausableReference

BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N",
              "valve_cmd", "pid_p", "pid_i", "pid_d", "dither")
N_KEYS = len(BLOCK_KEYS)

__all__ = ["ABORT_FAIL", "ABORT_NONE", "ABORT_OPERATOR", "BLOCK_KEYS", "Mode", "RtLoop", "loop_main"]


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
        self.skips: list[tuple[float, int]] = []  # (CLOCK_MONOTONIC at the late tick's end, cycles skipped)

    def take(self):
        i = self.i
        blk = {k: self.rows[r, :i].copy() for r, k in enumerate(BLOCK_KEYS)}
        tim = {"late_s": self.late[:i].copy(), "period_s": self.period[:i].copy(),
               "exec_s": self.exec[:i].copy(), "read_s": self.read[:i].copy(), "skipped": self.skipped,
               "skips": self.skips}
        self.i = 0
        self.skipped = 0
        self.skips = []
        return blk, tim


def loop_main(hw_dict, profile, x_ref_um, out_q, abort_flag, options=None, logger_ack=None, logger_alive=None,
              pause_req=None):
    """Entry point of the loop process. ``abort_flag``: a shared ``multiprocessing.Value('i')``
    (1: operator abort, hold then safe; 2: the session failed, e.g. its log: safe at once);
    ``logger_ack``: a shared ``Value('q')``, the number of blocks the session has logged;
    ``logger_alive``: a shared ``Value('d')``, the ``time.monotonic()`` of the logger's last heartbeat
    (0: not started); ``pause_req``: a shared ``Value('i')``, 1 while the operator asks for a pause."""
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
             logger_ack, logger_alive, pause_req)
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
        gain = d.dither_gain_min if isinstance(d, DitherChecked) else None
        if gain is not None:
            out[f"{d.name}_dither_gain_min"] = gain  # the margin of the valve's dither check (trips < min)
    return out


def _run(hw_dict, profile, x_ref, out_q, abort_flag, stop_req, options, logger_ack=None, logger_alive=None,
         pause_req=None):
    """Connect, run every tick, end in the safe state; everything it has to say goes to ``out_q``."""
    import logging
    import sys

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported as DeviceError
    sys.setswitchinterval(1e-4)
    loop = RtLoop(parse_hardware(hw_dict), profile, x_ref, out_q, abort_flag, stop_req, options,
                  logger_ack, logger_alive, pause_req=pause_req)
    if not loop.connect():
        return
    loop.start()
    while loop.tick():
        pass
    loop.finish()


class RtLoop:
    """The real-time loop over the rig's devices (see the module docstring): :meth:`connect`,
    :meth:`start`, then :meth:`tick` (``read`` -> ``update`` -> ``write`` -> ``record`` -> ``advance``)
    until it says the run is over, then :meth:`finish` (the safe state, confirmed by the valve).
    Every trip goes through :meth:`trip`."""

    def __init__(self, hw, profile, x_ref, out_q, abort_flag, stop_req, options, logger_ack=None,
                 logger_alive=None, devices=None, clock=None, pause_req=None):
        """``devices``: a :class:`rig.hardware.devices.RigDevices` (default: the profile's); ``clock``: a
        simulated clock (:class:`rig.hardware.fake.FakeClock`: no real-time setup, no sleeping)."""
        self.hw, self.out_q, self.abort_flag, self.stop_req = hw, out_q, abort_flag, stop_req
        self.logger_ack, self.logger_alive = logger_ack, logger_alive
        ilc = hw.interlocks
        self.period = float(options.get("period_s") or profile.loop.dt_s)
        self.inv_dt = 1.0 / self.period
        self.use_ctl = options.get("controller", True)
        self.cpar = apply_switches(controller_params_from_profile(profile), options.get("switches"))
        self.ff_N = np.ascontiguousarray(options.get("ff_N", np.empty(0)), dtype=np.float64)  # per tick
        if self.ff_N.size and self.ff_N.size != len(x_ref):
            raise ValueError(f"friction feed-forward has {self.ff_N.size} ticks, the reference {len(x_ref)}")
        self.n_ff = int(self.ff_N.size)
        self.cst = new_controller_state()
        self.rig = devices if devices is not None else build_devices(hw)
        self.fake_clock = clock
        self.clock = clock if clock is not None else time.monotonic
        self.devices = self.rig.all
        self.pos, self.forces, self.valve = self.rig.position, self.rig.forces, self.rig.valve
        self.safety = self.rig.safety  # the safety chain's I/O (None: the profile has none)
        if self.safety is not None and options.get("safety_link") is not None:
            self.safety.attach(*options["safety_link"])  # its link process, started by the session's side
        self.il = Interlocks(ilc, float(profile.stroke.min_um), float(profile.stroke.max_um),
                             hw.valve.heartbeat_timeout_s, self.period)
        self.timing = TimingWatch(ilc, self.period)
        self.logger = LoggerWatch(ilc)
        self.parent = os.getppid()
        self.x_ref = x_ref
        self.n_ticks = len(x_ref)
        # the reference tick by tick, with the operator's pauses (held at the plan's next safe point, a
        # run-up of runup_um at the segment's velocity on resume)
        self.ref = PausableReference(x_ref, self.period, options.get("safe_ticks", ()), options.get("runup_um", 0.0),
                                     (self.il.x_min, self.il.x_max))
        self.pause_req = pause_req
        self._pause_seen = 0
        self.max_pause_s = ilc.max_pause_s
        self.hold_ticks = max(1, int(round(ilc.stop_hold_s / self.period)))
        self.blk = _Block(hw.realtime.block_ticks)
        self.status = "completed"
        self.trip_: Trip | None = None
        self.mode = Mode.RUN
        self.hold_ref = 0.0
        self.hold_ff_k = self.hold_end_k = 0
        self.stop_k = 1 << 62  # the plan's end (or a trip, a stop) sets it
        self.kr = 0  # the reference index: +1 per executed tick (a stall holds the reference; t_s = kr * period)
        self.sent_t: list[float] = []  # when each block went to the logger
        self.read_max = [0.0] * len(self.devices)  # the longest read of each device (s)
        self.x = self.f = self.n1 = self.n2 = 0.0
        self.cmd = self.p = self.i_ = self.d_ = self.dz = 0.0
        self.xr = self.xr_prev = float(x_ref[0])
        self.last_wake = math.nan
        self.gap = math.nan
        self.prev_skipped = self.carry_skip = self.stall_due = 0
        self.stall_gap: float | None = None  # this tick's gap when it is a stall
        self.dev_trip: Trip | None = None
        self.wall_ns_tick0: int | None = None  # time.time_ns() at tick 0's deadline (see start())

    # -- before the first tick ----------------------------------------------------------------------
    def connect(self) -> bool:
        """Connect every device and wait for its first data; False (and a ``done`` message naming every
        device that did not answer) when any failed."""
        mono = self.clock
        latched = latched_message(self.hw.safety) if self.safety is not None else None
        if latched:
            self.out_q.put(("done", {"status": "error", "message": latched, "safety_latched": True}))
            return False
        failed: list[DeviceError] = []
        for dev in self.devices:
            try:
                dev.connect()
            except DeviceError as exc:
                failed.append(exc)
        if not failed:
            try:
                wait_for_data(self.devices, max(0.5, 4 * self.hw.valve.heartbeat_timeout_s), mono)
            except DeviceError as exc:
                failed.append(exc)
        if failed:
            for d in self.devices:
                d.close()
            self.out_q.put(("done", {"status": "error", "message": "; ".join(map(str, failed)),
                                     "devices_failed": [{"device": e.device, "address": e.address} for e in failed]}))
            return False
        self.health = {d.name: d.health(mono()) for d in self.devices}  # updated in place by d.health(now)
        return True

    def start(self) -> None:
        """Real-time setup, everything compiled, the valve's explicit start, then tick 0's deadline."""
        rt, fake = self.hw.realtime, self.fake_clock
        self.rt_info = setup_realtime(rt.sched_fifo, rt.priority, rt.cpu) if fake is None else \
            {"sched": "simulated clock", "priority": 0, "note": ""}
        self.out_q.put(("info", {"realtime": self.rt_info, "period_s": self.period,
                                 "devices": {d.name: d.address for d in self.devices}}))
        controller_step_v(self.cpar, self.cst, self.xr, self.xr, math.nan, 0.0)  # compiled before the first tick
        self.cst[:] = new_controller_state()
        self.il.command(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.pacer = Pacer(self.period, self.rt_info["sched"] == "SCHED_FIFO", rt.spin_s) if fake is None else \
            Pacer(self.period, True, 0.0, clock=fake, sleep=fake.sleep)
        # the explicit start (NMT start, fault reset, enable; verified by the valve's status PDO): only
        # here, never after a trip
        start_trip = None
        try:
            self.valve.start()
        except DeviceError as exc:
            start_trip = valve_enable_trip(exc, self.valve.final_state()["status_bits"])
        for d in self.devices:  # drain what arrived while enabling; staleness counts from here
            try:
                d.read(self.clock())
            except DeviceError:
                pass
        # the cyclic GC would scan every object numba/numpy/pydantic created (tens of ms):
        # freeze what exists and switch it off; the loop makes (almost) no reference cycles
        gc.collect()
        gc.freeze()
        gc.disable()
        self.pacer.start()
        # THE WALL CLOCK OF TICK 0: tick k's deadline is pacer.t0 + k * period on CLOCK_MONOTONIC; its
        # wall-clock time is wall_ns_tick0 + k * period (handed to the session in ``loop_start``)
        self.wall_ns_tick0 = time.time_ns() + int(round((self.pacer.t0 - self.clock()) * 1e9))
        self.out_q.put(("event", 0.0, "loop_start", {"sched": self.rt_info["sched"], "note": self.rt_info["note"],
                                                     "wall_ns_tick0": self.wall_ns_tick0}))
        if start_trip is not None:
            self.trip(start_trip)
            self.stop_k = 0
        self.x = self.pos.position_um

    # -- one tick ----------------------------------------------------------------------------------
    def tick(self) -> bool:
        """Wait for the next deadline and run one tick; False once the run is over."""
        _k, dl, wake = self.pacer.wait()
        if self.kr >= self.stop_k:
            return False
        c0 = time.perf_counter()
        self.read(wake)
        c1 = time.perf_counter()
        self.update(wake, dl)
        self.write(wake)
        self.record(wake, dl, c0, c1)
        self.advance()
        return True

    def read(self, wake: float) -> None:
        """Every device's ``read``; a DeviceError is judged by the interlocks in :meth:`update`."""
        perf = time.perf_counter
        self.dev_trip = None
        t_s = self.kr * self.period
        ca = perf()
        for di, dev in enumerate(self.devices):
            try:
                dev.read(wake)
            except DeviceError as exc:
                self.dev_trip = self.dev_trip or self.il.device_error(t_s, dev.name, exc, dev.health(wake))
            cb = perf()
            if cb - ca > self.read_max[di]:
                self.read_max[di] = cb - ca
            ca = cb
        self.x = self.pos.position_um
        self.f, self.n1, self.n2 = self.forces.forces_N
        for dev in self.devices:
            dev.health(wake)

    def update(self, wake: float, deadline: float) -> None:
        """The reference, the stop states, the interlocks, the controller."""
        kr, t_s = self.kr, self.kr * self.period
        if self.mode is Mode.HOLD:
            xr = self.hold_ref
        else:
            xr = self.reference(t_s)
        v_ref = (xr - self.xr_prev) * self.inv_dt if kr else 0.0
        self.xr = self.xr_prev = xr
        self.gap = wake - self.last_wake
        self.last_wake = wake
        if self.mode is not Mode.SAFE:
            tr = self.check(t_s, wake, deadline, v_ref)
            if tr is not None:
                self.trip(tr)
            elif self.mode is Mode.RUN and (self.abort_flag.value or self.stop_req["why"]):
                self.status, self.mode, self.hold_ref = "aborted", Mode.HOLD, xr
                self.hold_ff_k = max(0, self.ref.k_plan - 1)  # the feed-forward holds with the reference
                self.hold_end_k = kr + self.hold_ticks
                self.stop_k = self.hold_end_k + 1
                self.out_q.put(("event", t_s, "abort", {"reason": "operator abort" if self.abort_flag.value
                                                        else self.stop_req["why"], "hold_um": xr}))
            elif self.mode is Mode.HOLD and kr >= self.hold_end_k:
                self.mode = Mode.SAFE
        self.control(t_s)

    def reference(self, t_s: float) -> float:
        """This tick's reference from the pausable plan; the operator's pause requests; their events."""
        ref = self.ref
        pr = self.pause_req
        if pr is not None and pr.value != self._pause_seen:
            self._pause_seen = pr.value
            if self._pause_seen:
                ref.request_pause()
            else:
                ref.request_resume()
        xr = ref.next()
        if ref.events:
            for k, kind, data in ref.events:
                self.out_q.put(("event", k * self.period, kind, data))
            ref.events.clear()
        return xr

    def check(self, t_s: float, wake: float, deadline: float, v_ref: float) -> Trip | None:
        """Every interlock of this tick (:mod:`rig.hardware.interlocks`), first trip wins."""
        tr = self.dev_trip
        gap = self.gap
        if self.timing.is_stall(gap):  # its event goes out after advance()
            self.stall_due = self.pacer.due_skips(wake)
            self.stall_gap = gap
            tr = tr or self.timing.stall(t_s, gap, self.carry_skip + self.stall_due)
        if tr is None:
            tr = self.il.check(t_s, wake, self.xr, self.x, self.f, self.n1, self.n2, self.health, wake - deadline,
                               v_ref)
        if tr is None:
            ack = self.logger_ack.value if self.logger_ack is not None else None
            hb = self.logger_alive.value if self.logger_alive is not None else None
            tr = self.logger.check(t_s, wake, self.sent_t, ack, hb, lambda: _process_exiting(self.parent))
        if tr is None and self.ref.hold_ticks:
            tr = pause_trip(t_s, self.ref.hold_s, self.max_pause_s)
        if tr is None:
            why = self.stop_req["why"]
            tr = session_trip(t_s, self.abort_flag.value, why, bool(why) and os.getppid() != self.parent)
        return tr

    def control(self, t_s: float) -> None:
        if self.mode is Mode.SAFE or not self.use_ctl:
            self.cmd = self.p = self.i_ = self.d_ = self.dz = 0.0
            return
        ffk = 0.0
        if self.n_ff:  # held with the reference (hold, stall, pause): the force of the plan's tick
            kf = self.hold_ff_k if self.mode is Mode.HOLD else max(0, self.ref.k_plan - 1)
            ffk = float(self.ff_N[kf if kf < self.n_ff else self.n_ff - 1])
        cmd, p, i_, d_, dz = controller_step_v(self.cpar, self.cst, self.xr, self.x, math.nan, ffk)
        s_ = cmd + p + i_ + d_ + dz
        if s_ - s_ != 0.0:  # a non-finite controller output: never sent (the driver would null it)
            self.trip(self.il.command(t_s, cmd, p, i_, d_, dz))
            cmd = p = i_ = d_ = dz = 0.0
        self.cmd, self.p, self.i_, self.d_, self.dz = cmd, p, i_, d_, dz

    def write(self, wake: float) -> None:
        """The valve's set-point (nulled and disabled in SAFE); every device's ``write``."""
        valve = self.valve
        valve.command = self.cmd
        valve.enable = self.mode is not Mode.SAFE
        if self.safety is not None:
            self.safety.enable = valve.enable  # the amplifier's enable follows the valve's
        for dev in self.devices:
            try:
                dev.write(wake)
            except DeviceError as exc:
                if self.mode is not Mode.SAFE:
                    tr = self.il.device_error(self.kr * self.period, dev.name, exc, dev.health(wake))
                    if tr is not None:
                        self.trip(tr)

    def record(self, wake: float, deadline: float, c0: float, c1: float) -> None:
        """This tick's row and timing into the block; a full block goes to the logger."""
        blk = self.blk
        j = blk.i
        r = blk.rows
        r[0, j] = self.kr * self.period
        r[1, j] = self.xr
        r[2, j] = self.x
        r[3, j] = self.f
        r[4, j] = self.n1
        r[5, j] = self.n2
        r[6, j] = self.cmd
        r[7, j] = self.p
        r[8, j] = self.i_
        r[9, j] = self.d_
        r[10, j] = self.dz
        blk.late[j] = wake - deadline
        blk.period[j] = self.gap if self.prev_skipped == 0 else float("nan")
        blk.read[j] = c1 - c0
        blk.i = j + 1
        blk.exec[j] = time.perf_counter() - c0
        if blk.i >= blk.n:
            self.send_block()
            self.sent_t.append(self.clock())

    def advance(self) -> None:
        """To the next tick: skipped deadlines, the stall's event, the skipped-cycles watch, the plan's end."""
        t_s = self.kr * self.period
        wake = self.last_wake
        self.kr += 1
        now = self.clock()
        self.prev_skipped = self.pacer.advance(now)
        if self.prev_skipped:
            self.blk.skipped += self.prev_skipped
            self.blk.skips.append((now, self.prev_skipped))
        # the cycles a stall cost: those the previous tick's overrun skipped (they made this gap) and,
        # for a late wake, those already due when this tick woke (skipped by this tick's advance)
        if self.stall_gap is not None:
            due = min(self.prev_skipped, self.stall_due)
            self.out_q.put(("event", t_s, "stall", {"gap_s": self.stall_gap, "skipped": self.carry_skip + due,
                                                    "reference_held": True, "wake_monotonic_s": wake}))
            self.carry_skip = self.prev_skipped - due
            self.stall_gap = None
        else:
            self.carry_skip = self.prev_skipped
        tr = self.timing.skipped(t_s, now, self.pacer.skipped)
        if tr is not None and self.mode is not Mode.SAFE:
            self.trip(tr)
        if self.mode is Mode.RUN and self.ref.done:
            self.mode, self.stop_k = Mode.SAFE, self.kr  # end of the plan

    # -- the one trip path ----------------------------------------------------------------------------
    def trip(self, tr: Trip) -> None:
        """Any interlock: to SAFE (valve nulled and disabled from this tick's write on). The sensors are
        logged for ``stop_hold_s`` after a process-limit trip, for one more tick after a device trip
        (nothing from the devices or the loop's timing can be trusted then); the first trip is kept."""
        if self.trip_ is None:
            self.trip_ = tr
        self.status, self.mode = "tripped", Mode.SAFE
        self.stop_k = self.kr + (1 if tr.name in DEVICE_TRIPS else self.hold_ticks)
        self.out_q.put(("event", tr.t_s, "interlock", tr.as_dict()))

    # -- after the last tick -----------------------------------------------------------------------
    def send_block(self) -> None:
        b, tim = self.blk.take()
        # the log's clock (issue 21): the wall-clock time of the block's LAST tick, from its wake on the
        # monotonic clock (after a stall this is later than wall_ns_tick0 + t_s: the reference was held)
        if self.wall_ns_tick0 is not None and self.last_wake == self.last_wake:
            tim["wall_ns"] = self.wall_ns_tick0 + int(round((self.last_wake - self.pacer.t0) * 1e9))
        tim["devices"] = _device_counters(self.devices)
        self.out_q.put(("block", b, tim))

    def finish(self) -> None:
        """Null and disable the valve and wait for its confirmation; the last block; the summary."""
        valve, mono = self.valve, self.clock
        valve.command, valve.enable = 0.0, False
        try:
            valve.write(mono())
        except DeviceError:
            pass
        trip = self.trip_
        if trip is not None and trip.name == "logger_died" and os.getppid() != self.parent:
            # nobody reads the queue any more: never wait for it at exit (only then: cancelling can leave a
            # half-written message in the pipe, which would block a reader that is still there)
            self.out_q.cancel_join_thread()
        confirmed = False
        try:
            confirmed = valve.safe_stop()
        except DeviceError:
            pass
        safety_final = None
        if self.safety is not None:
            off = self.safety.safe_stop()
            safety_final = {"enable_output_off": off, "state": self.safety.describe()}
            if trip is not None and trip.name in SAFETY_TRIPS:
                safety_final["latch"] = str(write_latch(self.hw.safety, trip.as_dict()))
        if self.blk.i:
            self.send_block()
        summary = {"status": self.status, "ticks": int(self.kr), "skipped": int(self.pacer.skipped),
                   "devices": {d.name: d.health(mono()).as_dict() for d in self.devices}, "realtime": self.rt_info,
                   "read_max_us_by_device": {d.name: round(m * 1e6, 1) for d, m in zip(self.devices, self.read_max)},
                   "wall_ns_tick0": self.wall_ns_tick0}
        if trip is not None:
            summary["trip"] = trip.as_dict()
            summary["message"] = str(trip)
        try:
            valve.read(mono())
        except DeviceError:
            pass
        summary["valve_final"] = {**valve.final_state(), "confirmed": confirmed}
        if safety_final is not None:
            summary["safety_final"] = safety_final
        for dev in self.devices:
            dev.close()
        gc.enable()  # (the loop process ends here; an in-process test goes on)
        self.out_q.put(("done", summary))
