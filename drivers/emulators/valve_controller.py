"""Servovalve controller emulator on a python-can bus (:mod:`drivers.valve` frames).

State: enabled / fault / watchdog. The output follows the setpoints while
enabled and not faulted; when no setpoint arrived for ``watchdog_s`` the
controller nulls its output by itself (bit ``ST_WATCHDOG``) until setpoints
resume. Status frames every ``status_period_s`` and after each command.

Faults (``self.faults``): ``fault`` (fault bit set, output nulled, code 0x0101),
``silent`` (no status frames: the host sees a missing heartbeat),
``ignore_setpoints``.
"""

from __future__ import annotations

import time

from drivers.config import ValveConfig
from drivers.valve import (
    CMD_CLEAR_FAULT, CMD_DISABLE, CMD_ENABLE, ST_ENABLED, ST_FAULT, ST_NULL, ST_WATCHDOG,
    command_id, decode_setpoint, encode_status, open_bus, setpoint_id, status_id,
)


class ValveControllerEmulator:
    def __init__(self, cfg: ValveConfig, watchdog_s: float = 0.02, status_period_s: float = 0.01):
        self.cfg = cfg
        self.watchdog_s = watchdog_s
        self.status_period_s = status_period_s
        self.faults: dict = {}
        self.enabled = False
        self.setpoint = 0.0
        self.last_setpoint_t = -1e9
        self.heartbeat = 0
        self._last_status_t = -1e9
        self.n_setpoints = 0
        self.n_commands = 0
        self.bus = None
        self._sp = setpoint_id(cfg.node_id)
        self._cmd = command_id(cfg.node_id)
        self._st = status_id(cfg.node_id)

    def start(self) -> None:
        self.bus = open_bus(self.cfg)

    def stop(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    @property
    def fault(self) -> bool:
        return bool(self.faults.get("fault"))

    def watchdog_tripped(self, now: float) -> bool:
        return now - self.last_setpoint_t > self.watchdog_s

    def output(self, now: float) -> float:
        """What the valve does now: the setpoint, or null (disabled, fault, watchdog)."""
        if not self.enabled or self.fault or self.watchdog_tripped(now):
            return 0.0
        return self.setpoint

    def handle(self, msg, now: float) -> str | None:
        """Process one received frame; returns 'setpoint', 'command' or None."""
        if msg is None or msg.is_error_frame:
            return None
        if msg.arbitration_id == self._sp and len(msg.data) >= 4:
            if self.faults.get("ignore_setpoints"):
                return None
            self.setpoint, _seq, _flags = decode_setpoint(msg.data)
            self.last_setpoint_t = now
            self.n_setpoints += 1
            return "setpoint"
        if msg.arbitration_id == self._cmd and len(msg.data) >= 1:
            self.n_commands += 1
            code = msg.data[0]
            if code == CMD_ENABLE and not self.fault:
                self.enabled = True
            elif code == CMD_DISABLE:
                self.enabled = False
                self.setpoint = 0.0
            elif code == CMD_CLEAR_FAULT:
                self.faults.pop("fault", None)
            self.send_status(now)
            return "command"
        return None

    def status_bits(self, now: float) -> int:
        bits = 0
        if self.enabled:
            bits |= ST_ENABLED
        if self.fault:
            bits |= ST_FAULT
        if self.watchdog_tripped(now):
            bits |= ST_WATCHDOG
        if self.output(now) == 0.0:
            bits |= ST_NULL
        return bits

    def send_status(self, now: float) -> None:
        import can

        self._last_status_t = now
        if self.faults.get("silent") or self.bus is None:
            return
        self.heartbeat = (self.heartbeat + 1) & 0xFF
        data = encode_status(self.status_bits(now), self.heartbeat, self.output(now),
                             0x0101 if self.fault else 0)
        try:
            self.bus.send(can.Message(arbitration_id=self._st, data=data, is_extended_id=False))
        except Exception:  # noqa: BLE001 - a lost frame; the host sees the heartbeat gap
            pass

    def maybe_status(self, now: float) -> None:
        if now - self._last_status_t >= self.status_period_s:
            self.send_status(now)

    def recv(self, timeout: float):
        return self.bus.recv(timeout)


def _now() -> float:
    return time.monotonic()
