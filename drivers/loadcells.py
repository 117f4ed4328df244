"""Load-cell conditioner over Modbus TCP or RTU (pymodbus 3.16.1, pinned).

Register map of the conditioner (defaults of :class:`drivers.config.LoadCellConfig`;
every address is configurable, input or holding registers):

=======  ==============================================================
address  content
=======  ==============================================================
0        uint16 sample counter (increments with every new conversion)
1        uint16 status word (bit0 overload, bit1 sensor fault)
2-3      friction channel (float32 or int32, word order configurable)
4-5      normal force 1 (rider 1)
6-7      normal force 2 (rider 2)
=======  ==============================================================

With ``encoding: int16`` each channel is one register (signed). One read
request covers every register used (:meth:`LoadCellConfig.span`), so the
three forces come from the same conversion. Calibration per channel:
``force_N = raw * scale + offset - tare_N``; :meth:`LoadCellReader.tare`
takes the current readings as the new zeros (Dupont & Dunlap 1995, section 3:
friction +-0.25 N, normal forces +-0.6 N).

Staleness: the age of the data is the time since the sample counter last
changed (or since the last good read if there is no counter).

Pipelined (``LoadCellReader(cfg, pipelined=True)``, Modbus TCP; what the 1 kHz
loop uses): no blocking request inside the tick. ``read(now)`` collects the
answer to the request sent one tick earlier from a non-blocking socket, then
sends the next request at once, so the conditioner answers while the loop
does its other work and the forces are one tick older than a blocking read's.
Each request has its own MBAP transaction id: a late answer is recognised and
dropped, never taken for the next one. A tick whose answer has not arrived
counts one missed answer (``frames_lost``, so a slow conditioner shows as a
rate); no answer within ``timeout_s`` is an error (``consecutive_errors``)
and the request is sent again; a closed connection raises at once.
"""

from __future__ import annotations

import socket
import struct
import time

from drivers.config import LoadCellConfig
from drivers.device import DeviceHealth, release_quietly
from drivers.errors import DeviceError
from drivers.linux import close_quietly, open_tcp_nodelay, recv_available

DEVICE = "load-cell conditioner"
#: tries of one register read in a blocking check (shunt): a missed answer within the loop's timeout is
#: not yet a silent conditioner
SHUNT_READ_ATTEMPTS = 3
CHANNELS = ("friction", "normal_1", "normal_2")
_U16 = struct.Struct(">H")
_MBAP = struct.Struct(">HHH")   # transaction id, protocol id (0), length of what follows
_VALUE = {"float32": struct.Struct(">f"), "int32": struct.Struct(">i"), "int16": struct.Struct(">h")}


def decode_value(regs: list[int], encoding: str, word_order: str) -> float:
    """Decode one channel from its registers (exact: float32 / int32 / int16)."""
    if encoding == "int16":
        return float(struct.unpack(">h", struct.pack(">H", regs[0]))[0])
    hi, lo = (regs[0], regs[1]) if word_order == "big" else (regs[1], regs[0])
    raw = struct.pack(">HH", hi, lo)
    return float(struct.unpack(">f" if encoding == "float32" else ">i", raw)[0])


def encode_value(value: float, encoding: str, word_order: str) -> list[int]:
    """Inverse of :func:`decode_value` (used by the emulator and the tests)."""
    if encoding == "int16":
        v = max(-32768, min(32767, int(round(value))))
        return [struct.unpack(">H", struct.pack(">h", v))[0]]
    if encoding == "float32":
        raw = struct.pack(">f", value)
    else:
        v = max(-(2**31), min(2**31 - 1, int(round(value))))
        raw = struct.pack(">i", v)
    hi, lo = struct.unpack(">HH", raw)
    return [hi, lo] if word_order == "big" else [lo, hi]


