"""Load-cell conditioner emulator: a pymodbus 3.16 server (TCP, or RTU over a pty bridge).

The register map is the driver's (:mod:`drivers.loadcells`), from the same
:class:`LoadCellConfig`. Values change on every read, so they are filled in by
the ``SimDevice(action=...)`` hook from the latest plant sample (a subclassed
datablock's ``getValues`` is ignored by pymodbus 3.16). The emulator stores
*raw* values: ``raw = (force_N - offset) / scale`` (tare is the host's business).

Faults (``self.faults``): ``slow_s`` (answer after a delay), ``silent`` (never
answer), ``exception`` (Modbus exception 4, device failure), ``freeze_counter``,
``nan_friction`` (the friction channel reads NaN), ``inf_normal_1`` (normal force 1
reads +inf): what a broken conditioner's float32 registers can hold.

Calibration (issue 21): each channel with a ``shunt_address`` has a shunt-calibration
register: the reading with the bridge's shunt resistor engaged, i.e. the
channel's ``calibration.shunt_reference_N`` as the bridge reports it (ASTM E4 /
ISO 7500-1 practice: a drifted bridge or amplifier moves it). ``drift`` (a
fraction) scales every bridge output, the shunt readings included: a gain drift
of the cell or its amplifier. ``reference_channel`` (1, 2, 3: friction, normal
1, normal 2; 0 off) and ``reference_load_N``: the reference-load input, a known
load applied to that cell (dead weights or a reference cell in a calibration
frame) in place of the rig's force, for ``rig calibrate verify``.
"""

from __future__ import annotations

import asyncio
import threading

from drivers.config import LoadCellConfig
from drivers.loadcells import CHANNELS, encode_value


FAULT_KEYS = ("slow_s", "silent", "exception", "freeze_counter", "nan_friction", "inf_normal_1", "drift",
              "reference_channel", "reference_load_N")


class SharedSample:
    """Forces, counter, status and faults in shared memory, so the server can run in its
    own process (no GIL shared with the plant). Seqlock: ``seq`` is odd while writing."""

    def __init__(self, ctx):
        self.vals = ctx.Array("d", 6, lock=False)    # seq, f, n1, n2, counter, status
        self.faults = ctx.Array("d", len(FAULT_KEYS), lock=False)

    def write(self, forces, counter, status):
        v = self.vals
        v[0] += 1
        v[1], v[2], v[3] = forces
        v[4] = counter
        v[5] = status
        v[0] += 1

    def read(self):
        v = self.vals
        for _ in range(100):
            s0 = v[0]
            out = ([v[1], v[2], v[3]], int(v[4]), int(v[5]))
            if s0 == v[0] and int(s0) % 2 == 0:
                return out
        return out

    def set_fault(self, key, value):
        self.faults[FAULT_KEYS.index(key)] = 0.0 if value in (None, False) else float(value)

    def fault_dict(self) -> dict:
        return {k: self.faults[i] for i, k in enumerate(FAULT_KEYS) if self.faults[i]}


