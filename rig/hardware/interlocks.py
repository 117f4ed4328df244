"""Interlocks checked every tick of the real-time loop.

Each trip names the interlock, says what happened in words, and carries the
time and the values that tripped it. Any trip sends the loop to the safe
state: valve command nulled, controller disabled (the servovalve controller
also nulls itself when setpoints stop: its watchdog), the actuator then holds
where it is (a nulled servovalve blocks the cylinder's ports).

The interlocks see the process values and each device's
:class:`drivers.device.DeviceHealth` (frames ok/bad/lost, age of the last
data, errors, status and fault bits), never a driver's internals. Devices by
their loop name: ``lvdt`` (position), ``loadcells`` (forces), ``valve``.

Limits (``hardware.interlocks`` of the profile): stroke limits (default: the
profile's stroke; the paper's LVDT and actuator allow 5 mm), friction force
limit, normal force band per rider, stale sensor data, device fault bits and
the devices' own problems (the CANopen valve: foreign or malformed frames,
EMCY, watchdog, heartbeat, a spool that does not follow), CAN errors,
consecutive Modbus and CAN send errors, bad checksums / lost frames / garbage
per second, a run of late cycles, following error scaled with the reference
velocity (LinuxCNC's FERROR / MIN_FERROR), non-finite values (any sensor, the
reference, the controller's output: a ``non_finite`` trip naming the channel).
Every limit is written ``not (value within limit)``, so NaN trips.

The loop's own watches live here too: :class:`TimingWatch` (a stall between two
ticks: ``loop_stall``; skipped cycles per second: ``skipped_cycles``),
:class:`LoggerWatch` (blocks not taken: ``logger_stalled``; no heartbeat from a
dying logger: ``logger_died``) and :func:`session_trip` (the session failed:
``logger_failed``; the parent gone: ``logger_died``). The loop (:mod:`rig.hardware.loop`)
asks them in one place and sends every trip down one path.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Mapping

from drivers.config import InterlockConfig
from drivers.device import DeviceHealth
from drivers.errors import DeviceError

# per device: the names of its trips
STALE_TRIP = {"lvdt": "stale_position", "loadcells": "stale_forces", "valve": "valve_heartbeat",
              "safety": "stale_safety_io"}
FAULT_TRIP = {"lvdt": "lvdt_fault", "loadcells": "loadcell_fault", "valve": "valve_fault"}
ERRORS_TRIP = {"loadcells": "modbus_errors", "valve": "can_bus_errors", "safety": "safety_io_errors"}
# the safety chain's trips (its I/O module's problems): they latch until `rig reset` (rig.hardware.safety)
SAFETY_TRIPS = frozenset({"estop", "hydraulic_pressure"})
# trips after which nothing from the device (or the loop's timing) can be trusted: stop at once (no hold)
DEVICE_TRIPS = frozenset({"device_lost", "modbus_errors", "can_bus_errors", "stale_forces", "stale_position",
                          "valve_heartbeat", "non_finite", "frame_loss", "serial_checksum_errors",
                          "stream_garbage", "loop_stall", "skipped_cycles", "logger_failed", "logger_stalled", "logger_died",
                          "valve_enable", "missed_deadlines", "stale_safety_io", "safety_io_errors"})
# what the per-second counters of a device's health are called in a trip
WINDOW_COUNTERS = (("frames_bad", "max_checksum_errors", "serial_checksum_errors", "frames with a bad checksum"),
                   ("frames_lost", "max_lost_frames", "frame_loss", "lost frames or missed answers"),
                   ("garbage_bytes", "max_garbage_bytes", "stream_garbage", "garbage bytes"))
SENSOR_CHANNELS = ("position_um", "friction_N", "normal_1_N", "normal_2_N")
SENSOR_DEVICE = {"position_um": "lvdt", "friction_N": "loadcells", "normal_1_N": "loadcells",
                 "normal_2_N": "loadcells"}


@dataclass
class Trip:
    name: str
    message: str
    t_s: float
    values: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        vals = ", ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}"
                         for k, v in self.values.items())
        return f"INTERLOCK {self.name} at t={self.t_s:.3f} s: {self.message} ({vals})"


def non_finite(t_s: float, names: tuple, values: tuple, source: str = "") -> Trip | None:
    """A ``non_finite`` trip naming the first of ``names`` whose value is NaN or infinite, else None."""
    for nm, v in zip(names, values):
        if not math.isfinite(v):
            return Trip("non_finite", f"{nm} is {v!r}{(' (' + source + ')') if source else ''}", t_s,
                        {"channel": nm, "value": str(v)})
    return None


class Interlocks:
    def __init__(self, cfg: InterlockConfig, stroke_min_um: float, stroke_max_um: float,
                 heartbeat_timeout_s: float, period_s: float = 1e-3):
        self.cfg = cfg
        self.period_s = period_s
        # stale = older than its limit AND no new data over that many loop ticks, so that a
        # stall of the whole machine (the loop itself late) is not taken for a dead device
        self.stale_ticks = max(2, int(round(cfg.stale_s / period_s)))
        self.stale_s = {"lvdt": cfg.stale_s, "loadcells": cfg.stale_s, "valve": heartbeat_timeout_s}
        self.x_min = cfg.stroke_min_um if cfg.stroke_min_um is not None else stroke_min_um
        self.x_max = cfg.stroke_max_um if cfg.stroke_max_um is not None else stroke_max_um
        self.ferror_per_um_s = cfg.following_error_um / cfg.max_velocity_um_s
        self.late_run = 0
        self._win_t: float | None = None
        self._win0: dict = {}
        self.device_names: dict = {}

    def following_limit_um(self, v_ref_um_s: float) -> float:
        """LinuxCNC's following-error limit: max(MIN_FERROR, FERROR * |v| / v_max) (µm)."""
        lim = self.ferror_per_um_s * abs(v_ref_um_s)
        m = self.cfg.min_following_error_um
        return lim if lim > m else m

    def check(self, t_s: float, now: float, x_ref: float, x: float, f: float, n1: float, n2: float,
              health: Mapping[str, DeviceHealth], late_s: float, v_ref_um_s: float = 0.0) -> Trip | None:
        """The per-tick checks, cheapest and most fundamental first. Every limit is written as
        ``not (value within limit)`` so that NaN trips."""
        c = self.cfg
        # non-finite process values (NaN passes every `>` comparison): name the channel and its device
        s = x + f + n1 + n2 + x_ref + v_ref_um_s
        if s - s != 0.0:
            vals = (x, f, n1, n2)
            for nm, v in zip(SENSOR_CHANNELS, vals):
                if not math.isfinite(v):
                    h = health.get(SENSOR_DEVICE[nm])
                    src = f"from the {h.device} at {h.address}" if h is not None else ""
                    return non_finite(t_s, (nm,), (v,), src)
            return non_finite(t_s, ("position_ref_um", "reference velocity_um_s"), (x_ref, v_ref_um_s),
                              "the reference")
        # deadlines
        if not (late_s <= c.late_threshold_s):
            self.late_run += 1
            if self.late_run >= c.max_consecutive_late:
                return Trip("missed_deadlines",
                            f"{self.late_run} consecutive cycles more than "
                            f"{c.late_threshold_s * 1e3:g} ms late", t_s,
                            {"late_s": late_s, "run": self.late_run})
        else:
            self.late_run = 0
        # what the devices' own checks found (e.g. the servovalve: foreign frames, watchdog, following)
        for name, h in health.items():
            if h.problems:
                code, msg = h.problems[0]
                return Trip(code, msg + (f" (and {len(h.problems) - 1} more)" if len(h.problems) > 1 else ""),
                            t_s, {"device": h.device, "address": h.address,
                                  "problems": [p[0] for p in h.problems]})
        # stale data, faults
        for name, h in health.items():
            limit = self.stale_s.get(name, c.stale_s)
            if not (h.age_s <= limit) and h.polls_since_new >= self.stale_ticks:
                return Trip(STALE_TRIP.get(name, f"stale_{name}"),
                            f"no new data from the {h.device} at {h.address} for {h.age_s * 1e3:.1f} ms",
                            t_s, {"age_s": h.age_s, "limit_s": limit, "polls": h.polls_since_new})
        for name, h in health.items():
            if h.fault:
                return Trip(FAULT_TRIP.get(name, f"{name}_fault"),
                            f"the {h.device} at {h.address} reports a fault (code 0x{h.fault_code:04x})", t_s,
                            {"status": h.status, "fault_code": h.fault_code})
        # link quality per second: bad checksums, lost frames / missed answers, garbage on a stream
        tr = self._windows(t_s, now, health)
        if tr is not None:
            return tr
        va = health.get("valve")
        if va is not None and va.frames_bad:
            return Trip("can_bus_errors", f"{va.frames_bad} bad or foreign CAN frames on {va.address}",
                        t_s, {"error_frames": va.frames_bad})
        # process limits
        if not (self.x_min <= x <= self.x_max):
            return Trip("stroke_limit", f"position {x:.1f} µm outside the stroke "
                        f"[{self.x_min:g}, {self.x_max:g}] µm", t_s,
                        {"position_um": x, "min_um": self.x_min, "max_um": self.x_max})
        if not (abs(f) <= c.friction_max_N):
            return Trip("friction_limit", f"|friction| {abs(f):.1f} N above {c.friction_max_N:g} N",
                        t_s, {"friction_N": f, "limit_N": c.friction_max_N})
        for name, n in (("normal_1", n1), ("normal_2", n2)):
            if not (c.normal_min_N <= n <= c.normal_max_N):
                return Trip("normal_force_band", f"{name} {n:.1f} N outside "
                            f"[{c.normal_min_N:g}, {c.normal_max_N:g}] N", t_s,
                            {f"{name}_N": n, "min_N": c.normal_min_N, "max_N": c.normal_max_N})
        lim = self.following_limit_um(v_ref_um_s)
        if not (abs(x_ref - x) <= lim):
            return Trip("following_error", f"|x_ref - x| = {abs(x_ref - x):.1f} µm above {lim:.1f} µm "
                        f"(at {v_ref_um_s:.1f} µm/s)", t_s,
                        {"position_ref_um": x_ref, "position_um": x, "limit_um": lim, "v_ref_um_s": v_ref_um_s})
        return None

    def _windows(self, t_s: float, now: float, health: Mapping[str, DeviceHealth]) -> Trip | None:
        c = self.cfg
        if self._win_t is None or not (now - self._win_t < 1.0):
            self._win_t = now
            self._win0 = {name: tuple(getattr(h, a) for a, *_ in WINDOW_COUNTERS) for name, h in health.items()}
            return None
        for name, h in health.items():
            base = self._win0.get(name)
            if base is None:
                continue
            for (attr, limit_name, trip, what), b0 in zip(WINDOW_COUNTERS, base):
                if name == "valve" and attr != "frames_lost":
                    continue  # the valve's bad frames trip at once (its problems)
                d = getattr(h, attr) - b0
                limit = getattr(c, limit_name)
                if not (d <= limit):
                    return Trip(trip, f"{d} {what} within 1 s from the {h.device} at {h.address}", t_s,
                                {attr: d, "limit": limit, "device": name})
        return None

    def command(self, t_s: float, cmd: float, p: float, i: float, d: float, dz: float) -> Trip | None:
        """The controller's output and terms must be finite (a NaN set-point would be sent as null)."""
        s = cmd + p + i + d + dz
        if s - s != 0.0:
            return non_finite(t_s, ("valve_cmd", "pid_p", "pid_i", "pid_d", "dither"), (cmd, p, i, d, dz),
                              "the controller's output")
        return None

    def device_error(self, t_s: float, name: str, exc: DeviceError, health: DeviceHealth) -> Trip | None:
        """A DeviceError from device ``name`` this tick: Modbus failures and CAN send errors trip when
        their consecutive count (``health.consecutive_errors``) reaches its limit; anything else
        (a port lost, a bus gone) at once."""
        c = self.cfg
        kind = exc.kind
        if kind == "lost":  # the connection itself is gone: nothing to count, no next answer to wait for
            return Trip("device_lost", str(exc), t_s, {"device": exc.device, "address": exc.address})
        limit = {"loadcells": c.max_modbus_errors, "safety": c.max_modbus_errors,
                 "valve": c.max_can_errors if kind == "bus" else None}.get(name)
        if limit is not None:
            n = health.consecutive_errors
            if n < limit:
                return None
            return Trip(ERRORS_TRIP[name], f"{exc} ({n} consecutive failures)", t_s,
                        {"consecutive": n, "limit": limit})
        return Trip("device_lost", str(exc), t_s, {"device": exc.device, "address": exc.address})


