"""The safety chain's digital I/O module on Modbus TCP: e-stop and pressure-OK inputs, enable and watchdog outputs.

:class:`SafetyIO` is a :class:`drivers.device.Device` (``name`` "safety"). Each
tick the loop sets ``enable`` (the valve amplifier's enable: on only while the
loop controls the valve) and calls ``write(now)``, which sends, in one TCP
write, the outputs (function 15, write multiple coils: the enable and the
watchdog, toggled every tick) and a request for the inputs (function 2, read
discrete inputs); ``read(now)`` at the next tick takes the answers in
(pipelined: the module answers while the loop works). ``estop_ok`` is the
normally closed e-stop input (1: closed, healthy; 0: pressed or a broken wire),
``pressure_ok`` the hydraulic power unit's pressure-OK input. ``health(now)``
names an open e-stop (``estop``) or a lost pressure (``hydraulic_pressure``) in
its ``problems``, each of which trips the loop (:mod:`rig.hardware.interlocks`);
a module that stops answering goes stale and trips too (fail safe).

The frames are packed and unpacked by the pure codec below (:func:`encode_read_inputs`,
:func:`encode_write_coils`, :func:`decode_answer`), tested frame by frame with no
I/O; the emulator (:mod:`drivers.emulators.modbus_io`) uses the same codec.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass

from drivers.config import SafetyConfig
from drivers.device import DeviceHealth
from drivers.errors import DeviceError
from drivers.linux import close_quietly, open_tcp_nodelay, recv_available

DEVICE = "safety I/O module"
FC_READ_COILS, FC_READ_INPUTS, FC_WRITE_COILS = 0x01, 0x02, 0x0F
MBAP = struct.Struct(">HHHB")  # transaction id, protocol id (0), length (unit id + PDU), unit id
_U16 = struct.Struct(">H")


# -- the codec: frames <-> values, pure ----------------------------------------------------------------

def pack_bits(bits) -> bytes:
    """Bits (LSB of the first byte first), as Modbus packs coils and inputs."""
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def unpack_bits(data: bytes, n: int) -> list[bool]:
    return [bool(data[i // 8] >> (i % 8) & 1) for i in range(n)]


def frame(tid: int, unit: int, pdu: bytes) -> bytes:
    """One Modbus TCP frame: MBAP header + PDU."""
    return MBAP.pack(tid & 0xFFFF, 0, len(pdu) + 1, unit) + pdu


def encode_read(tid: int, unit: int, fc: int, first: int, count: int) -> bytes:
    """Read coils (1) or discrete inputs (2): ``count`` bits from ``first``."""
    return frame(tid, unit, struct.pack(">BHH", fc, first, count))


def encode_read_inputs(tid: int, unit: int, first: int, count: int) -> bytes:
    return encode_read(tid, unit, FC_READ_INPUTS, first, count)


def encode_write_coils(tid: int, unit: int, first: int, bits) -> bytes:
    """Write multiple coils (15) from ``first``."""
    data = pack_bits(bits)
    return frame(tid, unit, struct.pack(">BHHB", FC_WRITE_COILS, first, len(bits), len(data)) + data)


@dataclass(frozen=True, slots=True)
class Answer:
    tid: int
    unit: int
    fc: int
    bits: bytes = b""        # read answers: the packed bits
    exception: int = 0       # an exception response's code (fc has 0x80 set)


def decode_answer(buf: bytes | bytearray) -> tuple[Answer | None, int]:
    """The first whole answer in ``buf`` and the bytes it took (None, 0: not whole yet). ValueError for
    what is not Modbus TCP."""
    if len(buf) < 8:
        return None, 0
    tid, pid, ln, unit = MBAP.unpack_from(buf)
    if pid != 0 or not 2 <= ln <= 254:
        raise ValueError(f"not a Modbus TCP frame (protocol id {pid}, length {ln})")
    if len(buf) < 6 + ln:
        return None, 0
    pdu = bytes(buf[7:6 + ln])
    fc = pdu[0]
    if fc & 0x80:
        return Answer(tid, unit, fc, exception=pdu[1] if len(pdu) > 1 else 0), 6 + ln
    if fc in (FC_READ_COILS, FC_READ_INPUTS):
        if len(pdu) < 2 or pdu[1] != len(pdu) - 2:
            raise ValueError(f"read answer of {len(pdu)} bytes with byte count {pdu[1] if len(pdu) > 1 else '?'}")
        return Answer(tid, unit, fc, bits=pdu[2:]), 6 + ln
    if fc == FC_WRITE_COILS and len(pdu) == 5:
        return Answer(tid, unit, fc), 6 + ln
    raise ValueError(f"unexpected answer: function {fc}, {len(pdu)} bytes")


def span(a: int, b: int) -> tuple[int, int]:
    """(first, count) covering addresses a and b."""
    return min(a, b), abs(a - b) + 1


# -- the device ----------------------------------------------------------------------------------------

class SafetyIO:
    """The safety chain's I/O module as a Device (see the module docstring)."""

    name = "safety"

    def __init__(self, cfg: SafetyConfig):
        self.cfg = cfg
        self.address = cfg.address_text
        self._health = DeviceHealth(DEVICE, self.address)
        self.enable = False
        self.watchdog = False
        self.estop_ok = False        # unknown until the first answer: not healthy
        self.pressure_ok = False
        self.outputs: list[bool] | None = None  # the coils as last read back (safe_stop, check)
        self._sock: socket.socket | None = None
        self._rx = bytearray()
        self._tid = 0
        self._pending: dict[int, int] = {}  # tid -> function code in flight
        self._t_sent = 0.0
        self._t_new = 0.0
        self._writing = False  # the loop's writes ask for the inputs; before them, read() does
        self._tick_tids: tuple[int, int] | None = None  # the per-tick request in flight (fast path)
        self._problems_key = None
        self._in0, self._in_n = span(cfg.estop_input, cfg.pressure_ok_input)
        self._out0, self._out_n = span(cfg.enable_output, cfg.watchdog_output)
        c = cfg
        # the per-tick request (outputs + inputs), built once per (enable, watchdog); each send only writes
        # its two transaction ids; its answers' length, and where the input bits are in them
        self._tick_frames = {}
        for en in (False, True):
            for wd in (False, True):
                bits = [False] * self._out_n
                bits[c.enable_output - self._out0], bits[c.watchdog_output - self._out0] = en, wd
                a = encode_write_coils(0, c.device_id, self._out0, bits)
                self._off2 = len(a)
                self._tick_frames[en, wd] = bytearray(a + encode_read_inputs(0, c.device_id, self._in0, self._in_n))
        self._in_bytes = (self._in_n + 7) // 8
        self._ans_len = 12 + 9 + self._in_bytes  # write-coils answer + read-inputs answer
        self._estop_bit, self._pressure_bit = c.estop_input - self._in0, c.pressure_ok_input - self._in0

    # -- connection ------------------------------------------------------------------------------------
    def connect(self) -> None:
        c = self.cfg
        self._sock = open_tcp_nodelay(c.host, c.port, c.timeout_s, DEVICE, self.address)
        self._rx.clear()
        self._pending.clear()
        self._t_new = time.monotonic()

    def close(self) -> None:
        close_quietly(self._sock)
        self._sock = None

    def _lost(self, msg: str) -> DeviceError:
        self.close()
        return DeviceError(DEVICE, self.address, msg, kind="lost")

    def _send(self, data: bytes) -> None:
        if self._sock is None:
            raise DeviceError(DEVICE, self.address, "not connected", kind="lost")
        try:
            self._sock.send(data)
        except OSError as exc:
            raise self._lost(f"connection lost: {exc}") from exc

    def _next_tid(self, fc: int) -> int:
        self._tid = (self._tid + 1) & 0xFFFF
        self._pending[self._tid] = fc
        return self._tid

    def _outputs_frame(self, enable: bool, watchdog: bool) -> bytes:
        bits = [False] * self._out_n
        bits[self.cfg.enable_output - self._out0] = enable
        bits[self.cfg.watchdog_output - self._out0] = watchdog
        return encode_write_coils(self._next_tid(FC_WRITE_COILS), self.cfg.device_id, self._out0, bits)

    # -- per tick --------------------------------------------------------------------------------------
    def write(self, now: float | None = None, toggle: bool = True) -> None:
        """The outputs (enable, the watchdog toggled unless ``toggle`` is false) and the request for the
        inputs, in one send."""
        now = time.monotonic() if now is None else now
        self._writing = True
        if self._pending or self._tick_tids is not None:
            return  # the last tick's answers are not all in yet: never queue behind a slow module
        if toggle:
            self.watchdog = not self.watchdog
        wd = self.watchdog
        buf = self._tick_frames[bool(self.enable), wd]
        t1 = (self._tid + 1) & 0xFFFF
        t2 = (t1 + 1) & 0xFFFF
        self._tid = t2
        _U16.pack_into(buf, 0, t1)
        _U16.pack_into(buf, self._off2, t2)
        self._tick_tids = (t1, t2)
        self._t_sent = now
        try:
            self._sock.send(buf)
        except (OSError, AttributeError) as exc:
            raise self._lost(f"connection lost: {exc}") from exc

    def read(self, now: float | None = None) -> None:
        """Take in the answers that have arrived (the inputs of the last request)."""
        now = time.monotonic() if now is None else now
        h = self._health
        sk = self._sock
        if sk is None:
            raise DeviceError(DEVICE, self.address, "not connected", kind="lost")
        recv_available(sk, self._rx, self._ans_len if self._tick_tids is not None else 1 << 30, self._lost, "module")
        new = False
        rx, tt = self._rx, self._tick_tids
        if tt is not None and len(rx) >= self._ans_len:
            unit = self.cfg.device_id
            if len(rx) == self._ans_len and (rx[0] << 8 | rx[1]) == tt[0] and rx[6] == unit and rx[7] == FC_WRITE_COILS \
                    and (rx[12] << 8 | rx[13]) == tt[1] and rx[18] == unit and rx[19] == FC_READ_INPUTS \
                    and rx[20] == self._in_bytes and not (rx[2] | rx[3] | rx[14] | rx[15]):
                # the fast path: this tick's two answers, whole and as expected
                b0 = int.from_bytes(rx[21:21 + self._in_bytes], "little")
                self.estop_ok = bool(b0 >> self._estop_bit & 1)
                self.pressure_ok = bool(b0 >> self._pressure_bit & 1)
                rx.clear()
                new = True
            else:  # anything else: the general decoder below
                self._pending[tt[0]] = FC_WRITE_COILS
                self._pending[tt[1]] = FC_READ_INPUTS
            self._tick_tids = None
        while rx:
            try:
                ans, used = decode_answer(self._rx)
            except ValueError as exc:
                self._rx.clear()
                h.frames_bad += 1
                raise DeviceError(DEVICE, self.address, str(exc), kind="protocol") from None
            if ans is None:
                break
            del self._rx[:used]
            fc = self._pending.pop(ans.tid, None)
            if fc is None:
                continue  # an answer to a request given up on
            if ans.exception:
                h.errors += 1
                h.consecutive_errors += 1
                raise DeviceError(DEVICE, self.address, f"Modbus exception {ans.exception} to function {fc}",
                                  kind="protocol")
            if fc == FC_READ_INPUTS:
                bits = unpack_bits(ans.bits, self._in_n)
                self.estop_ok = bits[self.cfg.estop_input - self._in0]
                self.pressure_ok = bits[self.cfg.pressure_ok_input - self._in0]
                new = True
            elif fc == FC_READ_COILS:
                self.outputs = unpack_bits(ans.bits, self._out_n)
        if new:
            h.frames_ok += 1
            h.polls_since_new = 0
            h.consecutive_errors = 0
            self._t_new = now
        else:
            h.polls_since_new += 1
            if (self._pending or self._tick_tids is not None) and now - self._t_sent > self.cfg.timeout_s:
                self._pending.clear()  # given up: the next write asks again
                self._tick_tids = None
                h.frames_lost += 1
                h.errors += 1
                h.consecutive_errors += 1
                raise DeviceError(DEVICE, self.address, f"no answer within {self.cfg.timeout_s * 1e3:g} ms")
            if not self._pending and not self._writing:  # before the loop writes (connect, wait for data)
                c = self.cfg
                self._t_sent = now
                self._send(encode_read_inputs(self._next_tid(FC_READ_INPUTS), c.device_id, self._in0, self._in_n))

    def health(self, now: float | None = None) -> DeviceHealth:
        now = time.monotonic() if now is None else now
        h, c = self._health, self.cfg
        h.age_s = now - self._t_new
        h.status = (1 if self.estop_ok else 0) | (2 if self.pressure_ok else 0) | (4 if self.enable else 0)
        key = (self.estop_ok, self.pressure_ok, h.frames_ok > 0)
        if key == self._problems_key:
            return h
        self._problems_key = key
        h.problems = _chain_problems(c, self.address, self.estop_ok, self.pressure_ok) if h.frames_ok else []
        return h

    # -- outside the loop ------------------------------------------------------------------------------
    def poll(self, timeout_s: float = 1.0) -> None:
        """Blocking: the inputs and the outputs read back once (check, reset)."""
        t_end = time.monotonic() + timeout_s
        c = self.cfg
        self._pending.clear()
        self._tick_tids = None
        n0 = self._health.frames_ok
        self._send(encode_read(self._next_tid(FC_READ_COILS), c.device_id, FC_READ_COILS, self._out0, self._out_n)
                   + encode_read_inputs(self._next_tid(FC_READ_INPUTS), c.device_id, self._in0, self._in_n))
        self._t_sent = time.monotonic()
        while self._pending:
            if time.monotonic() > t_end:
                raise DeviceError(DEVICE, self.address, f"no answer within {timeout_s:g} s")
            time.sleep(0.001)
            try:
                self.read(time.monotonic())
            except DeviceError as exc:
                if exc.kind != "io":
                    raise
        if self._health.frames_ok == n0:
            raise DeviceError(DEVICE, self.address, "no inputs in the answer")

    def safe_stop(self, timeout_s: float = 0.1) -> bool:
        """The enable output off; True once the module's coils read back off."""
        self.enable = False
        try:
            self._pending.clear()
            self._tick_tids = None
            self._send(self._outputs_frame(False, self.watchdog))
            self.poll(timeout_s)
        except DeviceError:
            return False
        return self.outputs is not None and not self.outputs[self.cfg.enable_output - self._out0]

    def describe(self) -> str:
        """The chain's state in words (devices check, reset)."""
        out = "unknown" if self.outputs is None else \
            ("on" if self.outputs[self.cfg.enable_output - self._out0] else "off")
        return (f"e-stop {'closed (healthy)' if self.estop_ok else 'OPEN (pressed or wire broken)'}, "
                f"pressure {'OK' if self.pressure_ok else 'LOST'}, enable output {out}")


