"""The emulated rig: the three device emulators (:mod:`drivers.emulators`) around one simulated plant.

The per-device protocol emulators know their devices only; they get their
values through small interfaces: the LVDT streamer ``send(position_um)``, the
Modbus conditioner ``update(friction_N, normal_1_N, normal_2_N)`` (or its
shared-memory :class:`drivers.emulators.modbus_conditioner.SharedSample` when
the server runs in its own process), the valve controller ``output(now)``.
This module composes them with the plant (:class:`rig.sim.SimRig`).

:class:`EmulatedRig` steps the plant (``rig.sim.SimRig.plant_step(valve_cmd)``)
once per SYNC from the host (the CANopen valve emulator's ``on_sync(spool)``),
so that the emulated devices run in lock step with the real-time loop (tick k's
set-point moves the plant; tick k+1 reads the result, as in
``SimRig.run_blocks``). When SYNCs stop, the plant free-runs at the loop rate
with the valve's spool as it is (held, then nulled by the valve's set-point
watchdog), so the sensors keep streaming.

Each emulated rig gets a CAN channel of its own (:func:`private_channel`), so
two runs on one machine never share a bus; except the one `rig emulate` serves
(``private=False``: the profile's channel and ports), which other processes
(`rig run`, `rig devices check`) reach with the same profile; `rig run` finds it
by its control socket (:class:`EmulatorService`, :class:`RemoteEmulator`) and
homes its plant through it instead of starting emulators of its own.

:func:`start_emulator_process` runs it in its own process (the GIL) and
returns an :class:`EmulatorHandle` (``inject(device, fault, value)``,
``stop()``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

from drivers.config import HardwareConfig, parse_hardware
from drivers.emulators.lvdt_streamer import LvdtStreamer
from drivers.emulators.modbus_io import IoState, io_server_main
from drivers.emulators.modbus_conditioner import (
    ModbusConditionerEmulator, SharedSample, free_tcp_port, modbus_server_main,
)
from drivers.linux import serve_private_socket, set_pdeathsig, set_process_name
from drivers.emulators.pty import PtyBridge
from drivers.emulators.valve_controller import ValveControllerEmulator
from drivers.valve import SW_WATCHDOG
from rig.sim import SimRig
from rig.sim.plant import Z_XSP

SENSOR_KEYS = ("position_um", "friction_N", "normal_1_N", "normal_2_N")


class IntegratorPlant:
    """A stand-in plant for driver tests: the valve command is a velocity.

    ``x += cmd * v_full_um_s * dt``; friction = ``mu * N * sign(v)`` (both
    interfaces), constant normal forces. Deterministic.
    """

    def __init__(self, dt_s: float = 1e-3, v_full_um_s: float = 1000.0, normal_N: float = 100.0,
                 mu: float = 0.1, x0_um: float = 0.0):
        self.dt_s, self.v_full_um_s, self.normal_N, self.mu = dt_s, v_full_um_s, normal_N, mu
        self.x_um = x0_um
        self.t_s = 0.0

    def reset(self, x0_um: float, v_init_um_s: float | None = None) -> None:
        self.x_um = float(x0_um)

    def plant_step(self, valve_cmd: float) -> dict:
        v = valve_cmd * self.v_full_um_s
        self.x_um += v * self.dt_s
        self.t_s += self.dt_s
        f = 2.0 * self.mu * self.normal_N * (1.0 if v > 0 else -1.0 if v < 0 else 0.0)
        return {"position_um": self.x_um, "friction_N": f, "normal_1_N": self.normal_N,
                "normal_2_N": self.normal_N}


def sim_plant(profile, lubricant: str | None = None, normal_force_N: float | None = None,
              seed: int = 1):
    """The simulated rig (:class:`rig.sim.SimRig`) as the emulators' plant."""
    lub = lubricant or "paraffin"
    model = profile.friction_model(lub)
    kwargs = {"seed": seed}
    if normal_force_N is not None:
        kwargs["normal_force_N"] = normal_force_N
    return SimRig(profile, model, **kwargs)


