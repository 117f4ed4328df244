"""Interlocks checked every tick of the real-time loop.

Each trip names the interlock, says what happened in words, and carries the
time and the values that tripped it. Any trip sends the loop to the safe
state: valve command nulled, controller disabled (the servovalve controller
also nulls itself when setpoints stop: its watchdog), the actuator then holds
where it is (a nulled servovalve blocks the cylinder's ports).

Limits (``hardware.interlocks`` of the profile): stroke limits (default: the
profile's stroke; the paper's LVDT and actuator allow 5 mm), friction force
limit, normal force band per rider, stale sensor data, valve fault bit or
missing heartbeat, CAN send errors, Modbus exceptions/timeouts, serial
checksum errors in one second, a run of late cycles, following error.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from drivers.config import InterlockConfig


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
        # stale = older than stale_s AND no new data over that many loop ticks, so that a
        # stall of the whole machine (the loop itself late) is not taken for a dead device
        self.stale_ticks = max(2, int(round(cfg.stale_s / period_s)))
        self.x_min = cfg.stroke_min_um if cfg.stroke_min_um is not None else stroke_min_um
        self.x_max = cfg.stroke_max_um if cfg.stroke_max_um is not None else stroke_max_um
        self.hb_timeout = heartbeat_timeout_s
        self.late_run = 0
        self._bad_window_start_t = None
        self._bad_at_window_start = 0

    def check(self, t_s, now, x_ref, x, f, n1, n2, lvdt, loadcells, valve, late_s) -> Trip | None:
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
        # stale data
        a = lvdt.age_s(now)
        if a > c.stale_s and lvdt.polls_since_frame >= self.stale_ticks:
            return Trip("stale_position", f"no LVDT frame from {lvdt.address} for {a * 1e3:.1f} ms",
                        t_s, {"age_s": a, "limit_s": c.stale_s, "polls": lvdt.polls_since_frame,
                              "forces_age_s": loadcells.age_s(now),
                              "forces_reads_since_new": loadcells.reads_since_new})
        a = loadcells.age_s(now)
        if a > c.stale_s and loadcells.reads_since_new >= self.stale_ticks:
            return Trip("stale_forces", f"load-cell sample counter at {loadcells.address} "
                        f"unchanged for {a * 1e3:.1f} ms", t_s, {"age_s": a, "limit_s": c.stale_s})
        # serial checksum errors per second
        bad = lvdt.parser.bad_frames
        if self._bad_window_start_t is None or now - self._bad_window_start_t >= 1.0:
            self._bad_window_start_t = now
            self._bad_at_window_start = bad
        if bad - self._bad_at_window_start > c.max_checksum_errors:
            return Trip("serial_checksum_errors",
                        f"{bad - self._bad_at_window_start} LVDT frames with a bad checksum within 1 s "
                        f"on {lvdt.address}", t_s,
                        {"bad_frames": bad, "limit": c.max_checksum_errors})
        if lvdt.status & 0x03:
            return Trip("lvdt_fault", f"LVDT conditioner reports status 0x{lvdt.status:02x}", t_s,
                        {"status": lvdt.status})
        if loadcells.status & 0x03:
            return Trip("loadcell_fault", f"load-cell conditioner reports status 0x{loadcells.status:04x}",
                        t_s, {"status": loadcells.status})
        # valve
        if valve.fault:
            return Trip("valve_fault", f"servovalve controller at {valve.address} reports a fault "
                        f"(code 0x{valve.fault_code:04x})", t_s,
                        {"status_bits": valve.status_bits, "fault_code": valve.fault_code})
        a = valve.heartbeat_age_s(now)
        if a > self.hb_timeout and valve.polls_since_status >= self.stale_ticks:
            return Trip("valve_heartbeat", f"no status frame from the servovalve controller at "
                        f"{valve.address} for {a * 1e3:.1f} ms", t_s,
                        {"age_s": a, "limit_s": self.hb_timeout})
        if valve.bus_error_frames:
            return Trip("can_bus_errors", f"{valve.bus_error_frames} CAN error frames on {valve.address}",
                        t_s, {"error_frames": valve.bus_error_frames})
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

    def device_error(self, t_s, exc, counters: dict) -> Trip | None:
        """A DeviceError this tick: trips when the consecutive count reaches its limit."""
        c = self.cfg
        dev = getattr(exc, "device", "device")
        kind = getattr(exc, "kind", "io")
        if dev.startswith("load-cell"):
            n = counters.get("modbus", 0)
            if n < c.max_modbus_errors:
                return None
            return Trip("modbus_errors", f"{exc} ({n} consecutive failures)", t_s,
                        {"consecutive": n, "limit": c.max_modbus_errors})
        if dev.startswith("servovalve") and kind == "bus":
            n = counters.get("can", 0)
            if n < c.max_can_errors:
                return None
            return Trip("can_bus_errors", f"{exc} ({n} consecutive failures)", t_s,
                        {"consecutive": n, "limit": c.max_can_errors})
        return Trip("device_lost", str(exc), t_s, {"device": dev,
                                                    "address": getattr(exc, "address", "?")})