class LoadCellReader:
    """Reads friction, normal 1 and normal 2 (N) in one Modbus request.

    A :class:`drivers.device.Device` (``name`` "loadcells"): ``read(now)``
    makes the request, the values are ``forces_N`` = (friction, normal 1,
    normal 2); ``write`` does nothing (a sensor).
    """

    name = "loadcells"

    def __init__(self, cfg: LoadCellConfig, pipelined: bool = False):
        self.cfg = cfg
        self.pipelined = pipelined and cfg.transport == "tcp"
        self._sock: socket.socket | None = None
        self._rx = bytearray()
        self._tid = 0
        self._out_tid: int | None = None   # transaction id of the request in flight
        self._out_t = 0.0
        self.late_answers = 0              # answers that came after their request timed out
        self.missed = 0                    # ticks whose answer had not arrived (frames_lost)
        self.address = cfg.address_text
        self._health = DeviceHealth(DEVICE, self.address)
        self.forces_N: tuple[float, float, float] = (float("nan"),) * 3
        self._first, self._count = cfg.span()
        self._build_decoder()
        self._client = None
        self._last_counter: int | None = None
        self._last_change_t = 0.0
        self.n_reads = 0
        self.n_errors = 0
        self.consecutive_errors = 0
        self.status = 0
        self.counter = 0
        self.reads_since_new = 0  # reads (loop ticks) without a new sample

    # -- lifecycle -----------------------------------------------------------------
    def connect(self) -> None:
        if self.pipelined:
            self._connect_socket()
            return
        import logging

        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # failures are raised as DeviceError
        from pymodbus.framer import FramerType

        c = self.cfg
        if c.transport == "tcp":
            self._client = ModbusTcpClient(c.host, port=c.port, timeout=c.timeout_s, retries=0,
                                           reconnect_delay=0)
        else:
            self._client = ModbusSerialClient(c.serial_port, framer=FramerType.RTU,
                                              baudrate=c.baudrate, timeout=c.timeout_s,
                                              retries=0, reconnect_delay=0)
        try:
            ok = self._client.connect()
        except Exception as exc:  # noqa: BLE001 - any transport failure
            raise DeviceError(DEVICE, self.address, f"cannot connect: {exc}") from exc
        if not ok:
            raise DeviceError(DEVICE, self.address, "cannot connect (refused or no such port)")
        self._last_change_t = time.monotonic()

    def _connect_socket(self) -> None:
        c = self.cfg
        self._sock = open_tcp_nodelay(c.host, c.port, c.timeout_s, DEVICE, self.address)
        self._rx.clear()
        self._out_tid = None
        fc = 4 if c.register_type == "input" else 3
        # the request, built once; each send only writes its transaction id into the first two bytes
        self._req = bytearray(struct.pack(">HHHBBHH", 0, 0, 6, c.device_id, fc, self._first, self._count))
        self._fc = fc
        self._answer_len = 6 + 3 + 2 * self._count  # MBAP + unit, function code, byte count + registers
        self._last_change_t = time.monotonic()

    def _drop_socket(self) -> None:
        close_quietly(self._sock)
        self._sock = None

    def close(self) -> None:
        self._drop_socket()
        if self._client is not None:
            release_quietly(self._client.close)
            self._client = None

    # -- reading -------------------------------------------------------------------
    def read_raw(self) -> list[int]:
        """One request for every register used; DeviceError on timeout/exception/loss."""
        if self._client is None:
            raise DeviceError(DEVICE, self.address, "not connected")
        c = self.cfg
        try:
            if c.register_type == "input":
                rr = self._client.read_input_registers(self._first, count=self._count,
                                                       device_id=c.device_id)
            else:
                rr = self._client.read_holding_registers(self._first, count=self._count,
                                                         device_id=c.device_id)
        except Exception as exc:  # noqa: BLE001 - ModbusIOException, ConnectionException, OSError
            self._error()
            self._resync()
            raise DeviceError(DEVICE, self.address, f"no answer: {exc}") from exc
        if rr.isError():
            self._error()
            code = getattr(rr, "exception_code", None)
            raise DeviceError(DEVICE, self.address, f"Modbus exception response (code {code})",
                              kind="protocol")
        regs = list(rr.registers)
        if len(regs) < self._count:
            self._error()
            raise DeviceError(DEVICE, self.address,
                              f"short response: {len(regs)} of {self._count} registers",
                              kind="protocol")
        self.consecutive_errors = 0
        self.n_reads += 1
        return regs

    def _resync(self) -> None:
        """After a timeout, drop the connection so a late answer cannot be taken for the next one."""
        try:
            self._client.close()
            self._client.connect()
        except Exception:  # noqa: BLE001 - reported by the next read
            pass

    def _lost(self, message: str) -> DeviceError:
        """The TCP connection is gone (the conditioner closed it, died or reset it): counted, the
        socket dropped (every later read says so too, never a stale value taken for a new one), and
        the error returned with ``kind="lost"``, which the loop trips on at once (``device_lost``)."""
        self._error()
        self._drop_socket()
        self._out_tid = None
        self._rx.clear()
        return DeviceError(DEVICE, self.address, message, kind="lost")

    def _error(self):
        self.n_errors += 1
        self.consecutive_errors += 1

    def _build_decoder(self) -> None:
        """Byte offsets of every field inside the registers' bytes, and each channel's struct (a
        big-word-order float32/int32 or an int16 is one big-endian value in the register bytes; the
        little word order swaps the two words first)."""
        c, first = self.cfg, self._first
        self._chan = [(2 * (getattr(c, ch).address - first), getattr(c, ch)) for ch in CHANNELS]
        self._val = _VALUE[c.encoding]
        self._swap = c.encoding != "int16" and c.word_order == "little"
        self._cnt_off = None if c.counter_address is None else 2 * (c.counter_address - first)
        self._st_off = None if c.status_address is None else 2 * (c.status_address - first)

    def _decode(self, buf: bytes, base: int, now: float) -> tuple[float, float, float]:
        """The fields of the register bytes at ``buf[base:]`` (counter, status, three forces,
        calibrated and tared)."""
        if self._cnt_off is not None:
            cnt = _U16.unpack_from(buf, base + self._cnt_off)[0]
            if cnt != self._last_counter:
                self._last_counter = cnt
                self._last_change_t = now
                self.reads_since_new = 0
            else:
                self.reads_since_new += 1
            self.counter = cnt
        else:
            self._last_change_t = now
        if self._st_off is not None:
            self.status = _U16.unpack_from(buf, base + self._st_off)[0]
        val, out = self._val, []
        for off, cal in self._chan:
            o = base + off
            raw = val.unpack(buf[o + 2:o + 4] + buf[o:o + 2])[0] if self._swap else val.unpack_from(buf, o)[0]
            out.append(raw * cal.scale + cal.offset - cal.tare_N)
        self.forces_N = (out[0], out[1], out[2])
        return self.forces_N

    # -- pipelined Modbus TCP ----------------------------------------------------------
    def _send_request(self, now: float) -> None:
        self._tid = (self._tid + 1) & 0xFFFF
        _U16.pack_into(self._req, 0, self._tid)
        try:
            self._sock.send(self._req)
        except OSError as exc:
            raise self._lost(f"connection lost: {exc}") from exc
        self._out_tid, self._out_t = self._tid, now

    def _collect(self, now: float) -> bytes | None:
        """The answer to the request in flight if it has arrived (its PDU: unit id, function code,
        byte count, registers), else None. Validated: transaction id (a late answer is dropped),
        protocol id, unit id, function code, byte count, exception responses."""
        rx = self._rx
        recv_available(self._sock, rx, self._answer_len, self._lost, "conditioner")
        frame = None
        while len(rx) >= 8:
            tid, pid, ln = _MBAP.unpack_from(rx)
            if pid != 0 or ln < 2 or ln > 260:
                rx.clear()  # not Modbus TCP: drop what we have, the request will time out
                break
            if len(rx) < 6 + ln:
                break
            pdu = bytes(rx[6:6 + ln])
            del rx[:6 + ln]
            if tid != self._out_tid:
                self.late_answers += 1  # an answer to a request that timed out: never used
                continue
            self._out_tid = None
            unit, fc = pdu[0], pdu[1]
            if unit != self.cfg.device_id:
                self._error()
                raise DeviceError(DEVICE, self.address, f"answer from unit {unit}, not {self.cfg.device_id}",
                                  kind="protocol")
            if fc & 0x80:
                self._error()
                raise DeviceError(DEVICE, self.address, f"Modbus exception response (code {pdu[2]})",
                                  kind="protocol")
            nbytes = pdu[2] if len(pdu) > 2 else 0
            if fc != self._fc or nbytes != 2 * self._count or len(pdu) != 3 + nbytes:
                self._error()
                raise DeviceError(DEVICE, self.address, f"short or malformed response ({len(pdu)} bytes)",
                                  kind="protocol")
            frame = pdu
        return frame

    def _read_pipelined(self, now: float) -> bytes | None:
        if self._sock is None:
            raise DeviceError(DEVICE, self.address, "not connected", kind="lost")
        pdu = None
        try:
            if self._out_tid is not None:
                pdu = self._collect(now)
                if pdu is None:
                    if now - self._out_t > self.cfg.timeout_s:
                        self._out_tid = None
                        self._error()
                        raise DeviceError(DEVICE, self.address,
                                          f"no answer within {self.cfg.timeout_s * 1e3:g} ms")
                    self.missed += 1
                    self.reads_since_new += 1
        finally:
            if self._out_tid is None and self._sock is not None:
                self._send_request(now)  # the next request goes out now, answered while the loop works
        if pdu is not None:
            self.consecutive_errors = 0
            self.n_reads += 1
        return pdu

    def read(self, now: float | None = None) -> tuple[float, float, float]:
        """One request: ``forces_N`` = (friction_N, normal_1_N, normal_2_N), calibrated and tared
        (also returned). Pipelined: the answer to the previous tick's request, if it has arrived."""
        now = time.monotonic() if now is None else now
        if self.pipelined:
            pdu = self._read_pipelined(now)
            if pdu is None:
                return self.forces_N
            return self._decode(pdu, 3, now)  # registers after unit id, function code, byte count
        regs = self.read_raw()
        return self._decode(struct.pack(f">{len(regs)}H", *regs), 0, now)

    def write(self, now: float | None = None) -> None:
        pass

    def health(self, now: float | None = None) -> DeviceHealth:
        h = self._health
        h.frames_ok, h.errors, h.consecutive_errors = self.n_reads, self.n_errors, self.consecutive_errors
        h.frames_lost = self.missed
        h.age_s = self.age_s(now)
        h.polls_since_new = self.reads_since_new
        h.status = self.status
        h.fault = bool(self.status & 0x03)
        h.fault_code = self.status
        return h

    def age_s(self, now: float | None = None) -> float:
        """Time since the conditioner last produced a new sample."""
        now = time.monotonic() if now is None else now
        return now - self._last_change_t

    def read_shunt(self, n: int = 10) -> dict[str, float]:
        """Each channel's shunt-calibration reading (N, mean of ``n`` reads of its ``shunt_address``;
        channels without one are left out). Blocking: for ``rig calibrate`` and the check before a
        trial, never inside the loop. DeviceError when the conditioner does not answer."""
        c = self.cfg
        out: dict[str, float] = {}
        for ch in CHANNELS:
            cal = getattr(c, ch)
            if cal.shunt_address is None:
                continue
            total = 0.0
            for _ in range(n):
                rr = self._read_patiently(cal.shunt_address, f"shunt register of {ch}")
                if rr.isError():
                    raise DeviceError(DEVICE, self.address, f"shunt register of {ch}: Modbus exception "
                                      f"(code {getattr(rr, 'exception_code', None)})", kind="protocol")
                total += decode_value(list(rr.registers), c.encoding, c.word_order) * cal.scale + cal.offset
            out[ch] = total / n
        return out

    def _read_patiently(self, address: int, what: str, attempts: int = SHUNT_READ_ATTEMPTS):
        """One register read outside the loop: the client's timeout is the loop's (a few ms), so a
        blocking check retries a missed answer before it calls the conditioner silent."""
        c = self.cfg
        for attempt in range(attempts):
            try:
                return self._client.read_input_registers(address, count=c.words_per_value, device_id=c.device_id)
            except Exception as exc:  # noqa: BLE001 - ModbusIOException, ConnectionException, OSError
                if attempt == attempts - 1:
                    raise DeviceError(DEVICE, self.address, f"{what}: no answer in {attempts} tries: {exc}") from exc
                time.sleep(0.01)

    def tare(self, n: int = 20) -> dict[str, float]:
        """Average ``n`` readings and make them the zeros (sets each channel's ``tare_N``)."""
        sums = [0.0, 0.0, 0.0]
        for _ in range(n):
            vals = self.read()
            for k in range(3):
                sums[k] += vals[k]
            time.sleep(0.001)
        out = {}
        for k, ch in enumerate(CHANNELS):
            cal = getattr(self.cfg, ch)
            cal.tare_N = cal.tare_N + sums[k] / n
            out[ch] = cal.tare_N
        return out