# -- the module on a process of its own: what the loop drives ------------------------------------------------

# the link's shared values: the loop's tick count and enable request; the module's inputs and link health
L_SEQ, L_ENABLE, L_ESTOP, L_PRESSURE, L_FRAMES, L_T_NEW, L_ERRORS, L_CONSEC, L_LOST, L_BAD, L_N = range(11)


def _link_main(cfg_dict, shm, conn, period_s: float, priority: int) -> None:
    """The link process: every ``period_s`` the module's inputs (into ``shm``) and its outputs (the loop's
    enable request; the watchdog toggled only when the loop's tick count moved since the last time)."""
    import os
    import signal as _signal

    from drivers.linux import set_pdeathsig, set_process_name

    set_pdeathsig()
    set_process_name("rig-safety-link")
    _signal.signal(_signal.SIGINT, _signal.SIG_IGN)
    io = SafetyIO(SafetyConfig.model_validate(cfg_dict))
    try:
        io.connect()
        io.poll()
    except DeviceError as exc:
        conn.send(("error", str(exc)))
        return
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError):
            pass
    conn.send(("ready", None))
    seq_seen, mono = -1.0, time.monotonic
    nxt = mono()
    while True:
        nxt += period_s
        left = nxt - mono()
        if left > 0:
            time.sleep(left)
        else:
            nxt = mono()
        now = mono()
        try:
            io.read(now)
        except DeviceError:
            pass  # counted in its health: the loop sees the link go stale or its errors
        h = io._health
        if h.frames_ok != shm[L_FRAMES]:
            shm[L_ESTOP], shm[L_PRESSURE], shm[L_T_NEW] = float(io.estop_ok), float(io.pressure_ok), now
            shm[L_FRAMES] = h.frames_ok
        shm[L_ERRORS], shm[L_CONSEC], shm[L_LOST], shm[L_BAD] = h.errors, h.consecutive_errors, h.frames_lost, \
            h.frames_bad
        seq = shm[L_SEQ]
        io.enable = bool(shm[L_ENABLE])
        try:
            io.write(now, toggle=seq != seq_seen)  # a stalled loop stops the watchdog: the relay drops
        except DeviceError:
            pass
        seq_seen = seq
        if conn.poll():
            try:
                req = conn.recv()
            except EOFError:
                break
            if req == "safe_stop":
                shm[L_ENABLE] = 0.0
                ok = io.safe_stop()
                conn.send(("safe_stop", ok, io.describe()))
            elif req == "stop":
                break
    io.close()


