"""One trial session over a :class:`Backend`: the plan in, the log out.

:class:`TrialSession` runs a compiled plan (:class:`trajectories.Plan`) on a
backend (the simulated rig, :class:`rig.session.sim.SimBackend`; the hardware,
:class:`rig.session.hardware.HardwareBackend`) and is the only code that:

* logs the planned events as the backend's blocks reach them, the
  ``trial_start`` event, the backend's own events (interlocks, loop start);
* writes every block to the log writer;
* logs loop statistics every ``stats_every_s`` of trial time (ticks, wall time,
  real-time factor, tracking error, valve saturation; plus the backend's own
  window figures, e.g. the hardware loop's lateness);
* handles stopping, as a small explicit state machine (:class:`StopMachine`):
  ``RUNNING -> STOPPING -> SAFE -> DONE``, with the reason and its cause.
  Ctrl-C / SIGTERM / SIGHUP (or a KeyboardInterrupt raised while the session runs) asks
  the backend for a controlled stop; the session keeps logging what the
  backend still sends (the hardware holds position, then nulls and disables
  the valve) until the backend says it is safe. A third signal insists (the
  hardware loop is terminated; the valve controller's watchdog nulls the valve).
* closes the log with the status: ``completed``, ``interrupted`` or ``failed`` (one
  :class:`Outcome` decides the status and the logged cause);
* passes the operator's pause and resume (SIGUSR1, `rig pause` / `rig resume`:
  :class:`rig.session.pausing.PauseControl`) to a backend that can pause, and
  schedules the plan's events later by the time a pause added (``pause`` ...
  ``runup_done`` events of the backend), so that each is logged when it happens.

The writer is a :class:`TrialWriter` (:class:`rig.log.TrialLogWriter`, or
:class:`rig.session.memory.MemoryLog`). What a backend or a writer can do beyond
that is a small capability protocol, asked with ``isinstance``: :class:`Pausable`,
:class:`LoggerWatched` (``block_logged``, ``heartbeat``), :class:`FailStoppable`
(``fail_stop``), :class:`FlushPaced` (``log_flush_interval_s``) and, of a writer,
:class:`Anchored` (``anchor``).
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Callable, Protocol, runtime_checkable

from rig.log.figures import BlockFigures  # the figures of the logged samples (one accumulator)


# the signals that ask for an operator's stop (safe stop, finished log, exit 130): Ctrl-C, SIGTERM
# (a service manager, `kill`) and SIGHUP (the operator's terminal or SSH session went away: a trial
# must not be cut off mid-block with an unfinished log by that)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def detach_from_terminal() -> None:
    """The terminal is gone (SIGHUP): standard output and error that went to it go to /dev/null
    from now on, so that a message written while the trial stops is not an EIO that cuts the stop
    short and leaves the log unfinished. Output to a file or a pipe is kept."""
    import os
    import stat

    try:
        null = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return
    for fd in (1, 2):
        try:
            if stat.S_ISCHR(os.fstat(fd).st_mode):
                os.dup2(null, fd)
        except OSError:
            pass
    os.close(null)


# ---------------------------------------------------------------------------
# What a backend sends
# ---------------------------------------------------------------------------

@dataclass(slots=True)
class Block:
    """Loop samples: a dict of equal-length numpy arrays (``t_s`` and the block keys).

    ``wall_ns``: the wall-clock time (ns since the epoch) at which the block's LAST sample was
    taken, when the backend knows it (the hardware loop's tick, a paced or a starting simulation);
    the session anchors the log's clock on it (:meth:`rig.log.TrialLogWriter.anchor`).

    ``frozen``: the backend never writes these arrays again (the simulation's, fresh for every chunk), so the
    log's writer thread may encode them without a copy (:meth:`rig.log.TrialLogWriter.write_block`)."""

    data: dict
    wall_ns: int | None = None
    frozen: bool = False


@dataclass(slots=True)
class Event:
    """Something the backend observed at trial time ``t_s`` (``interlock``, ``loop_start``, ...)."""

    t_s: float
    kind: str
    data: dict = field(default_factory=dict)


class Outcome(str, Enum):
    """How a run ended: the one vocabulary of a trial's end.

    A backend's :class:`Ending`, the stop state machine's cause and the log's status are
    all this; the strings the log and the CLI show are its :attr:`value` (``trial_failed``'s
    ``status``), :attr:`cause` (``stop_state``'s and the summary's ``stop_cause``) and
    :attr:`status` (the log's status)."""

    COMPLETED = "completed"   # the plan ran to its end
    STOPPED = "stopped"       # a stop that was asked for: the operator (Ctrl-C, SIGTERM, SIGHUP)
    TRIPPED = "tripped"       # an interlock
    FAILED = "failed"         # a device, the loop process, the session itself (its log)

    @property
    def cause(self) -> str:
        """The stop's cause as logged: ``end_of_plan``, ``operator``, ``trip`` or ``failure``."""
        return {"completed": "end_of_plan", "stopped": "operator", "tripped": "trip"}.get(self.value, "failure")

    @property
    def status(self) -> str:
        """The log's status: ``completed``, ``interrupted`` (an operator's stop) or ``failed``."""
        return {"completed": "completed", "stopped": "interrupted"}.get(self.value, "failed")


@dataclass
class Ending:
    """How the backend's run ended.

    ``outcome``: an :class:`Outcome` (a string of one is accepted). ``safe``: the backend left
    its actuator safe (nulled, disabled), or has none. ``message``: one line for the operator.
    ``final_stats``: the backend's whole-trial statistics (logged once, with
    ``final: true``); ``report``: text for the operator (e.g. loop timing).
    """

    outcome: Outcome
    message: str = ""
    safe: bool = True
    summary: dict = field(default_factory=dict)
    final_stats: dict | None = None
    report: str = ""

    def __post_init__(self):
        self.outcome = Outcome(self.outcome)


class BackendError(RuntimeError):
    """The backend cannot run (e.g. a device does not answer); the message names what and where."""


@runtime_checkable
class Backend(Protocol):
    """What a trial runs on. One instance runs one trial.

    ``start(plan)`` prepares (devices connected, loop started) and raises
    :class:`BackendError` when it cannot; ``receive()`` returns the next
    :class:`Block` or :class:`Event`, or ``None`` once the run has ended (end of
    plan, stop done, trip, failure); ``request_stop(reason, insist)`` asks for
    a controlled stop and returns at once; ``stats_window()`` gives the
    backend's own statistics since the last call (merged into the session's
    ``loop_stats``); ``finish()`` says how the run ended; ``close()`` releases
    everything (idempotent, also after a failure).
    """

    name: str

    def describe(self) -> dict: ...

    def start(self, plan) -> None: ...

    def receive(self) -> Block | Event | None: ...

    def request_stop(self, reason: str, insist: bool = False) -> None: ...

    def stats_window(self) -> dict: ...

    def finish(self) -> Ending: ...

    def close(self) -> None: ...


# Capabilities a backend may have beyond :class:`Backend` (Bluesky's manner: one small protocol
# each, asked with isinstance, never a getattr probe)

@runtime_checkable
class Pausable(Protocol):
    """Holds at the plan's next safe point and runs up again (the operator's pause)."""

    def pause(self, realtime: bool = True) -> None: ...

    def resume(self) -> None: ...


@runtime_checkable
class LoggerWatched(Protocol):
    """Trips when the logger stops taking blocks (``block_logged`` after every logged block) or
    stops beating (``heartbeat``, every few ms from the session's monitor thread, at
    ``heartbeat_priority`` SCHED_FIFO when permitted; None: the thread's own)."""

    heartbeat_priority: int | None

    def block_logged(self) -> None: ...

    def heartbeat(self) -> None: ...


@runtime_checkable
class FailStoppable(Protocol):
    """Stops at once, without a hold, when the session fails (its log): from any thread."""

    def fail_stop(self, reason: str) -> None: ...


@runtime_checkable
class FlushPaced(Protocol):
    """Says how often (wall-clock seconds) its trial's log is flushed and fsync'd."""

    log_flush_interval_s: float


# ---------------------------------------------------------------------------
# What the log writer does
# ---------------------------------------------------------------------------

@runtime_checkable
class TrialWriter(Protocol):
    """Where a session logs one trial (:class:`rig.log.TrialLogWriter`, :class:`rig.session.memory.MemoryLog`).

    ``schedule_events(events)``: planned events (dicts with ``t_s`` and ``kind``), logged once a
    block reaches their time; ``event(t_s, kind, **data)``; ``write_block(block)`` (a dict of
    equal-length arrays with ``t_s``); ``loop_stats(t_s, stats)``; ``warm_up()``: load what the
    first block needs, before the backend starts; ``failure()``: the exception that stopped it,
    or None (asked every 5 ms by a monitor thread); ``close(status, timeout_s=..., **summary)``:
    finish the log with the status (an :attr:`Outcome.status`), never longer than ``timeout_s``.
    """

    def schedule_events(self, events) -> None: ...

    def event(self, t_s: float, kind: str, **data: Any) -> None: ...

    def write_block(self, block: dict) -> None: ...

    def loop_stats(self, t_s: float, stats: dict) -> None: ...

    def warm_up(self) -> None: ...

    def failure(self) -> BaseException | None: ...

    def close(self, status: str = "completed", *, timeout_s: float | None = None, **summary: Any) -> None: ...


@runtime_checkable
class Anchored(Protocol):
    """A writer whose log keeps the wall-clock time of the samples (:meth:`rig.log.TrialLogWriter.anchor`)."""

    def anchor(self, t_s: float, wall_ns: int) -> None: ...


# ---------------------------------------------------------------------------
# Stopping
# ---------------------------------------------------------------------------

class Phase(str, Enum):
    RUNNING = "running"
    STOPPING = "stopping"   # a stop was asked for (or the backend ended); not yet safe
    SAFE = "safe"           # the backend reports its actuator safe (nulled, disabled)
    DONE = "done"           # log closed


_ALLOWED = {
    Phase.RUNNING: {Phase.STOPPING},
    Phase.STOPPING: {Phase.SAFE, Phase.DONE},  # DONE directly: could not reach a safe state
    Phase.SAFE: {Phase.DONE},
    Phase.DONE: set(),
}


class StopMachine:
    """RUNNING -> STOPPING -> SAFE -> DONE, with the first reason given (later ones are counted).

    ``history`` keeps ``(phase, reason, monotonic time)`` of every transition. Its state is
    changed only through its methods (:meth:`request`, :meth:`overrule`, :meth:`safe`, :meth:`done`).
    """

    def __init__(self):
        self.phase = Phase.RUNNING
        self.outcome: Outcome | None = None
        self.reason = ""
        self.requests = 0
        self.history: list[tuple[Phase, str, float]] = [(Phase.RUNNING, "", time.monotonic())]

    def _go(self, phase: Phase, reason: str = "") -> None:
        if phase not in _ALLOWED[self.phase]:
            raise RuntimeError(f"stop state machine: {self.phase.value} -> {phase.value} is not allowed")
        self.phase = phase
        self.history.append((phase, reason, time.monotonic()))

    def request(self, outcome: Outcome, reason: str) -> bool:
        """A stop is asked for, ending the run with ``outcome``; True if this is the first request
        (RUNNING -> STOPPING)."""
        self.requests += 1
        if self.phase is not Phase.RUNNING:
            return False
        self.outcome, self.reason = Outcome(outcome), reason
        self._go(Phase.STOPPING, reason)
        return True

    def overrule(self, outcome: Outcome, reason: str) -> None:
        """A trip or a failure after the stop was asked for (during an operator's stop; the log
        could not be finished): the trial failed, for this reason. Only before DONE."""
        outcome = Outcome(outcome)
        if outcome not in (Outcome.TRIPPED, Outcome.FAILED):
            raise ValueError(f"stop state machine: only a trip or a failure overrules a stop, not {outcome.value}")
        if self.phase in (Phase.RUNNING, Phase.DONE):
            raise RuntimeError(f"stop state machine: nothing to overrule in {self.phase.value}")
        self.outcome, self.reason = outcome, reason

    def safe(self, detail: str = "") -> None:
        self._go(Phase.SAFE, detail)

    def done(self) -> None:
        self._go(Phase.DONE)

    @property
    def status(self) -> str:
        """The log's status: completed, interrupted or failed (:attr:`Outcome.status`)."""
        return "failed" if self.outcome is None else self.outcome.status

    @property
    def cause(self) -> str | None:
        """The stop's cause as logged (:attr:`Outcome.cause`), None while running."""
        return None if self.outcome is None else self.outcome.cause


# ---------------------------------------------------------------------------
# The session
# ---------------------------------------------------------------------------

@dataclass
class TrialResult:
    outcome: Outcome            # how the trial ended (status and cause below are its strings)
    reason: str                 # one line: why it stopped
    ticks: int
    duration_s: float           # trial time of the last logged sample
    wall_s: float
    figures: BlockFigures
    ending: Ending | None
    safe: bool                  # the backend ended safe
    close_error: str | None = None  # the log could not be finished (e.g. disk full)
    history: list = field(default_factory=list)

    @property
    def status(self) -> str:
        """completed | interrupted | failed"""
        return self.outcome.status

    @property
    def cause(self) -> str:
        """end_of_plan | operator | trip | failure"""
        return self.outcome.cause

    @property
    def summary(self) -> dict:
        return self.ending.summary if self.ending is not None else {}


def _noop(*_a, **_k) -> None:
    return None


class _Guarded:
    """The writer's event/loop_stats, with failures collected instead of raised."""

    def __init__(self, writer, errors: list):
        self._w, self._errors = writer, errors

    def event(self, *a, **k) -> None:
        self._call(self._w.event, *a, **k)

    def loop_stats(self, *a, **k) -> None:
        self._call(self._w.loop_stats, *a, **k)

    def _call(self, fn, *a, **k) -> None:
        try:
            fn(*a, **k)
        except Exception as exc:  # noqa: BLE001
            self._errors.append(f"{type(exc).__name__}: {exc}")


def writer_failure(writer) -> str | None:
    """Has the log writer failed (a write raised, its thread died)? A sentence naming the exception,
    or None. The writer's own answer: ``writer.failure()`` (:meth:`rig.log.TrialLogWriter.failure`)."""
    try:
        exc = writer.failure()
    except Exception as err:  # noqa: BLE001
        exc = err
    return None if exc is None else f"the log writer failed: {type(exc).__name__}: {exc}"


class _WriterMonitor:
    """A thread that beats the backend's logger heartbeat (``backend.heartbeat()``, at
    ``backend.heartbeat_priority`` SCHED_FIFO when permitted) and watches the log writer while the
    trial runs: when it fails (disk full, a write
    error, its thread dead) the backend is told at once (``fail_stop``: the hardware loop nulls and
    disables the valve at its next tick), without waiting for the next block. When a write hangs
    for ``hang_exit_s`` (a dead disk), the backend is stopped the same way and, once it has had
    ``drain_s`` to reach its safe state, the process exits with status 1 and a message: never hang."""

    def __init__(self, session: "TrialSession", poll_s: float = 0.005, hang_exit_s: float = 10.0,
                 drain_s: float = 3.0):
        self.s = session
        self.poll_s, self.hang_exit_s, self.drain_s = poll_s, hang_exit_s, drain_s
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, name="rig-writer-monitor", daemon=True)

    def start(self) -> None:
        self._th.start()

    def stop(self) -> None:
        self._stop.set()
        if self._th.is_alive():
            self._th.join(1.0)

    def _fail(self, reason: str) -> None:
        s = self.s
        if s.writer_failure is None:
            s.writer_failure = reason
            if isinstance(s.backend, FailStoppable):
                s.backend.fail_stop(reason)

    def _run(self) -> None:
        s = self.s
        watched = isinstance(s.backend, LoggerWatched)
        beat = s.backend.heartbeat if watched else None
        prio = s.backend.heartbeat_priority if watched else None
        if beat is not None and prio:
            try:  # the heartbeat must not wait behind the machine's other work (this thread only)
                import os

                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            except (OSError, AttributeError):
                pass
        while not self._stop.wait(self.poll_s):
            if beat is not None:
                beat()
            why = writer_failure(s.writer)
            if why:
                self._fail(why)
            t = s._in_write
            if t is not None and time.monotonic() - t > self.hang_exit_s:
                self._fail(f"the log writer hung for {self.hang_exit_s:g} s")
                self._stop.wait(self.drain_s)
                import os
                import sys

                sys.stderr.write(f"error: the log writer hung for over {self.hang_exit_s:g} s (disk?); the "
                                 "hardware was told to stop at once (valve nulled and disabled); exiting\n")
                sys.stderr.flush()
                os._exit(1)


class TrialSession:
    """Run ``plan`` on ``backend``, logging to ``writer`` (see the module docstring).

    ``progress(t_s)``: called after every block. ``echo(text)``: operator
    messages (interlock trips, the backend's final report). ``trial_fields``:
    extra fields of the ``trial_start`` event. ``handle_signals``: install
    SIGINT/SIGTERM/SIGHUP handlers for the run (main thread only).
    """

    def __init__(self, plan, backend: Backend, writer: TrialWriter, *, progress: Callable[[float], Any] | None = None,
                 echo: Callable[[str], Any] = _noop, stats_every_s: float = 1.0,
                 trial_fields: dict | None = None, handle_signals: bool = True, pause=None):
        self.plan = plan
        self.backend = backend
        self.writer = writer
        self.progress = progress
        self.echo = echo
        self.stats_every_s = float(stats_every_s)
        self.trial_fields = dict(trial_fields or {})
        self.handle_signals = handle_signals
        self.stop = StopMachine()
        self.figures = BlockFigures()
        self._signals: list[str] = []
        self._in_write: float | None = None  # monotonic start of the write_block in progress
        self._logged = None
        self.writer_failure: str | None = None
        self.close_timeout_s = 10.0  # finishing the log never hangs longer (a dead disk): rig recover
        # the operator's pause (rig.session.pausing.PauseControl): by default where signals are handled
        if pause is None and handle_signals and isinstance(backend, Pausable):
            from rig.session.pausing import PauseControl

            pause = PauseControl()
        self.pause = pause if isinstance(backend, Pausable) else None
        self._planned = sorted((dict(e) for e in getattr(plan, "events", []) or []), key=lambda e: e["t_s"])
        self._plan_shift_s = 0.0       # trial time - plan time of the events after the last pause
        self._plan_shift_um = 0.0      # and the position the run-ups added
        self._plan_frozen_s = None     # plan time from which events wait for the run-up to end

    # -- stop requests ---------------------------------------------------------
    def request_stop(self, outcome: Outcome, reason: str) -> None:
        first = self.stop.request(outcome, reason)
        if outcome is Outcome.STOPPED:
            self.backend.request_stop(reason, insist=self.stop.requests >= 3)
        elif first:
            self.backend.request_stop(reason)
        if first:
            self.writer.event(self.figures.last_t_s, "stop_state", state=Phase.STOPPING.value,
                              cause=outcome.cause, reason=reason)

    def _on_signal(self, signum, _frame) -> None:
        # only note it here: the run loop turns it into a stop request between two messages
        if signum == signal.SIGHUP:
            detach_from_terminal()
        self._signals.append(signal.Signals(signum).name)

    def _install_signals(self) -> dict:
        old = {}
        if not self.handle_signals or threading.current_thread() is not threading.main_thread():
            return old
        for sig in STOP_SIGNALS:
            old[sig] = signal.signal(sig, self._on_signal)
        return old

    # -- run -------------------------------------------------------------------
    def run(self) -> TrialResult:
        plan, backend, w = self.plan, self.backend, self.writer
        rate = float(plan.loop_rate_hz)
        half_tick = 0.5 / rate
        w.event(0.0, "trial_start", **{**self.trial_fields, "backend": backend.name,
                                       "duration_s": float(plan.duration_s), "n_ticks": int(plan.n_ticks),
                                       **backend.describe()})
        t_wall0 = time.perf_counter()
        self._next_stats = self.stats_every_s
        ending: Ending | None = None
        handled = 0  # signals turned into stop requests
        old = self._install_signals()
        w.warm_up()  # numba & co. compiled/loaded now: the first second of the run is as durable as the rest
        self.figures.warm_up()
        self._logged = backend.block_logged if isinstance(backend, LoggerWatched) else None
        anchor = w.anchor if isinstance(w, Anchored) else None  # the log's clock: the samples' wall-clock time
        monitor = _WriterMonitor(self, poll_s=0.005)
        try:
            try:
                backend.start(plan)
                monitor.start()
                if self.pause is not None:
                    self.pause.start()
                while True:
                    try:
                        while handled < len(self._signals):
                            name = self._signals[handled]
                            handled += 1
                            self.request_stop(Outcome.STOPPED, f"operator abort ({name})")
                        if self.pause is not None and self.stop.phase is Phase.RUNNING:
                            self.pause.apply(backend, self.figures.last_t_s)
                        msg = backend.receive()
                        if msg is None:
                            break
                        if type(msg) is Block:
                            self._on_block(msg, anchor, rate, half_tick)
                        else:
                            w.event(msg.t_s, msg.kind, **msg.data)
                            if msg.kind in ("pause", "resume", "runup_done", "pause_refused"):
                                self._on_pause_event(msg)
                            if msg.kind == "interlock":
                                self.echo(f"INTERLOCK {msg.data.get('name')} at t={msg.t_s:.3f} s: "
                                          f"{msg.data.get('message')}")
                    except KeyboardInterrupt:
                        self._signals.append("KeyboardInterrupt")
                        handled = len(self._signals)
                        self.request_stop(Outcome.STOPPED, "operator abort (Ctrl-C)")
                ending = backend.finish()
            except BackendError as exc:
                ending = Ending(Outcome.FAILED, str(exc), safe=True)
            except Exception as exc:  # noqa: BLE001 - a failure while running (e.g. the log): stop the backend
                ending = self._fail_stop(f"{type(exc).__name__}: {exc}")
        finally:
            monitor.stop()
            if self.pause is not None:
                self.pause.stop()
            for sig, h in old.items():
                signal.signal(sig, h)
            try:
                backend.close()
            except Exception as exc:  # noqa: BLE001
                if ending is not None:
                    ending.message += f"; closing the backend failed: {exc}"
        return self._end(ending, time.perf_counter() - t_wall0)

    def _on_block(self, msg: Block, anchor, rate: float, half_tick: float) -> None:
        """One block: the planned events it reaches, the log (its clock anchored on the block's wall-clock
        time), the figures, loop statistics every ``stats_every_s`` of trial time, the progress."""
        w = self.writer
        self._schedule_planned(float(msg.data["t_s"][-1]) + half_tick)
        self._in_write = time.monotonic()
        if msg.wall_ns is not None and anchor is not None and len(msg.data["t_s"]):
            anchor(float(msg.data["t_s"][-1]), msg.wall_ns)
        if msg.frozen:
            w.write_block(msg.data, frozen=True)
        else:
            w.write_block(msg.data)
        self._in_write = None
        if self._logged is not None:
            self._logged()
        self.figures.add(msg.data)
        t = self.figures.last_t_s
        if t >= self._next_stats - half_tick:
            st = self.figures.window(rate)
            st.update(self.backend.stats_window())
            w.loop_stats(t, st)
            self._next_stats += self.stats_every_s
        if self.progress is not None:
            self.progress(t)

    # -- the plan's events, later by what pauses added -----------------------------------------------------
    def _schedule_planned(self, until_s: float | None = None) -> None:
        """Hand the writer the planned events due by trial time ``until_s`` (None: all that are left),
        at their plan time plus the pauses' shift; none from the plan time a pause holds at until its
        run-up has ended."""
        k, shift, frozen = 0, self._plan_shift_s, self._plan_frozen_s
        ev = self._planned
        while k < len(ev) and (until_s is None or (
                (frozen is None or ev[k]["t_s"] < frozen) and ev[k]["t_s"] + shift <= until_s)):
            k += 1
        if k:
            from trajectories.pause import shift_event

            self.writer.schedule_events([shift_event(e, shift, self._plan_shift_um) if shift else e for e in ev[:k]])
            del ev[:k]

    def _on_pause_event(self, msg: Event) -> None:
        if msg.kind == "pause":
            # the events of the safe point's tick (their times are not on the tick grid) wait too
            self._plan_frozen_s = float(msg.data["plan_t_s"]) - 0.5 / float(self.plan.loop_rate_hz)
            self.echo(f"paused at t={msg.t_s:.3f} s (holding {msg.data.get('hold_um', float('nan')):.2f} µm)")
        elif msg.kind == "resume":
            self.echo(f"resumed at t={msg.t_s:.3f} s: run-up of {msg.data.get('runup_um', 0.0):.1f} µm")
        elif msg.kind == "runup_done":
            self._plan_shift_s = msg.t_s - float(msg.data["plan_t_s"])
            self._plan_shift_um = float(msg.data.get("shift_um", 0.0))
            self._plan_frozen_s = None
        if self.pause is not None:
            self.pause.on_event(msg.kind, msg.t_s)

    def _fail_stop(self, reason: str, drain_s: float = 2.0) -> Ending:
        """The session itself failed (its writer, its progress): ask the backend for a stop, let it
        reach its safe state (its messages are dropped: the log may be what failed), say how it ended."""
        self.stop.request(Outcome.FAILED, reason)
        try:
            be = self.backend
            (be.fail_stop if isinstance(be, FailStoppable) else be.request_stop)(reason)
            t_end = time.monotonic() + drain_s
            while time.monotonic() < t_end and self.backend.receive() is not None:
                pass
            if time.monotonic() >= t_end:
                self.backend.request_stop(reason, insist=True)
            got = self.backend.finish()
        except Exception as exc:  # noqa: BLE001
            return Ending(Outcome.FAILED, f"{reason}; stopping the backend failed: {exc}", safe=False)
        return Ending(Outcome.FAILED, reason, safe=got.safe, summary=got.summary, final_stats=got.final_stats,
                      report=got.report)

    def _end(self, ending: Ending, wall_s: float) -> TrialResult:
        sm, fig = self.stop, self.figures
        t_last = fig.last_t_s
        log_errors: list[str] = []
        w = _Guarded(self.writer, log_errors)  # after a failure of the log, the rest is best effort
        # how it ended decides the cause unless a stop was already asked for
        if sm.phase is Phase.RUNNING:
            sm.request(ending.outcome, ending.message or ending.outcome.value)
            w.event(t_last, "stop_state", state=Phase.STOPPING.value, cause=sm.cause, reason=sm.reason)
        elif ending.outcome in (Outcome.TRIPPED, Outcome.FAILED):
            sm.overrule(ending.outcome, ending.message)  # a trip or a failure during an operator stop
        try:
            self._schedule_planned()  # what is left of the plan (the writer logs those the blocks reached)
        except Exception as exc:  # noqa: BLE001
            log_errors.append(f"{type(exc).__name__}: {exc}")
        if ending.final_stats:
            w.loop_stats(t_last, {**ending.final_stats, "final": True})
        if ending.report:
            self.echo(ending.report)
        if ending.safe:
            detail = ending.summary.get("safe_state", "")
            sm.safe(detail)
            w.event(t_last, "stop_state", state=Phase.SAFE.value, **({"detail": detail} if detail else {}))
        status = sm.status
        if status == "interrupted":
            sig = self._signals[0] if self._signals else "abort"
            w.event(t_last, "interrupted", reason=f"operator abort ({sig})" if sig != "KeyboardInterrupt"
                    else "KeyboardInterrupt (Ctrl-C)")
        elif status == "failed":
            w.event(t_last, "trial_failed", status=ending.outcome.value, message=sm.reason)
        close_error = "; ".join(log_errors) or None
        try:
            self.writer.close(status, timeout_s=self.close_timeout_s, wall_s=wall_s, ticks_per_s=fig.ticks / wall_s if wall_s > 0 else 0.0,
                              realtime_factor=t_last / wall_s if wall_s > 0 else 0.0,
                              tracking_error_rms_um=fig.tracking_error_rms_um, mean_friction_N=fig.mean_friction_N,
                              mean_abs_friction_N=fig.mean_abs_friction_N, stop_reason=sm.reason,
                              stop_cause=sm.cause)
        except Exception as exc:  # noqa: BLE001 - e.g. disk full: the file cannot be finished
            close_error = f"{type(exc).__name__}: {exc}"
        if close_error and sm.status == "completed":
            sm.overrule(Outcome.FAILED, f"the log could not be finished: {close_error}")
        sm.done()
        return TrialResult(outcome=sm.outcome, reason=sm.reason, ticks=fig.ticks,
                           duration_s=t_last, wall_s=wall_s, figures=fig, ending=ending, safe=ending.safe,
                           close_error=close_error, history=list(sm.history))


def run_trial(plan, backend: Backend, writer: TrialWriter, **kw) -> TrialResult:
    """``TrialSession(plan, backend, writer, **kw).run()``."""
    return TrialSession(plan, backend, writer, **kw).run()


__all__ = ["Anchored", "Backend", "BackendError", "Block", "BlockFigures", "Ending", "Event", "FailStoppable",
           "FlushPaced", "LoggerWatched", "Outcome", "Pausable", "Phase", "StopMachine", "TrialResult",
           "TrialSession", "TrialWriter", "run_trial", "writer_failure"]