class TimingWatch:
    """The loop's timing. A gap between two ticks over ``stall_event_s`` is a stall (an event), over
    ``stall_trip_s`` a ``loop_stall`` trip; more skipped cycles within one second than
    ``max_skipped_fraction`` of the ticks of a second, a ``skipped_cycles`` trip."""

    def __init__(self, cfg: InterlockConfig, period_s: float):
        self.event_s, self.trip_s = cfg.stall_event_s, cfg.stall_trip_s
        self.max_skip_per_s = cfg.max_skipped_fraction / period_s
        self._win_t: float | None = None
        self._win_skip0 = 0

    def is_stall(self, gap_s: float) -> bool:
        """A gap worth an event (NaN, the first tick: no)."""
        return gap_s > self.event_s

    def stall(self, t_s: float, gap_s: float, skipped: int) -> Trip | None:
        if gap_s <= self.trip_s:
            return None
        return Trip("loop_stall", f"no tick for {gap_s * 1e3:.0f} ms (limit {self.trip_s * 1e3:g} ms)", t_s,
                    {"gap_s": gap_s, "skipped": skipped})

    def skipped(self, t_s: float, now: float, skipped_total: int) -> Trip | None:
        """Called once per tick with the pacer's running count of skipped cycles."""
        if self._win_t is None or not (now - self._win_t < 1.0):
            self._win_t, self._win_skip0 = now, skipped_total
            return None
        ds = skipped_total - self._win_skip0
        if ds <= self.max_skip_per_s:
            return None
        return Trip("skipped_cycles", f"{ds} cycles skipped within {now - self._win_t:.2f} s (limit "
                    f"{self.max_skip_per_s:.0f} per second)", t_s, {"skipped": ds, "limit": self.max_skip_per_s})