class _RemoteModbus:
    """The plant side of a Modbus server running in its own process."""

    def __init__(self, shared: SharedSample):
        self.shared = shared
        self.counter = 0
        self.status = 0
        self.n_requests = 0
        self.faults: dict = {}

    def update(self, friction_N, normal_1_N, normal_2_N):
        if not self.shared.faults[3]:  # freeze_counter
            self.counter = (self.counter + 1) & 0xFFFF
        self.shared.write((friction_N, normal_1_N, normal_2_N), self.counter, self.status)


class EmulatedRig:
    """Modbus conditioner + LVDT streamer + valve controller around one plant."""

    def __init__(self, hw: HardwareConfig, plant, period_s: float = 1e-3, modbus_process: bool = False):
        self.hw = hw
        self.plant = plant
        self.period_s = period_s
        em = hw.emulators
        Path(em.run_dir).mkdir(parents=True, exist_ok=True)
        self.bridge = None
        rtu_server_port = None
        if hw.loadcells.transport == "rtu":
            rtu_server_port = hw.loadcells.serial_port + ".server"
        self.rtu_server_port = rtu_server_port
        self.modbus_process = modbus_process
        self._mb_proc = self._mb_conn = None
        if modbus_process:
            self.shared = SharedSample(mp.get_context("spawn"))
            self.modbus = _RemoteModbus(self.shared)
        else:
            self.shared = None
            self.modbus = ModbusConditionerEmulator(hw.loadcells, rtu_server_port=rtu_server_port)
        self.lvdt = LvdtStreamer(hw.lvdt)
        self.valve = ValveControllerEmulator(hw.valve, on_sync=self._on_sync)
        # the safety chain's I/O module (its own process): its relay gates the valve amplifier
        self.io = IoState(mp.get_context("spawn"), hw.safety.watchdog_s) if hw.safety is not None else None
        self._io_proc = self._io_conn = None
        self.last = {k: 0.0 for k in SENSOR_KEYS}
        self.steps = 0
        self.free_steps = 0
        self.lock_steps = 0
        self.max_gap_s = 0.0   # longest time between two plant steps while serving
        self.gaps_over_5ms = 0
        self._last_step_t = None
        self.running = False
        self._was_enabled = False
        self.t_disabled = None  # when the valve last went from enabled to disabled (time.monotonic)

    def start(self) -> None:
        if self.hw.loadcells.transport == "rtu":
            self.bridge = PtyBridge(self.hw.loadcells.serial_port,
                                    self.hw.loadcells.serial_port + ".server")
        self.lvdt.start()
        self.valve.start()
        em = self.hw.emulators
        prio = em.priority if em.sched_fifo else 0
        if self.modbus_process:
            self._mb_proc, self._mb_conn = _start_server_process(
                modbus_server_main, "rig-emulator-modbus", "Modbus emulator",
                (self.hw.loadcells.model_dump(), self.shared, self.rtu_server_port, prio))
        else:
            self.modbus.start()
        if self.io is not None:
            self._io_proc, self._io_conn = _start_server_process(
                io_server_main, "rig-emulator-io", "I/O module emulator", (self.hw.safety.model_dump(), self.io, prio))
        self.step(0.0)

    def stop(self) -> None:
        self.running = False
        if self._mb_proc is not None:
            _stop_process(self._mb_proc, self._mb_conn)
        else:
            self.modbus.stop()
        if self._io_proc is not None:
            _stop_process(self._io_proc, self._io_conn)
        self.valve.stop()
        self.lvdt.stop()
        if self.bridge is not None:
            self.bridge.close()

    def step(self, cmd: float) -> None:
        now = time.monotonic()
        if self._last_step_t is not None and self.running:
            gap = now - self._last_step_t
            if gap > self.max_gap_s:
                self.max_gap_s = gap
            if gap > 0.005:
                self.gaps_over_5ms += 1
        self._last_step_t = now
        if self.io is not None and not self.io.amplifier_enabled(now):
            cmd = 0.0  # the amplifier is off (e-stop, enable output off, watchdog): the spool centres
        out = self.plant.plant_step(float(cmd))
        vals = {k: float(out[k]) for k in SENSOR_KEYS}
        self.last = vals
        self.steps += 1
        self.modbus.update(vals["friction_N"], vals["normal_1_N"], vals["normal_2_N"])
        self.lvdt.send(vals["position_um"])

    def modbus_requests(self) -> int:
        if self._mb_proc is None:
            return self.modbus.n_requests
        try:
            self._mb_conn.send(("stats",))
            if self._mb_conn.poll(1.0):
                return int(self._mb_conn.recv()[1])
        except (OSError, EOFError):
            pass
        return -1

    def _on_sync(self, spool: float) -> float | None:
        """One plant step per SYNC; returns the plant's spool position (what the valve's spool
        LVDT reports in its status PDO), or None for a plant without a spool model."""
        self.step(spool)
        self.lock_steps += 1
        en = self.valve.enabled
        if self._was_enabled and not en:
            self.t_disabled = time.monotonic()  # CLOCK_MONOTONIC: comparable across processes
        self._was_enabled = en
        st = getattr(self.plant, "st", None)
        return float(st[Z_XSP]) if st is not None else None

    def inject(self, device: str, fault: str, value=True) -> None:
        """Set (value) or clear (None/False) a fault on 'loadcells', 'lvdt', 'valve' or 'safety'
        (``estop``: the e-stop pressed; ``pressure_lost``: the hydraulic pressure gone)."""
        if device == "safety":
            if self.io is None:
                raise EmulatorError("the profile has no safety chain (hardware.safety)")
            on = value not in (None, False)
            {"estop": self.io.press_estop, "pressure_lost": self.io.lose_pressure}[fault](on)
            return
        if device == "lvdt" and fault == "vanish":
            if value:
                self.lvdt.vanish()
            return
        if device == "loadcells" and self.shared is not None:
            self.shared.set_fault(fault, value)
            return
        if device == "valve":
            self.valve.inject(fault, None if value is False else value)
            return
        target = {"loadcells": self.modbus, "lvdt": self.lvdt}[device]
        if value is None or value is False:
            target.faults.pop(fault, None)
        else:
            target.faults[fault] = value

    def run(self, should_stop=lambda: False, on_idle=None, max_s: float | None = None) -> None:
        """Serve until ``should_stop()``.

        The plant steps once per SYNC (lock step with the host, in ``_on_sync``);
        when the next SYNC is more than half a period late, the plant steps on its
        own clock with the valve's spool as it is (zero-order hold, as a real plant
        keeps moving; nulled once the valve's watchdog or heartbeat consumer trips).
        """
        self.running = True
        valve = self.valve
        dt = self.period_s
        t_start = time.monotonic()
        next_free = t_start + dt
        next_idle = t_start
        while self.running:
            now = time.monotonic()
            if now >= next_idle:
                next_idle = now + 0.005
                if on_idle is not None:
                    on_idle()
                if should_stop() or (max_s is not None and now - t_start > max_s):
                    break
            timeout = max(0.0, min(next_free, next_idle) - now)
            n0 = valve.n_sync
            valve.poll(timeout)
            now = time.monotonic()
            if valve.n_sync != n0:
                next_free = now + 1.5 * dt
            elif now >= next_free:
                self.step(valve.spool)
                self.free_steps += 1
                next_free += dt
                if next_free < now:
                    next_free = now + dt  # skip, don't bunch
        self.running = False


