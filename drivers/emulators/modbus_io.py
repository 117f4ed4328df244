"""Digital I/O module emulator (the safety chain's; :mod:`drivers.safety_io`): a small Modbus TCP server.

Discrete inputs: the e-stop (normally closed: 1 while the circuit is closed) and
the hydraulic pressure-OK; coils: the valve amplifier's enable and the watchdog.
Its relay logic, as a safety relay's: the amplifier is enabled only while the
enable coil is on, the e-stop circuit closed and the watchdog coil toggled
within ``watchdog_s`` (:meth:`IoState.amplifier_enabled`). Functions 1 (read
coils), 2 (read discrete inputs) and 15 (write multiple coils); anything else
gets exception 1. Frames through the driver's codec.

State in shared memory (:class:`IoState`), so the server runs in its own
process (:func:`io_server_main`) while the emulated rig's plant reads the
amplifier's enable and a test presses the e-stop (``press_estop``,
``lose_pressure``).
"""

from __future__ import annotations

import socket
import struct
import threading
import time

from drivers.config import SafetyConfig
from drivers.safety_io import (
    FC_READ_COILS, FC_READ_INPUTS, FC_WRITE_COILS, MBAP, frame, pack_bits, unpack_bits,
)

# shared values: e-stop closed, pressure OK, enable coil, watchdog coil, last toggle (monotonic), requests
ESTOP, PRESSURE, ENABLE, WATCHDOG, T_TOGGLE, N_REQ = range(6)


class IoState:
    def __init__(self, ctx, watchdog_s: float):
        self.v = ctx.Array("d", 6, lock=False)
        self.v[ESTOP] = self.v[PRESSURE] = 1.0
        self.watchdog_s = watchdog_s

    def press_estop(self, pressed: bool = True) -> None:
        self.v[ESTOP] = 0.0 if pressed else 1.0

    def lose_pressure(self, lost: bool = True) -> None:
        self.v[PRESSURE] = 0.0 if lost else 1.0

    def amplifier_enabled(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        v = self.v
        return bool(v[ENABLE]) and bool(v[ESTOP]) and now - v[T_TOGGLE] <= self.watchdog_s

    def snapshot(self) -> dict:
        v = self.v
        return {"estop_closed": bool(v[ESTOP]), "pressure_ok": bool(v[PRESSURE]), "enable_coil": bool(v[ENABLE]),
                "amplifier_enabled": self.amplifier_enabled(), "requests": int(v[N_REQ])}


class IoModuleEmulator:
    def __init__(self, cfg: SafetyConfig, state: IoState):
        self.cfg, self.state = cfg, state
        self.sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self.running = False

    def _inputs(self) -> dict[int, bool]:
        v = self.state.v
        return {self.cfg.estop_input: bool(v[ESTOP]), self.cfg.pressure_ok_input: bool(v[PRESSURE])}

    def _coils(self) -> dict[int, bool]:
        v = self.state.v
        return {self.cfg.enable_output: bool(v[ENABLE]), self.cfg.watchdog_output: bool(v[WATCHDOG])}

    def answer(self, tid: int, unit: int, pdu: bytes) -> bytes:
        """The answer PDU (framed) to one request PDU."""
        self.state.v[N_REQ] += 1
        fc = pdu[0]
        if fc in (FC_READ_COILS, FC_READ_INPUTS) and len(pdu) == 5:
            first, n = struct.unpack_from(">HH", pdu, 1)
            vals = self._coils() if fc == FC_READ_COILS else self._inputs()
            data = pack_bits([vals.get(first + i, False) for i in range(n)])
            return frame(tid, unit, bytes((fc, len(data))) + data)
        if fc == FC_WRITE_COILS and len(pdu) >= 6:
            first, n, nb = struct.unpack_from(">HHB", pdu, 1)
            bits = unpack_bits(pdu[6:6 + nb], n)
            v = self.state.v
            for i, b in enumerate(bits):
                a = first + i
                if a == self.cfg.enable_output:
                    v[ENABLE] = float(b)
                elif a == self.cfg.watchdog_output:
                    if bool(b) != bool(v[WATCHDOG]):
                        v[T_TOGGLE] = time.monotonic()
                    v[WATCHDOG] = float(b)
            return frame(tid, unit, struct.pack(">BHH", fc, first, n))
        return frame(tid, unit, bytes((fc | 0x80, 1)))

    def start(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((self.cfg.host, self.cfg.port))
        except OSError as exc:
            s.close()
            raise RuntimeError(f"the I/O module emulator at {self.cfg.address_text} could not start: {exc} "
                               "(is the port in use?)") from None
        s.listen(4)
        self.sock, self.running = s, True
        th = threading.Thread(target=self._accept, name="io-emulator", daemon=True)
        th.start()
        self._threads.append(th)

    def _accept(self) -> None:
        while self.running:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            th = threading.Thread(target=self._serve, args=(conn,), name="io-emulator-conn", daemon=True)
            th.start()

    def _serve(self, conn: socket.socket) -> None:
        buf = bytearray()
        with conn:
            while self.running:
                try:
                    chunk = conn.recv(4096)
                except OSError:
                    return
                if not chunk:
                    return
                buf += chunk
                out = bytearray()
                while len(buf) >= 8:
                    tid, pid, ln, unit = MBAP.unpack_from(buf)
                    if pid != 0 or not 2 <= ln <= 254:
                        return  # not Modbus: drop the connection, as a module would
                    if len(buf) < 6 + ln:
                        break
                    pdu = bytes(buf[7:6 + ln])
                    del buf[:6 + ln]
                    if unit == self.cfg.device_id:
                        out += self.answer(tid, unit, pdu)
                if out:
                    try:
                        conn.sendall(out)
                    except OSError:
                        return

    def stop(self) -> None:
        self.running = False
        if self.sock is not None:
            try:
                self.sock.close()
            except OSError:
                pass


def io_server_main(cfg_dict, state: IoState, fifo_priority: int, conn) -> None:
    """Entry of the I/O module emulator's process (started by :class:`rig.hardware.emulated.EmulatedRig`)."""
    import os
    import signal

    from drivers.linux import serve_requests, set_pdeathsig, set_process_name

    set_pdeathsig()
    set_process_name("rig-emulator-io")
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
        except (OSError, AttributeError):
            pass
    em = IoModuleEmulator(SafetyConfig.model_validate(cfg_dict), state)
    try:
        em.start()
    except RuntimeError as exc:
        conn.send(("error", str(exc)))
        return
    conn.send(("ready", None))
    serve_requests(conn, lambda req: None)  # nothing to ask it but to stop: the state is shared
    em.stop()