class LoggerWatch:
    """The logger (the session, in the parent process): it must take every block within
    ``logger_timeout_s`` of its sending (``logger_stalled``) and beat its heartbeat; a heartbeat older
    than ``logger_heartbeat_s`` while the logger's process is exiting is ``logger_died``."""

    def __init__(self, cfg: InterlockConfig):
        self.timeout_s, self.heartbeat_s = cfg.logger_timeout_s, cfg.logger_heartbeat_s

    def check(self, t_s: float, now: float, sent_t: list, acked: int | None, heartbeat: float | None,
              exiting) -> Trip | None:
        """``sent_t``: when each block was sent; ``acked``: blocks logged (None: not watched);
        ``heartbeat``: the logger's last beat (None: not watched, 0: not started); ``exiting()``: is the
        logger's process exiting (asked only when the heartbeat is late)."""
        if sent_t and acked is not None and acked < len(sent_t) and not (now - sent_t[acked] <= self.timeout_s):
            return Trip("logger_stalled", f"the logger has not taken block {acked + 1} for "
                        f"{(now - sent_t[acked]) * 1e3:.0f} ms", t_s,
                        {"blocks_sent": len(sent_t), "blocks_logged": acked, "timeout_s": self.timeout_s})
        if heartbeat is not None and heartbeat > 0.0 and not (now - heartbeat <= self.heartbeat_s) and exiting():
            return Trip("logger_died", f"no heartbeat from the logger for {(now - heartbeat) * 1e3:.0f} ms "
                        f"(limit {self.heartbeat_s * 1e3:g} ms)", t_s,
                        {"age_s": now - heartbeat, "limit_s": self.heartbeat_s})
        return None