def _start_server_process(target, name: str, what: str, args: tuple):
    """A server process of the emulated rig (``target(*args, conn)``), once it says it is ready."""
    ctx = mp.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=target, name=name, daemon=True, args=(*args, child))
    proc.start()
    if not conn.poll(30):
        raise RuntimeError(f"{what} process did not start")
    kind, payload = conn.recv()
    if kind != "ready":
        raise EmulatorError(str(payload))
    return proc, conn


def _stop_process(proc, conn) -> None:
    """Ask a server process of the emulated rig to stop; kill it after 3 s."""
    try:
        conn.send(("stop",))
    except OSError:
        pass
    proc.join(3)
    if proc.is_alive():
        proc.kill()


# -- its own process -------------------------------------------------------------------

def _emulator_main(hw_dict, profile, lubricant, normal_force_N, seed, conn, plant_kind):
    """The emulator process: build and start the emulated rig, say ``ready`` (or ``error``), serve the
    parent's requests between steps until ``stop``, SIGTERM or the parent's end."""
    import logging
    import sys

    set_pdeathsig()
    set_process_name("rig-emulator")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    sys.setswitchinterval(1e-4)  # the Modbus server thread must not wait 5 ms for the GIL
    hw = parse_hardware(hw_dict)
    stop = {"flag": False}

    def _term(*_):
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        rig = _start_emulated_rig(hw, profile, lubricant, normal_force_N, seed, plant_kind)
    except BaseException as exc:  # noqa: BLE001
        conn.send(("error", str(exc) if isinstance(exc, (EmulatorError, RuntimeError))
                   else f"{type(exc).__name__}: {exc}"))
        return
    import gc

    gc.collect()
    gc.freeze()  # a full collection would scan numba's objects too (tens of ms)
    conn.send(("ready", None))

    def on_idle():
        while conn.poll():
            try:
                req = conn.recv()
            except EOFError:
                stop["flag"] = True
                return
            if req[0] == "stop":
                stop["flag"] = True
            else:
                _serve_request(rig, req, conn)

    try:
        rig.run(should_stop=lambda: stop["flag"], on_idle=on_idle)
    finally:
        rig.stop()
        try:
            conn.send(("stopped", None))
        except Exception:  # noqa: BLE001
            pass