class SafetyLink:
    """The safety chain's I/O module as the loop's Device (``name`` "safety"), served by a process of its
    own (:func:`_link_main`, every ``period_s``): the Modbus round trips (two TCP frames each way) stay out
    of the loop's tick, which only reads and writes shared memory. ``read`` takes the latest inputs,
    ``write`` hands over ``enable`` and the tick count (the link toggles the watchdog output only while the
    count moves: a stalled loop lets the module's relay drop the enable); ``health`` is the link's (a dead
    link goes stale and trips). ``safe_stop`` turns the enable output off and reads it back."""

    name = "safety"

    def __init__(self, cfg: SafetyConfig, period_s: float = 1e-3, priority: int = 0):
        import multiprocessing as mp

        self.cfg, self.address = cfg, cfg.address_text
        self.period_s, self.priority = period_s, priority
        self._ctx = mp.get_context("spawn")
        self.shm = self._ctx.Array("d", L_N, lock=False)
        self._health = DeviceHealth(DEVICE, self.address)
        self.enable = False
        self.estop_ok = self.pressure_ok = False
        self._proc = self._conn = None
        self._attached = False
        self._failed: str | None = None  # why the link another process started could not connect
        self._frames = 0.0
        self._problems_key = None
        self._final = ""

    def attach(self, shm, conn, failed: str | None = None) -> None:
        """Use a link another process started (:meth:`connect` there; the loop's process is a daemon and
        may not start processes): its shared values and its pipe, or why it could not connect (then
        :meth:`connect` raises it here, beside the other devices' failures)."""
        self.shm, self._conn, self._attached, self._failed = shm, conn, True, failed

    @property
    def link(self) -> tuple:
        """What :meth:`attach` needs in another process."""
        return self.shm, self._conn

    def connect(self) -> None:
        if self._attached:
            if self._failed:
                raise DeviceError(DEVICE, self.address, self._failed)
            return
        self._conn, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(target=_link_main, name="rig-safety-link", daemon=True,
                                       args=(self.cfg.model_dump(), self.shm, child, self.period_s, self.priority))
        self._proc.start()
        if not self._conn.poll(30.0):
            self.close()
            raise DeviceError(DEVICE, self.address, "the safety link process did not start")
        kind, payload = self._conn.recv()
        if kind != "ready":
            self.close()
            raise DeviceError(DEVICE, self.address, str(payload).split(": ", 1)[-1])

    def read(self, now: float | None = None) -> None:
        s, h = self.shm, self._health
        if s[L_FRAMES] != self._frames:
            self._frames = s[L_FRAMES]
            self.estop_ok, self.pressure_ok = s[L_ESTOP] > 0.5, s[L_PRESSURE] > 0.5
            h.polls_since_new = 0
        else:
            h.polls_since_new += 1

    def write(self, now: float | None = None) -> None:
        s = self.shm
        s[L_ENABLE] = 1.0 if self.enable else 0.0
        s[L_SEQ] += 1.0

    def health(self, now: float | None = None) -> DeviceHealth:
        now = time.monotonic() if now is None else now
        s, h, c = self.shm, self._health, self.cfg
        h.frames_ok = int(s[L_FRAMES])
        h.age_s = now - s[L_T_NEW] if s[L_T_NEW] else float("inf")
        h.errors, h.consecutive_errors, h.frames_lost, h.frames_bad = int(s[L_ERRORS]), int(s[L_CONSEC]), \
            int(s[L_LOST]), int(s[L_BAD])
        h.status = (1 if self.estop_ok else 0) | (2 if self.pressure_ok else 0) | (4 if self.enable else 0)
        key = (self.estop_ok, self.pressure_ok, h.frames_ok > 0)
        if key != self._problems_key:
            self._problems_key = key
            h.problems = _chain_problems(c, self.address, self.estop_ok, self.pressure_ok) if h.frames_ok else []
        return h

    def safe_stop(self, timeout_s: float = 0.5) -> bool:
        """The enable output off (the link turns it off and reads the coils back); True once it is."""
        self.enable = False
        self.shm[L_ENABLE] = 0.0
        if self._conn is None or (self._proc is not None and not self._proc.is_alive()):
            return False
        try:
            self._conn.send("safe_stop")
            if self._conn.poll(timeout_s):
                _, ok, self._final = self._conn.recv()
                return bool(ok)
        except (OSError, EOFError):
            pass
        return False

    def describe(self) -> str:
        return self._final or (f"e-stop {'closed (healthy)' if self.estop_ok else 'OPEN'}, "
                               f"pressure {'OK' if self.pressure_ok else 'LOST'}")

    def close(self) -> None:
        if self._attached:
            return  # the process that started the link stops it
        if self._proc is not None:
            try:
                self._conn.send("stop")
            except (OSError, BrokenPipeError):
                pass
            self._proc.join(2.0)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join(1.0)
            self._proc = None


def _chain_problems(c: SafetyConfig, address: str, estop_ok: bool, pressure_ok: bool) -> list:
    probs = []
    if not estop_ok:
        probs.append(("estop", f"e-stop pressed or its circuit open (input {c.estop_input} of {address})"))
    if not pressure_ok:
        probs.append(("hydraulic_pressure", f"hydraulic pressure lost (input {c.pressure_ok_input} of {address})"))
    return probs


__all__ = ["SafetyIO", "SafetyLink", "decode_answer", "encode_read_inputs", "encode_write_coils", "pack_bits", "unpack_bits"]