# values of the loop's shared ``abort_flag``: what the session asks for
ABORT_NONE, ABORT_OPERATOR, ABORT_FAIL = 0, 1, 2


def valve_enable_trip(exc: DeviceError, status_bits: int) -> Trip:
    """The valve's explicit start (NMT start, fault reset, enable) failed before the first tick."""
    return Trip("valve_enable", f"{exc}", 0.0, {"status_bits": status_bits})


def pause_trip(t_s: float, held_s: float, limit_s: float) -> Trip | None:
    """An operator's pause held longer than ``max_pause_s``: to the safe state."""
    if held_s <= limit_s:
        return None
    return Trip("pause_timeout", f"paused for {held_s:.1f} s (limit {limit_s:g} s)", t_s,
                {"held_s": held_s, "limit_s": limit_s})


def session_trip(t_s: float, abort_flag: int, signal_name: str | None, parent_gone: bool) -> Trip | None:
    """The session asked for a stop at once (its log failed), or the loop was signalled with its parent
    (the logger) gone."""
    if abort_flag == ABORT_FAIL:
        return Trip("logger_failed", "the session failed (its log): stop at once", t_s, {"abort_flag": ABORT_FAIL})
    if signal_name and parent_gone:
        return Trip("logger_died", "the logger (the parent process) died", t_s, {"signal": signal_name})
    return None