def _start_emulated_rig(hw, profile, lubricant, normal_force_N, seed, plant_kind) -> "EmulatedRig":
    """The emulated rig on its CPU (``emulators.cpu``, inherited by the Modbus server process) and at
    SCHED_FIFO when the profile asks (both best effort), its plant compiled, started."""
    if hw.emulators.cpu is not None:  # before the Modbus server process is started: it inherits it
        try:
            os.sched_setaffinity(0, {hw.emulators.cpu})
        except (OSError, AttributeError):
            pass
    if plant_kind == "integrator":
        plant = IntegratorPlant()
    else:
        plant = sim_plant(profile, lubricant, normal_force_N, seed)
        plant.plant_step(0.0)  # compile (numba) before serving
    rig = EmulatedRig(hw, plant, 1.0 / _rate_of(profile), modbus_process=True)
    if hw.emulators.sched_fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(hw.emulators.priority))
        except (OSError, AttributeError):
            pass
    rig.start()
    return rig


def _serve_request(rig: "EmulatedRig", req: tuple, conn) -> None:
    """One request of the parent process: ``inject`` a fault, ``stats``, ``reset`` the plant."""
    op = req[0]
    if op == "inject":
        rig.inject(*req[1:])
        conn.send(("ok", None))
    elif op == "stats":
        conn.send(("stats", {"steps": rig.steps, "lock_steps": rig.lock_steps,
                             "free_steps": rig.free_steps, "last": rig.last,
                             "valve_enabled": rig.valve.enabled,
                             "valve_output": rig.valve.spool,
                             "valve_watchdog": bool(rig.valve.latched & SW_WATCHDOG),
                             "valve": rig.valve.stats(), "t_valve_disabled": rig.t_disabled,
                             "n_setpoints": rig.valve.n_setpoints,
                             "modbus_requests": rig.modbus_requests(),
                             "lvdt_sent": rig.lvdt.sent, "max_gap_s": rig.max_gap_s,
                             "gaps_over_5ms": rig.gaps_over_5ms,
                             "lvdt_overflow": rig.lvdt.overflow,
                             "safety": rig.io.snapshot() if rig.io is not None else None}))
    elif op == "reset":
        x0, v0 = req[1], req[2]
        rig.plant.reset(x0, v0)
        rig.step(0.0)
        conn.send(("ok", None))