class ModbusConditionerEmulator:
    def __init__(self, cfg: LoadCellConfig, rtu_server_port: str | None = None,
                 shared: SharedSample | None = None):
        """``rtu_server_port``: for RTU, the serial port the *server* opens (the
        other end of the pty bridge from ``cfg.serial_port``)."""
        self.cfg = cfg
        self.rtu_server_port = rtu_server_port
        self.forces = [0.0, 0.0, 0.0]
        self.counter = 0
        self.status = 0
        self.faults: dict = {}
        self.shared = shared
        self.n_requests = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        first, count = cfg.span()
        shunts = [getattr(cfg, ch).shunt_address for ch in CHANNELS if getattr(cfg, ch).shunt_address is not None]
        self._size = max([first + count, 8] + [a + cfg.words_per_value for a in shunts]) + 1

    # -- values from the plant -------------------------------------------------------
    def update(self, friction_N: float, normal_1_N: float, normal_2_N: float) -> None:
        self.forces = [friction_N, normal_1_N, normal_2_N]
        if not self.faults.get("freeze_counter"):
            self.counter = (self.counter + 1) & 0xFFFF

    def registers(self) -> dict[int, int]:
        """Address -> register value for the current sample (what a read returns)."""
        c = self.cfg
        out: dict[int, int] = {}
        if self.shared is not None:
            self.forces, self.counter, self.status = self.shared.read()
        forces = list(self.forces)
        f = self.faults if self.shared is None else self.shared.fault_dict()
        if f.get("nan_friction"):
            forces[0] = float("nan")
        if f.get("inf_normal_1"):
            forces[1] = float("inf")
        ref = int(f.get("reference_channel", 0))
        if 1 <= ref <= 3:  # the reference-load input: a known load on that cell instead of the rig's force
            forces[ref - 1] = float(f.get("reference_load_N", 0.0))
        gain = 1.0 + float(f.get("drift", 0.0))
        for ch, force in zip(CHANNELS, forces):
            cal = getattr(c, ch)
            values = [(cal.address, force * gain)]
            if cal.shunt_address is not None:
                shunt = cal.calibration.shunt_reference_N if cal.calibration is not None else None
                values.append((cal.shunt_address, float("nan") if shunt is None else shunt * gain))
            for addr, val in values:
                raw = (val - cal.offset) / cal.scale
                for k, w in enumerate(encode_value(raw, c.encoding, c.word_order)):
                    out[addr + k] = w
        if c.counter_address is not None:
            out[c.counter_address] = self.counter
        if c.status_address is not None:
            out[c.status_address] = self.status
        return out

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        from pymodbus.constants import ExcCodes

        self.n_requests += 1
        f = self.faults if self.shared is None else self.shared.fault_dict()
        if f.get("silent"):
            await asyncio.sleep(3600)
        if f.get("slow_s"):
            await asyncio.sleep(float(f["slow_s"]))
        if f.get("exception"):
            return ExcCodes.DEVICE_FAILURE
        for addr, val in self.registers().items():
            i = addr - start_address
            if 0 <= i < len(registers):
                registers[i] = val
        return None

    # -- server --------------------------------------------------------------------
    def start(self, timeout_s: float = 5.0) -> None:
        self._thread = threading.Thread(target=self._run, name="modbus-emulator", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"Modbus emulator did not start ({self.cfg.address_text})")
        if self._error:
            raise RuntimeError(f"the Modbus server at {self.cfg.address_text} could not start: {self._error} "
                               "(is the port in use?)")

    def _run(self):
        from pymodbus.framer import FramerType
        from pymodbus.server import ModbusSerialServer, ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        c = self.cfg
        dev = SimDevice(c.device_id,
                        simdata=[SimData(0, count=self._size, values=0, datatype=DataType.REGISTERS)],
                        action=self._action)

        async def main():
            try:
                if c.transport == "tcp":
                    self._server = ModbusTcpServer(dev, address=(c.host, c.port))
                else:
                    self._server = ModbusSerialServer(dev, framer=FramerType.RTU,
                                                      port=self.rtu_server_port,
                                                      baudrate=c.baudrate, timeout=1)
                await self._server.serve_forever(background=True)
            except BaseException as exc:  # noqa: BLE001
                self._error = exc
                self._ready.set()
                return
            self._ready.set()
            await self._server.serving

        try:
            loop.run_until_complete(main())
        except BaseException as exc:  # noqa: BLE001
            self._error = exc
        finally:
            self._ready.set()

    def stop(self) -> None:
        if self._loop is not None and self._server is not None:
            fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
            try:
                fut.result(timeout=3)
            except Exception:  # noqa: BLE001
                pass
        if self._thread is not None:
            self._thread.join(timeout=3)


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (for an emulator's server)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def modbus_server_main(cfg_dict, shared: SharedSample, rtu_server_port, fifo_priority, conn):
    """Entry of the Modbus server process (started by the emulated rig, :class:`rig.hardware.emulated.EmulatedRig`)."""
    import logging
    import os
    import signal
    import sys
    import time

    from drivers.linux import serve_requests, set_pdeathsig

    set_pdeathsig()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    sys.setswitchinterval(1e-4)
    if fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
        except (OSError, AttributeError):
            pass
    em = ModbusConditionerEmulator(LoadCellConfig.model_validate(cfg_dict), rtu_server_port, shared)
    try:
        em.start()
    except Exception as exc:  # noqa: BLE001
        conn.send(("error", str(exc)))
        return
    import gc

    gc.collect()
    gc.freeze()
    conn.send(("ready", None))
    serve_requests(conn, lambda req: conn.send(("stats", em.n_requests)) if req[0] == "stats" else None)
    em.stop()
    del time
