"""Live view: the running trial served through the Foxglove WebSocket protocol (foxglove-sdk).

``rig run ... --live`` opens a :class:`LiveView` (a ``foxglove.start_server``
WebSocket server, bound to 127.0.0.1 unless told otherwise) and attaches it to
each trial's :class:`rig.log.TrialLogWriter` (``writer.add_listener``). It
publishes the log's JSON channels under the log's topic names and JSON schemas
(:data:`rig.log.schemas.JSON_TOPICS`), so ``config/foxglove/rig-trial.json``
works on the live connection as on a file:

``/log25`` (``rig.Sample``)
    the decimated samples (25 Hz): t_s, position_um, position_ref_um,
    friction_N, mu, normal_1_N, normal_2_N, valve_cmd;
``/events`` (``rig.Event``) and ``/loop_stats`` (``rig.LoopStats``).

``log_time`` of every message is the MCAP's: the trial's start (wall-clock ns
since the epoch) plus ``t_s``.

Where it runs, and why it cannot slow the loop: the 1 kHz hardware loop runs in
a process of its own (:mod:`rig.hardware`); the live view runs in the CLI's
session process, fed by the log writer's listener. The listener only appends
to a bounded ``collections.deque`` (no lock, no I/O, no encoding; the oldest
item is dropped and counted when it is full, :attr:`LiveView.dropped`); a
daemon thread encodes and hands the messages to foxglove-sdk's server, whose
per-client queue drops the oldest data message for a slow client
(``message_backlog_size``). Nothing on that path waits for a client.
"""

from __future__ import annotations

import collections
import json
import math
import threading
import time
from typing import Any, Callable

import numpy as np

from rig.log.schemas import EVENTS_TOPIC, JSON_TOPICS, LOG25_TOPIC, SAMPLE_FIELDS, SCHEMAS, STATS_TOPIC

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
_U64_MAX = (1 << 64) - 1


class LiveViewError(RuntimeError):
    """The live view could not start (e.g. the port is in use): the message says where."""


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


class LiveView:
    """A Foxglove WebSocket server publishing the trials of one ``rig run``.

    ``LiveView(host, port)`` starts the server (port 0: any free port; see
    :attr:`port` and :attr:`url`); :meth:`attach` connects it to a trial's log
    writer; :meth:`close` drains what is queued and stops the server. Use as a
    context manager. ``queue_items``: how many listener calls may wait for the
    publisher thread before the oldest is dropped. ``backlog``: messages
    foxglove-sdk buffers per client before it drops the oldest.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, name: str = "rig",
                 queue_items: int = 4096, backlog: int = 4096):
        try:
            import foxglove
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise LiveViewError(f"the live view needs foxglove-sdk (pip install foxglove-sdk): {exc}") from exc
        self.host = str(host)
        self._ctx = foxglove.Context()  # its own context: no global channels, no other sinks
        self._chan = {topic: foxglove.Channel(topic, schema=SCHEMAS[schema], context=self._ctx,
                                              metadata={"source": "rig run --live"})
                      for topic, schema in JSON_TOPICS}
        try:
            self._server = foxglove.start_server(name=name, host=self.host, port=int(port), context=self._ctx,
                                                 message_backlog_size=int(backlog))
        except Exception as exc:  # the SDK raises a RuntimeError naming the OS error
            raise LiveViewError(f"cannot serve the live view on {self.host}:{port}: {exc}") from exc
        self.port = int(self._server.port)
        self._q: collections.deque = collections.deque(maxlen=int(queue_items))
        self._maxlen = int(queue_items)
        self.dropped = 0          # listener calls dropped because the publisher thread fell behind
        self.published: collections.Counter = collections.Counter()  # messages handed to the server, by topic
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rig-live-view", daemon=True)
        self._thread.start()
        self.closed = False

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    # -- the writer side (the session's thread): append and return ---------------------------------
    def listener(self, start_time_ns: int | Callable[[], int]) -> Callable[[str, dict], None]:
        """A writer listener for a trial that started at ``start_time_ns`` (epoch ns of t_s = 0; or a callable
        giving it now: the log's clock is anchored on its samples' wall clock as they come, issue 21)."""
        q, maxlen = self._q, self._maxlen
        clock = start_time_ns if callable(start_time_ns) else (lambda t=int(start_time_ns): t)

        def live_view(kind: str, payload: dict) -> None:
            if len(q) >= maxlen:
                self.dropped += 1
            if kind == "samples":  # the writer's arrays may be views of the loop's buffers: copy (≈25 values)
                payload = {k: np.array(v, dtype=np.float64) for k, v in payload.items()}
            q.append((clock(), kind, payload))

        return live_view

    def attach(self, writer) -> Callable[[str, dict], None]:
        """Publish what ``writer`` (a :class:`rig.log.TrialLogWriter`) logs from now on; returns the listener."""
        fn = self.listener((lambda: writer.origin_ns) if hasattr(writer, "origin_ns") else writer.start_time_ns)
        writer.add_listener(fn)
        return fn

    # -- the publisher thread ------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop()
        finally:
            self.cpu_s = time.thread_time()  # CPU the publisher thread used (encoding + handing to the server)

    cpu_s = 0.0
    #: the publisher thread looks at the queue this often (s): the 25 Hz rate; the listener takes no lock to wake it
    POLL_S = 0.04

    def _loop(self) -> None:
        q = self._q
        while True:
            try:
                t0, kind, payload = q.popleft()
            except IndexError:
                if self._stop.is_set():
                    return
                time.sleep(self.POLL_S)
                continue
            try:
                self._publish(t0, kind, payload)
            except Exception as exc:  # noqa: BLE001 - a bad message must not end the view
                if len(self.errors) < 20:
                    self.errors.append(f"{kind}: {type(exc).__name__}: {exc}")

    @staticmethod
    def _ns(t0: int, t_s: float) -> int:
        if not math.isfinite(t_s):
            return t0
        return min(max(t0 + int(round(t_s * 1e9)), 0), _U64_MAX)

    def _publish(self, t0: int, kind: str, payload: dict) -> None:
        if kind == "samples":
            names = [nm for nm in SAMPLE_FIELDS if nm in payload]
            if "t_s" not in names:
                return
            ch = self._chan[LOG25_TOPIC]
            rows = np.array([payload[nm] for nm in names], dtype=np.float64).T.tolist()
            for row in rows:
                msg = {nm: _num(v) for nm, v in zip(names, row)}
                ch.log(_dumps(msg), log_time=self._ns(t0, row[0]))
            self.published[LOG25_TOPIC] += len(rows)
        elif kind in ("event", "loop_stats"):
            topic = EVENTS_TOPIC if kind == "event" else STATS_TOPIC
            t_s = float(payload.get("t_s", 0.0))
            self._chan[topic].log(_dumps(payload), log_time=self._ns(t0, t_s))
            self.published[topic] += 1

    # -- end -----------------------------------------------------------------------------------------
    def close(self, linger_s: float = 1.0) -> None:
        """Publish what is queued (at most ~2 s), give the clients ``linger_s`` to receive it, stop the server."""
        if self.closed:
            return
        self.closed = True
        self._stop.set()
        self._thread.join(timeout=2.0)
        if linger_s > 0:
            time.sleep(linger_s)
        try:
            self._server.stop()
        finally:
            for ch in self._chan.values():
                ch.close()

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["LiveView", "LiveViewError", "DEFAULT_HOST", "DEFAULT_PORT"]