def _rate_of(profile) -> float:
    return 1000.0 if profile is None else float(profile.loop.rate_hz)  # the integrator plant has no profile


class EmulatorError(RuntimeError):
    pass


class EmulatorHandle:
    """The emulated rig's process; ``hw``: the hardware section it serves (its private CAN channel)."""

    def __init__(self, proc, conn, hw: HardwareConfig | None = None):
        self.proc = proc
        self.conn = conn
        self.hw = hw

    def _call(self, *req, timeout: float = 2.0):
        self.conn.send(req)
        if not self.conn.poll(timeout):
            raise EmulatorError(f"emulator did not answer {req[0]!r}")
        return self.conn.recv()[1]

    def inject(self, device: str, fault: str, value=True):
        return self._call("inject", device, fault, value)

    def stats(self) -> dict:
        return self._call("stats")

    def reset_plant(self, x0_um: float, v_init_um_s: float | None = None):
        """Put the simulated test piece at rest at ``x0_um`` (the rig being homed)."""
        return self._call("reset", float(x0_um), v_init_um_s)

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.is_alive():
            try:
                self.conn.send(("stop",))
            except (OSError, BrokenPipeError):
                pass
            self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(1)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def private_channel(hw: HardwareConfig) -> HardwareConfig:
    """``hw`` with a CAN channel of its own (``<channel>-<pid>-<n>``) on the machine-local bus, so that
    two emulated rigs (two runs, two tests) never share a bus; other interfaces are left alone."""
    if hw.valve.interface != "rig_unix":
        return hw
    global _CHANNELS
    _CHANNELS += 1
    name = f"{hw.valve.channel[:40]}-{os.getpid()}-{_CHANNELS}-{int(time.time() * 1e3) % 100000}"
    return hw.model_copy(update={"valve": hw.valve.model_copy(update={"channel": name})})


_CHANNELS = 0


def start_emulator_process(hw: HardwareConfig | dict, profile=None, lubricant: str | None = None,
                           normal_force_N: float | None = None, seed: int | None = None,
                           plant: str = "sim", timeout_s: float = 60.0, private: bool = True) -> EmulatorHandle:
    """Start the emulated rig in its own process on a private CAN channel (``handle.hw``: the hardware
    section to drive it with; ``private=False``: the channel of ``hw``, for a ``rig run`` in another
    process given the same profile); returns when its devices answer."""
    hw = parse_hardware(hw) if not isinstance(hw, HardwareConfig) else hw
    if private:
        hw = private_channel(hw)
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    em = hw.emulators
    # not a daemon: it starts the Modbus server process; stopped by the handle (atexit too)
    proc = ctx.Process(target=_emulator_main, name="rig-emulator", daemon=False,
                       args=(hw.model_dump(), profile, lubricant or em.lubricant,
                             normal_force_N if normal_force_N is not None else em.normal_force_N,
                             em.seed if seed is None else seed, child, plant))
    proc.start()
    t_end = time.monotonic() + timeout_s
    while not parent.poll(0.05):
        if not proc.is_alive():
            raise EmulatorError(f"emulator process exited (code {proc.exitcode}) before it was ready")
        if time.monotonic() > t_end:
            proc.kill()
            raise EmulatorError(f"emulators did not start within {timeout_s:g} s")
    kind, payload = parent.recv()
    if kind != "ready":
        proc.join(2)
        raise EmulatorError(str(payload))
    handle = EmulatorHandle(proc, parent, hw)
    for device, faults in em.faults.items():  # the profile's emulator faults (issue 21: a drifted bridge in CI)
        for fault, value in faults.items():
            handle.inject(device, fault, value)
    import atexit

    atexit.register(handle.stop, 2.0)
    return handle


# -- serving other processes (`rig emulate`) ------------------------------------------------------------

def control_socket_path(hw: HardwareConfig) -> Path:
    """Where `rig emulate` listens for the plant's reset by a `rig run` in another process."""
    return Path(hw.emulators.run_dir) / "emulate.sock"


