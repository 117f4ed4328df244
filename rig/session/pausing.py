"""The operator's pause: where the requests come from, and what a backend needs to pause a plan.

A pause holds the position at the plan's next safe point and, on resume, runs up
``RUNUP_L`` x L at the segment's velocity before the plan goes on
(:class:`trajectories.pause.PausableReference`, which both backends drive: the
hardware loop tick by tick, the simulated rig block by block). Requests:

* SIGUSR1 to `rig run` toggles pause and resume;
* `rig pause` / `rig resume` (:func:`send`) through a Unix socket of the run
  (:func:`socket_path`: ``$XDG_RUNTIME_DIR/rig`` or ``/tmp/rig-UID``, a directory
  of mode 0700 owned by the operator's user; the socket 0600);
* a script (tests, benchmarks): ``[(t_s, hold_s), ...]``: pause once the trial
  reaches ``t_s``, resume once the hold has lasted ``hold_s`` of trial time.

:class:`PauseControl` collects them; the session (:class:`rig.session.TrialSession`)
asks it between two messages of the backend and calls ``backend.pause()`` /
``backend.resume()``.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
from pathlib import Path

from drivers.linux import serve_private_socket
from trajectories.pause import PausableReference, safe_ticks_of

RUNUP_L = 5.0  # slip distances run up after a pause before the plan goes on (exp(-5): 0.7 % of the state left)


def runup_um(friction_model) -> float:
    """``RUNUP_L`` x the model's L (µm; the longer of L and L2 for a two-state law); 0 without one."""
    p = getattr(friction_model, "params", None) or {}
    L = max(float(p.get("L_um", 0.0) or 0.0), float(p.get("L2_um", 0.0) or 0.0))
    return RUNUP_L * L


def pause_options(plan, friction_model) -> dict:
    """What a backend needs to pause ``plan``: its safe points (ticks), the run-up distance, the stroke."""
    lim = getattr(plan, "limits", None)
    stroke = (lim.stroke_min_um, lim.stroke_max_um) if lim is not None else (float("-inf"), float("inf"))
    return {"safe_ticks": safe_ticks_of(list(getattr(plan, "events", []) or []), float(plan.loop_rate_hz)),
            "runup_um": runup_um(friction_model), "stroke_um": stroke}


def pausable_reference(plan, friction_model) -> PausableReference:
    o = pause_options(plan, friction_model)
    return PausableReference(plan.x_ref_um, 1.0 / float(plan.loop_rate_hz), o["safe_ticks"], o["runup_um"],
                             o["stroke_um"])


def control_dir() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR")
    return Path(base) / "rig" if base else Path(f"/tmp/rig-{os.getuid()}")


def socket_path(pid: int | None = None) -> Path:
    return control_dir() / f"run-{os.getpid() if pid is None else pid}.sock"


def running_sockets() -> list[Path]:
    d = control_dir()
    return sorted(d.glob("run-*.sock")) if d.is_dir() else []


def send(command: str, pid: int | None = None, timeout_s: float = 2.0) -> str:
    """``pause``, ``resume`` or ``status`` to the run of ``pid`` (default: the only one running);
    its answer. OSError / ValueError with a sentence when there is none (or more than one)."""
    if pid is not None:
        path = socket_path(pid)
        if not path.exists():
            raise ValueError(f"no `rig run` of pid {pid} is running for this user (no socket {path})")
    else:
        socks = [p for p in running_sockets() if _alive(p)]
        if not socks:
            raise ValueError(f"no `rig run` is running for this user (no socket in {control_dir()})")
        if len(socks) > 1:
            pids = ", ".join(p.stem.split("-", 1)[1] for p in socks)
            raise ValueError(f"several runs ({pids}): name one with --pid")
        path = socks[0]
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        s.connect(str(path))
        s.sendall(command.encode() + b"\n")
        return s.makefile("r").readline().strip()


def _alive(path: Path) -> bool:
    try:
        return Path(f"/proc/{int(path.stem.split('-', 1)[1])}").exists()
    except ValueError:
        return False


class PauseControl:
    """The pause requests of one run (see the module docstring). ``want`` is what the operator asks for
    (True: paused); the session applies it with :meth:`apply`."""

    def __init__(self, script=None, listen: bool = True, signals: bool = True):
        self.script = sorted(script or [])
        self.scripted = bool(self.script)
        self.listen, self.signals = listen, signals
        self.want = False
        self.applied = False
        self.held_since: float | None = None  # trial time of the backend's `pause` event
        self.path: Path | None = None
        self._sock = None
        self._old = None
        self._lock = threading.Lock()

    # -- sources --------------------------------------------------------------------------------------
    def start(self) -> None:
        if self.signals and threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGUSR1, lambda *_: self.toggle())
        if self.listen:
            try:
                self._bind()
            except OSError:
                self._sock = None  # no socket (read-only /tmp?): SIGUSR1 still works

    def _bind(self) -> None:
        d = control_dir()
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = d.stat()
        if st.st_uid != os.getuid() or st.st_mode & 0o077:
            raise OSError(f"{d} is not private to this user")
        self.path = socket_path()
        self.path.unlink(missing_ok=True)
        self._sock = serve_private_socket(self.path, self._answer, "rig-pause-control")

    def _answer(self, cmd: str) -> str:
        if cmd == "pause":
            self.request(True)
        elif cmd == "resume":
            self.request(False)
        elif cmd != "status":
            return f"error: unknown command {cmd!r}"
        return f"ok {'paused' if self.want else 'running'}"

    def stop(self) -> None:
        if self._old is not None:
            signal.signal(signal.SIGUSR1, self._old)
            self._old = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            if self.path is not None:
                self.path.unlink(missing_ok=True)

    def toggle(self) -> None:
        with self._lock:
            self.want = not self.want

    def request(self, paused: bool) -> None:
        with self._lock:
            self.want = paused

    # -- the session's side ---------------------------------------------------------------------------
    def on_event(self, kind: str, t_s: float) -> None:
        """The backend's pause events: the scripted hold is counted from the ``pause`` event."""
        if kind == "pause":
            self.held_since = t_s
        elif kind in ("pause_refused", "runup_done"):
            self.held_since = None
            if kind == "pause_refused":
                self.request(False)

    def apply(self, backend, t_s: float) -> None:
        """Between two messages: the script's requests, then what is wanted, to the backend."""
        if self.script:
            t_req, hold_s = self.script[0]
            if not self.want and not self.applied and t_s >= t_req:
                self.request(True)
            elif self.applied and self.held_since is not None and t_s >= self.held_since + hold_s:
                self.request(False)
                self.script.pop(0)
        want = self.want
        if want != self.applied:
            self.applied = want
            if want:
                backend.pause(realtime=not self.scripted)  # a scripted hold need not last its wall time
            else:
                backend.resume()
