"""Servovalve controller on CAN (python-can).

Frames (11-bit ids, ``n`` = ``node_id``; multi-byte fields little-endian):

==========  ======  =============================================================
id          dlc     content
==========  ======  =============================================================
0x200 + n   4       setpoint, sent every tick: int16 command (+-32767 = +-1.0
                    full-scale spool), uint8 sequence, uint8 flags (bit0 enable)
0x100 + n   2       command: byte0 = 0x01 enable, 0x02 disable, 0x03 clear fault
0x180 + n   6       status (controller -> host, every 10 ms and after a command):
                    byte0 bits (bit0 enabled, bit1 fault, bit2 watchdog nulled,
                    bit3 output at null), byte1 heartbeat counter (+1 each frame),
                    int16 actual spool output, uint16 fault code
==========  ======  =============================================================

The controller nulls its output by itself when setpoints stop (watchdog), so a
dead host cannot leave the valve open. The host trips when the status shows a
fault or when no status arrived within ``heartbeat_timeout_s``.
"""

from __future__ import annotations

import struct
import time

from drivers.config import ValveConfig
from drivers.errors import DeviceError

DEVICE = "servovalve controller"
CMD_ENABLE, CMD_DISABLE, CMD_CLEAR_FAULT = 0x01, 0x02, 0x03
ST_ENABLED, ST_FAULT, ST_WATCHDOG, ST_NULL = 0x01, 0x02, 0x04, 0x08
FULL_SCALE = 32767


def setpoint_id(node: int) -> int:
    return 0x200 + node


def command_id(node: int) -> int:
    return 0x100 + node


def status_id(node: int) -> int:
    return 0x180 + node


def encode_setpoint(cmd: float, seq: int, enable: bool = True) -> bytes:
    v = int(round(max(-1.0, min(1.0, cmd)) * FULL_SCALE))
    return struct.pack("<hBB", v, seq & 0xFF, 1 if enable else 0)


def decode_setpoint(data: bytes) -> tuple[float, int, int]:
    v, seq, flags = struct.unpack("<hBB", bytes(data[:4]))
    return v / FULL_SCALE, seq, flags


def encode_status(bits: int, heartbeat: int, output: float, fault_code: int = 0) -> bytes:
    v = int(round(max(-1.0, min(1.0, output)) * FULL_SCALE))
    return struct.pack("<BBhH", bits & 0xFF, heartbeat & 0xFF, v, fault_code & 0xFFFF)


def decode_status(data: bytes) -> tuple[int, int, float, int]:
    bits, hb, v, code = struct.unpack("<BBhH", bytes(data[:6]))
    return bits, hb, v / FULL_SCALE, code


def open_bus(cfg: ValveConfig):
    import can

    kwargs = {"interface": cfg.interface, "channel": cfg.channel}
    if cfg.interface == "udp_multicast" and cfg.port:
        kwargs["port"] = cfg.port
    if cfg.interface == "virtual":
        kwargs["receive_own_messages"] = False
    return can.Bus(**kwargs)


class ValveController:
    """Host side of the valve controller: setpoints, enable/disable, status."""

    def __init__(self, cfg: ValveConfig):
        self.cfg = cfg
        self.address = cfg.address_text
        self._bus = None
        self._seq = 0
        self._sp_id = setpoint_id(cfg.node_id)
        self._cmd_id = command_id(cfg.node_id)
        self._st_id = status_id(cfg.node_id)
        self.status_bits = 0
        self.heartbeat = -1
        self.output = 0.0
        self.fault_code = 0
        self.last_status_t = 0.0
        self.n_status = 0
        self.send_errors = 0
        self.consecutive_send_errors = 0
        self.bus_error_frames = 0
        self.polls_since_status = 0

    def connect(self) -> None:
        try:
            self._bus = open_bus(self.cfg)
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(DEVICE, self.address, f"cannot open CAN bus: {exc}") from exc
        self.last_status_t = time.monotonic()

    def close(self) -> None:
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:  # noqa: BLE001
                pass
            self._bus = None

    def _send(self, arb_id: int, data: bytes) -> None:
        import can

        if self._bus is None:
            raise DeviceError(DEVICE, self.address, "CAN bus not open")
        try:
            self._bus.send(can.Message(arbitration_id=arb_id, data=data, is_extended_id=False))
        except Exception as exc:  # noqa: BLE001 - can.CanError, OSError
            self.send_errors += 1
            self.consecutive_send_errors += 1
            raise DeviceError(DEVICE, self.address, f"CAN send failed: {exc}", kind="bus") from exc
        self.consecutive_send_errors = 0

    def write(self, cmd: float, enable: bool = True) -> None:
        """Send the setpoint of this tick (``cmd`` in [-1, 1], saturated)."""
        self._seq = (self._seq + 1) & 0xFF
        self._send(self._sp_id, encode_setpoint(cmd, self._seq, enable))

    def command(self, code: int) -> None:
        self._send(self._cmd_id, bytes([code, 0]))

    def enable(self) -> None:
        self.command(CMD_ENABLE)

    def disable(self) -> None:
        self.command(CMD_DISABLE)

    def poll(self, now: float | None = None) -> int:
        """Drain received frames (non-blocking); returns the number of status frames."""
        if self._bus is None:
            raise DeviceError(DEVICE, self.address, "CAN bus not open")
        n = 0
        while True:
            try:
                msg = self._bus.recv(0)
            except Exception as exc:  # noqa: BLE001
                raise DeviceError(DEVICE, self.address, f"CAN receive failed: {exc}",
                                  kind="bus") from exc
            if msg is None:
                break
            if msg.is_error_frame:
                self.bus_error_frames += 1
                continue
            if msg.arbitration_id == self._st_id and len(msg.data) >= 6:
                self.status_bits, self.heartbeat, self.output, self.fault_code = decode_status(msg.data)
                self.n_status += 1
                n += 1
        if n:
            self.last_status_t = time.monotonic() if now is None else now
            self.polls_since_status = 0
        else:
            self.polls_since_status += 1
        return n

    def wait_status(self, timeout_s: float = 0.5) -> None:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.poll():
                return
            time.sleep(0.001)
        raise DeviceError(DEVICE, self.address, f"no status frame within {timeout_s:g} s")

    @property
    def fault(self) -> bool:
        return bool(self.status_bits & ST_FAULT)

    @property
    def enabled(self) -> bool:
        return bool(self.status_bits & ST_ENABLED)

    def heartbeat_age_s(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        return now - self.last_status_t