class EmulatorService:
    """Serves ``handle``'s ``reset_plant`` on a Unix socket owned by this user (mode 0600), one JSON line
    per request: ``{"op": "reset", "x0_um": .., "v_init_um_s": ..}`` or ``{"op": "hello"}``."""

    def __init__(self, handle: EmulatorHandle, path: Path):
        import threading

        self.handle, self.path = handle, Path(path)
        if self.path.exists():
            if RemoteEmulator.connect(handle.hw, self.path) is not None:
                raise EmulatorError(f"another `rig emulate` already serves {self.path}")
            self.path.unlink()
        self._lock = threading.Lock()
        self.sock = serve_private_socket(self.path, self._answer, "rig-emulate-control")

    def _answer(self, line: str) -> str:
        import json

        try:
            req = json.loads(line or "{}")
            with self._lock:
                if req.get("op") == "reset":
                    self.handle.reset_plant(float(req["x0_um"]), req.get("v_init_um_s"))
            return '{"ok": true}'
        except (ValueError, KeyError, EmulatorError) as exc:
            return json.dumps({"ok": False, "error": str(exc)})

    def close(self) -> None:
        try:
            self.sock.close()
        finally:
            self.path.unlink(missing_ok=True)


class RemoteEmulator:
    """The emulated rig a `rig emulate` in another process serves (the profile's own channel and ports):
    what :class:`rig.session.hardware.HardwareBackend` drives instead of starting its own."""

    def __init__(self, hw: HardwareConfig, path: Path):
        self.hw, self.path = hw, Path(path)

    @classmethod
    def connect(cls, hw: HardwareConfig, path: Path | None = None) -> "RemoteEmulator | None":
        """The one serving ``hw`` (its run_dir's socket answers), else None."""
        em = cls(hw, path or control_socket_path(hw))
        if not em.path.exists():
            return None
        try:
            em._call({"op": "hello"})
        except EmulatorError:
            return None
        return em

    def _call(self, req: dict) -> dict:
        import json
        import socket

        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(3.0)
                s.connect(str(self.path))
                s.sendall((json.dumps(req) + "\n").encode())
                ans = json.loads(s.makefile("r").readline() or "{}")
        except (OSError, ValueError) as exc:
            raise EmulatorError(f"the emulators at {self.path} did not answer: {exc}") from None
        if not ans.get("ok"):
            raise EmulatorError(f"the emulators at {self.path}: {ans.get('error', 'no answer')}")
        return ans

    def reset_plant(self, x0_um: float, v_init_um_s: float | None = None):
        return self._call({"op": "reset", "x0_um": float(x0_um), "v_init_um_s": v_init_um_s})

    def stop(self, timeout: float = 0.0) -> None:
        """Not ours to stop (the `rig emulate` that serves it is)."""


__all__ = ["EmulatedRig", "IntegratorPlant", "start_emulator_process", "EmulatorHandle", "EmulatorService",
           "EmulatorError", "RemoteEmulator", "control_socket_path", "sim_plant", "emulated_hardware",
           "free_tcp_port"]


def emulated_hardware(run_dir: str | os.PathLike, transport: str = "tcp",
                      modbus_port: int | None = None, **overrides) -> HardwareConfig:
    """A hardware section pointing at emulators private to ``run_dir`` (free ports, own CAN channel)."""
    run_dir = str(run_dir)
    d = {
        "loadcells": {"transport": transport, "host": "127.0.0.1",
                      "port": modbus_port or free_tcp_port(),
                      "serial_port": f"{run_dir}/loadcells-rtu" if transport == "rtu" else None,
                      "timeout_s": 0.01},
        "lvdt": {"port": f"{run_dir}/lvdt", "baudrate": 921600},
        "valve": {"interface": "rig_unix", "channel": f"emu-{os.getpid()}-{Path(run_dir).name}"[:64]},
        "emulators": {"autostart": True, "run_dir": run_dir},
    }
    for k, v in overrides.items():
        d.setdefault(k, {}).update(v)
    return parse_hardware(d)
