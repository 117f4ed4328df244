"""The hardware as a session backend (``rig run --hardware PROFILE``).

:class:`HardwareBackend` starts the emulated rig when the profile says
``hardware.emulators.autostart`` (``config/rigs/emulated.yaml``;
:mod:`rig.hardware.emulated`), then the 1 kHz loop process
(:mod:`rig.hardware.loop`), and turns what the loop sends into the session's
:class:`Block` / :class:`Event`. It keeps the loop's
timing statistics (lateness, period, execution time; a window every second
and the whole trial). A stop request sets the loop's abort flag (the loop
holds the position for ``stop_hold_s`` with the reference frozen, then nulls
and disables the valve); an insisted one terminates the loop process (the
valve controller's watchdog nulls the valve). If the loop process dies
(kill -9), the run ends with what was received.

It lives in the session layer (it speaks the session's :class:`Block`,
:class:`Event`, :class:`Ending`); the loop, the devices, the interlocks and
the emulated rig it drives are :mod:`rig.hardware`'s.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_mod
import time

import numpy as np

from drivers.config import HardwareConfig
from rig.hardware.emulated import EmulatorError, start_emulator_process
from rig.hardware.loop import ABORT_FAIL, ABORT_OPERATOR, loop_main
from rig.hardware.timing import TimingStats, format_stats
from rig.session.core import BackendError, Block, Ending, Event, Outcome
from rig.session.pausing import pause_options
from rig.model.feedforward import friction_feedforward_for_plan, initial_velocity_um_s


class HardwareBackend:
    """The rig of ``hw`` (a :class:`drivers.config.HardwareConfig`) as a :class:`rig.session.Backend`.

    ``emulator``: an already started :class:`rig.hardware.emulated.EmulatorHandle`
    (tests, loop-bench); otherwise the emulators are started here when
    ``hw.emulators.autostart``. ``lubricant``, ``normal_force_N``, ``seed``:
    for the emulated plant.
    """

    name = "hardware"
    log_flush_interval_s = 0.5  # real time: a crashed logger loses at most about half a second

    def __init__(self, hw: HardwareConfig, profile, *, emulator=None, lubricant: str | None = None,
                 normal_force_N: float | None = None, seed: int | None = None, controller: bool = True):
        self.hw = hw
        self.profile = profile
        self.emulator = emulator
        if emulator is not None and getattr(emulator, "hw", None) is not None:
            self.hw = emulator.hw  # the emulated rig's private CAN channel
        self._own_emulator = None
        self.logger_ack = None
        self.logger_alive = None
        self._blocks_logged = 0
        self.lubricant, self.normal_force_N, self.seed = lubricant, normal_force_N, seed
        self.controller = controller
        self.proc = None
        self.q = None
        self.abort = None
        self.pause_req = None
        self.safety_link = None  # the safety chain's link process (drivers.safety_io.SafetyLink)
        self.rate_hz = 1000.0
        self.stats = TimingStats(1e-3)
        self.read_max_s = 0.0  # the devices' read phase of a tick
        self.read_slow = 0
        self.skips: list = []  # (CLOCK_MONOTONIC, cycles skipped) of every late tick: attributed by loop-bench
        self._devices: dict = {}
        self._done: dict | None = None
        self._realtime: dict | None = None
        self._t_last = 0.0
        self._stop_reason: str | None = None

    @property
    def heartbeat_priority(self) -> int | None:
        """SCHED_FIFO priority of the session's heartbeat thread (below the loop's), None: not real-time."""
        rt = self.hw.realtime
        return max(1, rt.priority - 20) if rt.sched_fifo else None

    def describe(self) -> dict:
        return {"loadcells": self.hw.loadcells.address_text, "lvdt": self.hw.lvdt.address_text,
                "valve": self.hw.valve.address_text,
                "emulated": self.emulator is not None or self.hw.emulators.autostart}

    # -- start -----------------------------------------------------------------
    def start(self, plan) -> None:
        from rig.hardware.safety import latched_message

        latched = latched_message(self.hw.safety, str(getattr(self.profile, "source_path", None) or "PROFILE"))
        if latched:  # an e-stop or a pressure loss latched the chain: nothing starts until `rig reset`
            raise BackendError(latched)
        self.rate_hz = float(plan.loop_rate_hz)
        self.stats = TimingStats(1.0 / self.rate_hz)
        x_ref = np.asarray(plan.x_ref_um, dtype=float)
        if self.emulator is None and self.hw.emulators.autostart:
            from rig.hardware.emulated import RemoteEmulator

            self.emulator = RemoteEmulator.connect(self.hw)  # a `rig emulate` serving this profile
        if self.emulator is None and self.hw.emulators.autostart:
            try:
                self._own_emulator = self.emulator = start_emulator_process(
                    self.hw, self.profile, lubricant=self.lubricant, normal_force_N=self.normal_force_N,
                    seed=self.seed)
            except EmulatorError as exc:
                raise BackendError(str(exc)) from None
            self.hw = self.emulator.hw
        if self.emulator is not None:
            try:
                self.emulator.reset_plant(float(x_ref[0]), initial_velocity_um_s(
                    x_ref, self.rate_hz, self.profile.sim.initial_creep_um_s))
            except EmulatorError as exc:
                raise BackendError(str(exc)) from None
        switches = dict(getattr(plan, "controller", None) or {})
        ff_N = np.empty(0)
        if switches.get("friction_ff", False):
            # the rig knows the profile's identified single-state law of the recipe's lubricant
            if not self.lubricant:
                raise BackendError("the recipe asks for friction feed-forward (controller.friction_ff) but "
                                   "names no lubricant whose model the profile has")
            try:
                model = self.profile.friction_model(self.lubricant)
            except ValueError as exc:
                raise BackendError(f"friction feed-forward: {exc}") from None
            nf = float(self.normal_force_N or self.profile.normal.nominal_force_N)
            ff_N = friction_feedforward_for_plan(switches, x_ref, 1.0 / self.rate_hz, model, 2.0 * nf,
                                                 initial_velocity_um_s(x_ref, self.rate_hz,
                                                                       self.profile.sim.initial_creep_um_s))
        ctx = mp.get_context("spawn")
        self.q = ctx.Queue()
        self.abort = ctx.Value("i", 0, lock=False)
        self.logger_ack = ctx.Value("q", 0, lock=False)
        self.logger_alive = ctx.Value("d", 0.0, lock=False)
        self.pause_req = ctx.Value("i", 0, lock=False)
        popt = pause_options(plan, self._friction_model())
        link = None
        if self.hw.safety is not None:  # its own process, started here: the loop's process may not start one
            from drivers.errors import DeviceError
            from rig.hardware.devices import safety_link

            self.safety_link = safety_link(self.hw)
            try:
                self.safety_link.connect()
                link = self.safety_link.link
            except DeviceError as exc:  # named by the loop with every other device that does not answer
                link = (self.safety_link.shm, None, exc.message)
                self.safety_link = None
        self.proc = ctx.Process(target=loop_main, name="rig-rt-loop", daemon=True,
                                args=(self.hw.model_dump(), self.profile, x_ref, self.q, self.abort,
                                      {"period_s": 1.0 / self.rate_hz, "controller": self.controller,
                                       "switches": switches, "ff_N": ff_N, "safe_ticks": popt["safe_ticks"],
                                       "runup_um": popt["runup_um"], "safety_link": link},
                                      self.logger_ack, self.logger_alive, self.pause_req))
        self.proc.start()

    # -- run -------------------------------------------------------------------
    def receive(self) -> Block | Event | None:
        if self._done is not None:
            return None
        while True:
            try:
                msg = self.q.get(timeout=0.25)
                break
            except queue_mod.Empty:
                if not self.proc.is_alive():
                    try:  # what it sent before dying
                        msg = self.q.get(timeout=0.5)
                        break
                    except queue_mod.Empty:
                        self._done = {"status": "loop_died", "exitcode": self.proc.exitcode,
                                      "message": f"the loop process died (exit code {self.proc.exitcode}); "
                                                 f"log kept up to t={self._t_last:.3f} s"}
                        return Event(self._t_last, "loop_died", {"exitcode": self.proc.exitcode})
        kind = msg[0]
        if kind == "block":
            blk, tim = msg[1], msg[2]
            self.stats.add(tim["late_s"], tim["period_s"], tim["exec_s"], tim["skipped"])
            rd = tim["read_s"]
            if rd.size:
                self.read_max_s = max(self.read_max_s, float(rd.max()))
                self.read_slow += int((rd > 1e-3).sum())
            self._devices = tim.get("devices", self._devices)
            self.skips.extend(tim.get("skips", ()))
            self._t_last = float(blk["t_s"][-1])
            return Block(blk, tim.get("wall_ns"))  # issue 21: the wall-clock time of its last tick
        if kind == "event":
            _, t_s, ev, data = msg
            return Event(float(t_s), ev, {k: v for k, v in data.items() if k not in ("t_s", "kind")})
        if kind == "info":
            self._realtime = msg[1]["realtime"]
            return Event(0.0, "realtime", dict(self._realtime))
        if kind == "done":
            self._done = msg[1]
            return None
        raise RuntimeError(f"unknown message from the loop process: {kind!r}")

    def _friction_model(self):
        """The profile's model of the trial's lubricant (its L sets the run-up after a pause), or None."""
        try:
            return self.profile.friction_model(self.lubricant) if self.lubricant else None
        except (ValueError, KeyError, AttributeError):
            return None

    def pause(self, realtime: bool = True) -> None:
        """Hold at the plan's next safe point (the loop's :class:`trajectories.pause.PausableReference`)."""
        if self.pause_req is not None:
            self.pause_req.value = 1

    def resume(self) -> None:
        """Run up at the segment's velocity, then the plan goes on."""
        if self.pause_req is not None:
            self.pause_req.value = 0

    def block_logged(self) -> None:
        """The session has logged one more block (the loop trips if the logger stops taking them)."""
        self._blocks_logged += 1
        if self.logger_ack is not None:
            self.logger_ack.value = self._blocks_logged

    def heartbeat(self) -> None:
        """The logger is alive (the session's monitor thread, every few ms): the loop trips when the
        heartbeat is older than ``interlocks.logger_heartbeat_s`` (a killed logger stops at once)."""
        if self.logger_alive is not None:
            self.logger_alive.value = time.monotonic()

    def fail_stop(self, reason: str) -> None:
        """The session failed (its log): the loop nulls and disables the valve at its next tick (no hold).
        Safe to call from any thread."""
        self._stop_reason = reason
        if self.abort is not None:
            self.abort.value = ABORT_FAIL

    def request_stop(self, reason: str, insist: bool = False) -> None:
        self._stop_reason = reason
        if self.abort is not None and self.abort.value != ABORT_FAIL:
            self.abort.value = ABORT_OPERATOR  # controlled stop: the loop holds, nulls, disables
        if insist and self.proc is not None and self.proc.is_alive():
            self.proc.terminate()  # insisted: the loop stops now (the valve watchdog nulls the valve)

    def stats_window(self) -> dict:
        w = self.stats.window()
        w.pop("late_hist_edges_us", None)
        w.update(self._devices)  # cumulative device counters
        return w

    def finish(self) -> Ending:
        s = dict(self._done or {"status": "loop_died", "message": "the loop process ended without a summary"})
        final = self.stats.final()
        final["read_max_us"] = self.read_max_s * 1e6
        final["read_over_1ms"] = self.read_slow
        s["timing"] = final
        s["realtime"] = self._realtime
        s["skips"] = list(self.skips)
        status = s.get("status")
        outcome = {"completed": Outcome.COMPLETED, "aborted": Outcome.STOPPED,
                   "tripped": Outcome.TRIPPED}.get(status, Outcome.FAILED)
        vf = s.get("valve_final") or {}
        # safe: the loop reached its safe state and the valve confirms it is disabled (a dead loop or a
        # silent valve cannot confirm anything: the valve controller's watchdog is what nulls it then)
        safe = status in ("completed", "aborted", "tripped") and bool(vf) and not vf.get("enabled", True) \
            and vf.get("confirmed", False)
        if "devices_failed" in s:
            safe = True  # the devices did not answer before the start: nothing was ever enabled
        s["safe_state"] = (f"valve status word 0x{vf.get('status_bits', 0):04x}, enabled {vf.get('enabled')}, "
                           f"spool {vf.get('output')}, NMT {vf.get('nmt')}, confirmed {vf.get('confirmed')} "
                           f"(from its {vf.get('source', 'status PDO')})") if vf else ""
        sf = s.get("safety_final")
        if sf:
            s["safe_state"] += f"; safety chain: {sf['state']}, amplifier enable output off {sf['enable_output_off']}"
            safe = safe and sf["enable_output_off"]
        msg = s.get("message") or ("" if status == "completed" else str(status))
        return Ending(outcome, msg, safe=safe, summary=s, final_stats=dict(final) if final.get("n") else None,
                      report=format_stats(final, "loop timing (whole trial)") if final.get("n") else "")

    def close(self) -> None:
        if self.proc is not None:
            self.proc.join(3)
            if self.proc.is_alive():
                self.proc.terminate()
                self.proc.join(2)
        if self.safety_link is not None:
            self.safety_link.close()
            self.safety_link = None
        if self._own_emulator is not None:
            self._own_emulator.stop()
            self._own_emulator = None
