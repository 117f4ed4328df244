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
limit, normal force band per rider, stale sensor data, device fault bits,
missing valve heartbeat, CAN error frames, consecutive Modbus and CAN send
errors, serial checksum errors in one second, a run of late cycles,
following error.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Mapping

from drivers.config import InterlockConfig
from drivers.device import DeviceHealth
from drivers.errors import DeviceError

# per device: the names of its trips
STALE_TRIP = {"lvdt": "stale_position", "loadcells": "stale_forces", "valve": "valve_heartbeat"}
FAULT_TRIP = {"lvdt": "lvdt_fault", "loadcells": "loadcell_fault", "valve": "valve_fault"}
ERRORS_TRIP = {"loadcells": "modbus_errors", "valve": "can_bus_errors"}
# trips after which nothing from the device can be trusted: stop at once (no hold)
DEVICE_TRIPS = frozenset({"device_lost", "modbus_errors", "can_bus_errors", "stale_forces", "stale_position",
                          "valve_heartbeat"})


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


class Interlocks:
    def __init__(self, cfg: InterlockConfig, stroke_min_um: float, stroke_max_um: float,
                 heartbeat_timeout_s: float, period_s: float = 1e-3):
        self.cfg = cfg
        # stale = older than its limit AND no new data over that many loop ticks, so that a
        # stall of the whole machine (the loop itself late) is not taken for a dead device
        self.stale_ticks = max(2, int(round(cfg.stale_s / period_s)))
        self.stale_s = {"lvdt": cfg.stale_s, "loadcells": cfg.stale_s, "valve": heartbeat_timeout_s}
        self.x_min = cfg.stroke_min_um if cfg.stroke_min_um is not None else stroke_min_um
        self.x_max = cfg.stroke_max_um if cfg.stroke_max_um is not None else stroke_max_um
        self.late_run = 0
        self._bad_window_start_t = None
        self._bad_at_window_start = 0

    def check(self, t_s: float, now: float, x_ref: float, x: float, f: float, n1: float, n2: float,
              health: Mapping[str, DeviceHealth], late_s: float) -> Trip | None:
        c = self.cfg
        # deadlines
        if late_s > c.late_threshold_s:
            self.late_run += 1
            if self.late_run >= c.max_consecutive_late:
                return Trip("missed_deadlines",
                            f"{self.late_run} consecutive cycles more than "
                            f"{c.late_threshold_s * 1e3:g} ms late", t_s,
                            {"late_s": late_s, "run": self.late_run})
        else:
            self.late_run = 0
        # stale data, faults
        for name, h in health.items():
            limit = self.stale_s.get(name, c.stale_s)
            if h.age_s > limit and h.polls_since_new >= self.stale_ticks:
                return Trip(STALE_TRIP.get(name, f"stale_{name}"),
                            f"no new data from the {h.device} at {h.address} for {h.age_s * 1e3:.1f} ms",
                            t_s, {"age_s": h.age_s, "limit_s": limit, "polls": h.polls_since_new})
        for name, h in health.items():
            if h.fault:
                return Trip(FAULT_TRIP.get(name, f"{name}_fault"),
                            f"the {h.device} at {h.address} reports a fault (code 0x{h.fault_code:04x})", t_s,
                            {"status": h.status, "fault_code": h.fault_code})
        # serial checksum errors per second (the LVDT stream)
        lv = health.get("lvdt")
        if lv is not None:
            bad = lv.frames_bad
            if self._bad_window_start_t is None or now - self._bad_window_start_t >= 1.0:
                self._bad_window_start_t = now
                self._bad_at_window_start = bad
            if bad - self._bad_at_window_start > c.max_checksum_errors:
                return Trip("serial_checksum_errors",
                            f"{bad - self._bad_at_window_start} frames with a bad checksum within 1 s "
                            f"from the {lv.device} at {lv.address}", t_s,
                            {"bad_frames": bad, "limit": c.max_checksum_errors})
        va = health.get("valve")
        if va is not None and va.frames_bad:
            return Trip("can_bus_errors", f"{va.frames_bad} CAN error frames on {va.address}",
                        t_s, {"error_frames": va.frames_bad})
        # process limits
        if x < self.x_min or x > self.x_max:
            return Trip("stroke_limit", f"position {x:.1f} µm outside the stroke "
                        f"[{self.x_min:g}, {self.x_max:g}] µm", t_s,
                        {"position_um": x, "min_um": self.x_min, "max_um": self.x_max})
        if abs(f) > c.friction_max_N:
            return Trip("friction_limit", f"|friction| {abs(f):.1f} N above {c.friction_max_N:g} N",
                        t_s, {"friction_N": f, "limit_N": c.friction_max_N})
        for name, n in (("normal_1", n1), ("normal_2", n2)):
            if not (c.normal_min_N <= n <= c.normal_max_N):
                return Trip("normal_force_band", f"{name} {n:.1f} N outside "
                            f"[{c.normal_min_N:g}, {c.normal_max_N:g}] N", t_s,
                            {f"{name}_N": n, "min_N": c.normal_min_N, "max_N": c.normal_max_N})
        if c.max_following_error_um is not None and abs(x_ref - x) > c.max_following_error_um:
            return Trip("following_error", f"|x_ref - x| = {abs(x_ref - x):.1f} µm above "
                        f"{c.max_following_error_um:g} µm", t_s,
                        {"position_ref_um": x_ref, "position_um": x})
        return None

    def device_error(self, t_s: float, name: str, exc: DeviceError, health: DeviceHealth) -> Trip | None:
        """A DeviceError from device ``name`` this tick: Modbus failures and CAN send errors trip when
        their consecutive count (``health.consecutive_errors``) reaches its limit; anything else
        (a port lost, a bus gone) at once."""
        c = self.cfg
        kind = exc.kind
        limit = {"loadcells": c.max_modbus_errors, "valve": c.max_can_errors if kind == "bus" else None}.get(name)
        if limit is not None:
            n = health.consecutive_errors
            if n < limit:
                return None
            return Trip(ERRORS_TRIP[name], f"{exc} ({n} consecutive failures)", t_s,
                        {"consecutive": n, "limit": limit})
        return Trip("device_lost", str(exc), t_s, {"device": exc.device, "address": exc.address})
