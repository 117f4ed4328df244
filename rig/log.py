"""The trial log: one MCAP file per trial.

Layout (all channels: schema encoding ``jsonschema``, message encoding ``json``,
written with ``json.dumps(allow_nan=False)``; chunked, zstd, message index kept):

``/raw`` (schema ``rig.RawBlock``)
    The 1 kHz loop data as blocks of samples (about 0.1 s each): every key of the
    loop's block dict (``t_s, position_ref_um, position_um, friction_N,
    normal_1_N, normal_2_N, valve_cmd, pid_p, pid_i, pid_d, dither`` and, from the
    simulation, ``true_position_um, true_velocity_um_s, true_mu``). Each array is
    either base64 of little-endian float64 (``"encoding": "base64-f8le"``, the
    default: ~10x cheaper to encode than JSON numbers, so logging does not slow
    a simulation running hundreds of times faster than real time) or a JSON list
    (``"encoding": "json"``; non-finite values as ``null``). ``log_time`` = the
    block's first sample time.
``/log25`` (schema ``rig.Sample``)
    One message per sample at the decimated rate (25 Hz like the paper's log,
    section 4.2): ``t_s, position_um, friction_N, normal_1_N, normal_2_N,
    position_ref_um, valve_cmd``; ``log_time`` = the sample time, so Foxglove
    plots it over time. Decimation takes every n-th loop sample (the paper's
    logger sampled the analog-filtered signals; the rig's sensors are filtered
    at 100 Hz / 10 Hz upstream), no extra averaging.
``/events`` (schema ``rig.Event``)
    ``{t_s, kind, ...}``: segment start/end, velocity steps, stepped-pass levels,
    trial start/end, interruption, operator markers.
``/loop_stats`` (schema ``rig.LoopStats``)
    ``{t_s, ...}`` numbers: period statistics, tracking error, real-time factor.

Metadata records: ``trial`` (recipe name, lubricant, normal_force_N, seed,
software_version, trial index, loop and log rates, start time), ``recipe`` (the
validated recipe as JSON), ``rig_profile`` (the profile as JSON), ``trial_end``
(status ``completed`` / ``interrupted`` / ``failed``, counts), and, in a file
rewritten by :func:`recover`, ``recovery``. The recipe YAML is attached as
``recipe.yaml``. Time zero is the start of the trial (log_time in ns since then).

Crash safety: the writer closes the chunk in progress, flushes and ``os.fsync``s
at least every ``flush_interval_s`` of wall time (1 s), so a crash loses at most
the last second; :func:`recover` rewrites a file cut off anywhere (no footer)
into a readable one from every complete chunk.
"""

from __future__ import annotations

import base64
import datetime as _dt
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from mcap.reader import make_reader
from numba import njit
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from rig import __version__
from rig.data import DataFormatError, TrialData

RAW_TOPIC = "/raw"
LOG25_TOPIC = "/log25"
EVENTS_TOPIC = "/events"
STATS_TOPIC = "/loop_stats"
MCAP_PROFILE = "rig-trial"
SAMPLE_FIELDS = ("t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd")
BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N", "valve_cmd",
              "pid_p", "pid_i", "pid_d", "dither", "true_position_um", "true_velocity_um_s", "true_mu")
B64_ENCODING = "base64-f8le"
B64_F4_ENCODING = "base64-f4le"  # float32 fields (t_s stays float64, base64-f8le, under "t_s")

_NUM_OR_NULL = {"type": ["number", "null"]}
SCHEMAS: dict[str, dict] = {
    "rig.RawBlock": {
        "title": "rig.RawBlock",
        "description": "A block of 1 kHz loop samples. fields[key] is base64 of little-endian float64 "
                       "(encoding base64-f8le) or a JSON list (encoding json).",
        "type": "object",
        "properties": {
            "t0_s": {"type": "number", "description": "time of the first sample (s)"},
            "n": {"type": "integer", "description": "samples in the block"},
            "rate_hz": {"type": "number"},
            "encoding": {"type": "string", "enum": [B64_ENCODING, B64_F4_ENCODING, "json"]},
            "fields": {"type": "object", "additionalProperties": {
                "oneOf": [{"type": "string"}, {"type": "array", "items": _NUM_OR_NULL}]}},
        },
        "required": ["t0_s", "n", "encoding", "fields"],
    },
    "rig.Sample": {
        "title": "rig.Sample",
        "description": "One decimated sample (25 Hz like the paper's log). Units: s, µm, N, valve 1.",
        "type": "object",
        "properties": {name: ({"type": "number"} if name == "t_s" else _NUM_OR_NULL) for name in SAMPLE_FIELDS},
        "required": ["t_s", "position_um", "friction_N"],
    },
    "rig.Event": {
        "title": "rig.Event",
        "type": "object",
        "properties": {"t_s": {"type": "number"}, "kind": {"type": "string"}},
        "required": ["t_s", "kind"],
        "additionalProperties": True,
    },
    "rig.LoopStats": {
        "title": "rig.LoopStats",
        "type": "object",
        "properties": {"t_s": {"type": "number"}},
        "required": ["t_s"],
        "additionalProperties": _NUM_OR_NULL,
    },
}
TOPICS = ((RAW_TOPIC, "rig.RawBlock"), (LOG25_TOPIC, "rig.Sample"), (EVENTS_TOPIC, "rig.Event"),
          (STATS_TOPIC, "rig.LoopStats"))


def _ns(t_s: float) -> int:
    return max(0, int(round(float(t_s) * 1e9)))


def _jsonable(value: Any) -> Any:
    """Make ``value`` strict-JSON safe: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return str(value)


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


_KEY_CACHE: dict[str, bytes] = {}
_FMT_CACHE: dict[tuple, str] = {}


def _sample_format(names: tuple) -> str:
    """``{"t_s":%r,...}``: a printf template of one per-sample JSON object (cached)."""
    f = _FMT_CACHE.get(names)
    if f is None:
        f = _FMT_CACHE[names] = "{" + ",".join(json.dumps(nm).replace("%", "%%") + ":%r" for nm in names) + "}"
    return f


def _json_key(k: str) -> bytes:
    """``"key":`` as JSON bytes (cached)."""
    b = _KEY_CACHE.get(k)
    if b is None:
        b = _KEY_CACHE[k] = json.dumps(str(k)).encode() + b":"
    return b


def _list_or_null(a: np.ndarray) -> list:
    lst = a.tolist()
    if not np.isfinite(a).all():
        lst = [v if math.isfinite(v) else None for v in lst]
    return lst


_EMPTY = np.zeros(0)


@njit(cache=True)
def _block_stats(ref, pos, f, n1, n2, valve, acc):  # pragma: no cover - compiled
    """Accumulate a block's summary figures into ``acc`` (non-finite samples skipped):
    [sum (ref-pos)^2, max |ref-pos|, n, sum f, sum |f|, n_f, sum f/(n1+n2), n |valve| >= 1]."""
    if ref.size == pos.size:
        for i in range(ref.size):
            e = ref[i] - pos[i]
            if math.isfinite(e):
                acc[0] += e * e
                ae = abs(e)
                if ae > acc[1]:
                    acc[1] = ae
                acc[2] += 1.0
    with_n = n1.size == f.size and n2.size == f.size
    for i in range(f.size):
        fi = f[i]
        if math.isfinite(fi):
            acc[3] += fi
            acc[4] += abs(fi)
            acc[5] += 1.0
            if with_n:
                mu = fi / (n1[i] + n2[i])
                if math.isfinite(mu):
                    acc[6] += mu
    for i in range(valve.size):
        if abs(valve[i]) >= 1.0:
            acc[7] += 1.0


class _Sink:
    """Owns the mcap Writer and the file: adds messages/metadata, flushes (+fsync), finishes."""

    def __init__(self, writer: Writer, fh, fsync: bool):
        self.w = writer
        self.fh = fh
        self.fsync = fsync

    def messages(self, items: list) -> None:
        add = self.w.add_message
        for cid, ns, payload, seq in items:
            add(cid, log_time=ns, data=payload, publish_time=ns, sequence=seq)

    def metadata(self, name: str, data: dict) -> None:
        self.w.add_metadata(name, data)

    def flush(self) -> None:
        w = self.w
        if hasattr(w, "flush"):
            w.flush()
        else:  # mcap < 1.2
            w._Writer__finalize_chunk()  # type: ignore[attr-defined]
            w._Writer__flush()  # type: ignore[attr-defined]
        self._sync()

    def _sync(self) -> None:
        self.fh.flush()
        if self.fsync:
            try:
                os.fsync(self.fh.fileno())
            except OSError:
                pass

    def finish(self) -> None:
        self.w.finish()
        self._sync()
        self.fh.close()

    def abort(self) -> None:
        self.fh.close()


class _ThreadedSink:
    """Runs a :class:`_Sink` in a background thread, in order.

    The chunk compression (zstd releases the GIL) and the file I/O overlap the
    loop and the encoding in the caller's thread. A bounded queue keeps the
    backlog small (a crash still loses at most the last flush interval plus a
    few blocks); an error in the thread is raised in the caller at the next call.
    """

    _STOP = object()

    def __init__(self, sink: _Sink, maxsize: int = 64):
        import queue
        import threading

        self._sink = sink
        self._q: "queue.Queue" = queue.Queue(maxsize=maxsize)
        self._exc: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="rig-log-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is self._STOP:
                return
            fn, args = item
            if self._exc is not None:
                continue  # drain after a failure
            try:
                fn(*args)
            except BaseException as exc:  # reported to the caller
                self._exc = exc

    def _put(self, fn, *args) -> None:
        if self._exc is not None:
            raise RuntimeError(f"the log writer thread failed: {self._exc!r}") from self._exc
        self._q.put((fn, args))

    def messages(self, items: list) -> None:
        self._put(self._sink.messages, items)

    def metadata(self, name: str, data: dict) -> None:
        self._put(self._sink.metadata, name, data)

    def flush(self) -> None:
        self._put(self._sink.flush)

    def _stop(self, last) -> None:
        self._q.put((last, ()))
        self._q.put(self._STOP)
        while True:  # a second Ctrl-C must not leave the file unfinished
            try:
                self._thread.join()
                break
            except KeyboardInterrupt:
                continue
        if self._exc is not None:
            raise RuntimeError(f"the log writer thread failed: {self._exc!r}") from self._exc

    def finish(self) -> None:
        self._stop(self._sink.finish)

    def abort(self) -> None:
        self._stop(self._sink.abort)


class TrialLogWriter:
    """Writes one trial to an MCAP file (see the module docstring for the layout).

    ``write_block(block)`` takes the loop's block dict (numpy arrays, one entry
    per tick); ``event(t_s, kind, **data)``; ``loop_stats(t_s, stats)``;
    ``add_metadata(name, dict)``; ``close(status=...)`` writes the ``trial_end``
    record and the summary. Usable as a context manager (an exception marks the
    trial ``failed``, KeyboardInterrupt ``interrupted``).

    ``threaded`` (default): the mcap writer (chunk compression, file I/O,
    fsync) runs in a background thread, fed in order through a bounded queue;
    the caller's thread only encodes.
    """

    def __init__(self, path: str | os.PathLike, *, loop_rate_hz: float = 1000.0,
                 decimated_rate_hz: float = 25.0, raw_rate_hz: float | None = None,
                 metadata: dict[str, Any] | None = None, recipe_yaml: str | None = None,
                 recipe: dict | None = None, profile: dict | None = None,
                 raw_encoding: str = "base64", raw_dtype: str = "float64", flush_interval_s: float = 1.0,
                 chunk_size: int = 1 << 20, fsync: bool = True, threaded: bool = True):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.loop_rate_hz = float(loop_rate_hz)
        self.raw_rate_hz = float(raw_rate_hz or loop_rate_hz)
        self.decimated_rate_hz = float(decimated_rate_hz)
        self._raw_every = max(1, int(round(self.loop_rate_hz / self.raw_rate_hz)))
        self._dec_every = max(1, int(round(self.loop_rate_hz / self.decimated_rate_hz)))
        if raw_encoding not in ("base64", "json"):
            raise ValueError(f"raw_encoding must be 'base64' or 'json', not {raw_encoding!r}")
        self._raw_b64 = raw_encoding == "base64"
        if raw_dtype not in ("float64", "float32"):
            raise ValueError(f"raw_dtype must be 'float64' or 'float32', not {raw_dtype!r}")
        self._raw_dtype = np.dtype("<f8" if raw_dtype == "float64" else "<f4")
        self._raw_enc_name = B64_ENCODING if raw_dtype == "float64" else B64_F4_ENCODING
        self.flush_interval_s = float(flush_interval_s)
        self._fsync = fsync
        self._fh = open(self.path, "wb")
        self._w = Writer(self._fh, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile=MCAP_PROFILE, library=f"rig {__version__}")
        self._chan: dict[str, int] = {}
        for topic, schema_name in TOPICS:
            sid = self._w.register_schema(schema_name, "jsonschema", _dumps(SCHEMAS[schema_name]))
            self._chan[topic] = self._w.register_channel(topic, "json", sid)
        self._seq: dict[str, int] = {t: 0 for t, _ in TOPICS}
        self.counts: dict[str, int] = {t: 0 for t, _ in TOPICS}
        self.ticks = 0
        self.last_t_s = 0.0
        self.closed = False
        self.status: str | None = None
        self._pending: list[dict] = []
        # running figures for the end-of-trial summary (see _block_stats)
        self._stats_acc = np.zeros(8)
        trial = {"software_version": __version__, "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(),
                 "loop_rate_hz": self.loop_rate_hz, "raw_rate_hz": self.raw_rate_hz,
                 "decimated_rate_hz": self.decimated_rate_hz}
        trial.update(metadata or {})
        self.metadata = {k: _meta_str(v) for k, v in trial.items()}
        self._w.add_metadata("trial", self.metadata)
        if recipe is not None:
            self._w.add_metadata("recipe", {"json": json.dumps(_jsonable(recipe), allow_nan=False),
                                            "name": str(recipe.get("name", ""))})
        if profile is not None:
            self._w.add_metadata("rig_profile", {"json": json.dumps(_jsonable(profile), allow_nan=False)})
        if recipe_yaml is not None:
            now = time.time_ns()
            self._w.add_attachment(create_time=now, log_time=0, name="recipe.yaml",
                                   media_type="application/yaml", data=recipe_yaml.encode("utf-8"))
        self._batch: list = []
        sink = _Sink(self._w, self._fh, fsync)
        self._sink = _ThreadedSink(sink) if threaded else sink
        # the first chunk carries the schemas and channels: get it on disk now
        self.event(0.0, "log_start")
        self.flush()

    # -- writing ---------------------------------------------------------------
    def _add(self, topic: str, t_s: float, payload: bytes) -> None:
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        self._batch.append((self._chan[topic], _ns(t_s), payload, seq))
        self.counts[topic] += 1

    def _send(self) -> None:
        if self._batch:
            batch, self._batch = self._batch, []
            self._sink.messages(batch)

    def write_block(self, block: dict[str, np.ndarray]) -> None:
        """Log one block of loop samples (all keys as arrays of equal length; ``t_s`` required)."""
        if self.closed:
            raise RuntimeError("log closed")
        arrays = block if all(type(v) is np.ndarray and v.dtype == np.float64 for v in block.values()) \
            else {k: np.asarray(v, dtype=np.float64) for k, v in block.items()}
        t = arrays["t_s"]
        n = t.size
        if n == 0:
            return
        start = self.ticks
        if self._raw_every > 1:
            sel = np.flatnonzero((start + np.arange(n)) % self._raw_every == 0)
            raw = {k: v[sel] for k, v in arrays.items()}
        else:
            raw = arrays
        tr = raw["t_s"]
        if tr.size:
            t0 = float(tr[0])
            if self._raw_b64:
                # base64 needs no JSON escaping: assemble the (strict) JSON text directly,
                # which is ~10x cheaper than json.dumps over 15 kB of strings
                b64 = base64.b64encode
                dt = self._raw_dtype
                parts = [_json_key(k) + b'"' + b64((v if k == "t_s" else v.astype(dt, copy=False)).tobytes()) + b'"'
                         for k, v in raw.items()]
                payload = (b'{"t0_s":' + _dumps(t0) + b',"n":' + str(int(tr.size)).encode() + b',"rate_hz":'
                           + _dumps(self.raw_rate_hz) + b',"encoding":"' + self._raw_enc_name.encode()
                           + b'","fields":{' + b",".join(parts) + b"}}")
            else:
                fields = {k: _list_or_null(v) for k, v in raw.items()}
                payload = _dumps({"t0_s": t0, "n": int(tr.size), "rate_hz": self.raw_rate_hz, "encoding": "json",
                                  "fields": fields})
            self._add(RAW_TOPIC, t0, payload)
        # decimated per-sample channel: ticks whose global index is a multiple of the decimation
        first = (-start) % self._dec_every
        if first < n:
            idx = slice(first, n, self._dec_every)
            names = tuple(nm for nm in SAMPLE_FIELDS if nm in arrays)
            m = np.array([arrays[nm][idx] for nm in names])
            rows = m.T.tolist()
            if np.isfinite(m).all():
                # repr of a finite float is a valid JSON number: format directly (json.dumps is ~3x slower)
                fmt = _sample_format(names)
                for row in rows:
                    self._add(LOG25_TOPIC, row[0], (fmt % tuple(row)).encode())
            else:
                for row in rows:
                    rec = {k: (v if math.isfinite(v) else None) for k, v in zip(names, row)}
                    self._add(LOG25_TOPIC, row[0], _dumps(rec))
        self.ticks += n
        self.last_t_s = float(t[-1])
        self._running_stats(arrays)
        if self._pending and self._pending[0]["t_s"] <= self.last_t_s + 0.5 / self.loop_rate_hz:
            self._emit_pending(self.last_t_s + 0.5 / self.loop_rate_hz)
        self._send()
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def _running_stats(self, a: dict[str, np.ndarray]) -> None:
        empty = _EMPTY
        st = self._stats_acc
        _block_stats(a.get("position_ref_um", empty), a.get("position_um", empty), a.get("friction_N", empty),
                     a.get("normal_1_N", empty), a.get("normal_2_N", empty), a.get("valve_cmd", empty), st)

    # the running figures, read from the accumulator (see _block_stats)
    sum_err2_um2 = property(lambda self: float(self._stats_acc[0]))
    max_abs_err_um = property(lambda self: float(self._stats_acc[1]))
    n_err = property(lambda self: int(self._stats_acc[2]))
    sum_friction_N = property(lambda self: float(self._stats_acc[3]))
    sum_abs_friction_N = property(lambda self: float(self._stats_acc[4]))
    n_friction = property(lambda self: int(self._stats_acc[5]))
    sum_mu = property(lambda self: float(self._stats_acc[6]))
    n_valve_saturated = property(lambda self: int(self._stats_acc[7]))

    @property
    def tracking_error_rms_um(self) -> float:
        """RMS of position_ref_um - position_um over everything logged (µm)."""
        return math.sqrt(self.sum_err2_um2 / self.n_err) if self.n_err else float("nan")

    @property
    def mean_friction_N(self) -> float:
        return self.sum_friction_N / self.n_friction if self.n_friction else float("nan")

    @property
    def mean_abs_friction_N(self) -> float:
        """Mean |friction| (N): the sliding friction level whatever the direction."""
        return self.sum_abs_friction_N / self.n_friction if self.n_friction else float("nan")

    @property
    def mean_mu(self) -> float:
        return self.sum_mu / self.n_friction if self.n_friction else float("nan")

    def schedule_events(self, events: Iterable[dict]) -> None:
        """Queue planned events (``{t_s, kind, ...}``); each is logged once a block reaches its time.

        An interrupted trial therefore logs only the events it actually reached.
        """
        self._pending.extend(sorted((dict(e) for e in events), key=lambda e: e["t_s"]))
        self._pending.sort(key=lambda e: e["t_s"])

    _emitting = False

    def _emit_pending(self, t_until: float) -> None:
        self._emitting = True
        k = 0
        while k < len(self._pending) and self._pending[k]["t_s"] <= t_until:
            e = dict(self._pending[k])
            self.event(e.pop("t_s"), e.pop("kind"), **e)
            k += 1
        if k:
            del self._pending[:k]
        self._emitting = False

    def event(self, t_s: float, kind: str, **data: Any) -> None:
        """Log an event ``{t_s, kind, **data}`` (segment boundaries, steps, levels, markers)."""
        rec = {"t_s": float(t_s), "kind": str(kind)}
        rec.update(_jsonable({k: v for k, v in data.items() if k not in ("t_s", "kind")}))
        self._add(EVENTS_TOPIC, t_s, _dumps(rec))
        if not self._emitting:
            self._send()

    def loop_stats(self, t_s: float, stats: dict[str, Any]) -> None:
        """Log loop statistics (numbers) at time ``t_s``."""
        rec = {"t_s": float(t_s)}
        for k, v in stats.items():
            if k == "t_s":
                continue
            v = _jsonable(v)
            rec[str(k)] = v if isinstance(v, (int, float)) or v is None else None
        self._add(STATS_TOPIC, t_s, _dumps(rec))
        self._send()

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        self._send()
        self._sink.metadata(name, {str(k): _meta_str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Close the chunk in progress, write it and fsync: everything logged so far survives a crash.

        With the writer thread, the flush is queued behind what was logged before it."""
        self._send()
        self._sink.flush()
        self._last_flush = time.monotonic()

    _last_flush = 0.0

    def close(self, status: str = "completed", **summary: Any) -> None:
        """Finish the file: ``trial_end`` metadata (status and summary), summary section, fsync."""
        if self.closed:
            return
        self.status = status
        end = {"status": status, "ticks": self.ticks, "duration_s": self.last_t_s,
               "raw_blocks": self.counts[RAW_TOPIC], "samples_decimated": self.counts[LOG25_TOPIC],
               "events": self.counts[EVENTS_TOPIC],
               "ended_utc": _dt.datetime.now(_dt.timezone.utc).isoformat()}
        end.update(summary)
        self.event(self.last_t_s, "log_end", status=status)
        self.add_metadata("trial_end", end)
        self.closed = True
        self._sink.finish()

    def abort(self) -> None:
        """Stop without finishing: what was flushed stays, the open chunk is lost (simulates a crash;
        used by tests)."""
        if not self.closed:
            self._batch = []
            self.closed = True
            self._sink.abort()

    def __enter__(self) -> "TrialLogWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close("completed")
        elif issubclass(exc_type, KeyboardInterrupt):
            self.close("interrupted")
        else:
            self.close("failed", error=f"{exc_type.__name__}: {exc}")


def _meta_str(v: Any) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else str(v)
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(_jsonable(v), allow_nan=False)
    return str(v)


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------

def _decode_array(value: Any, encoding: str, key: str = "") -> np.ndarray:
    if encoding == B64_ENCODING or (encoding == B64_F4_ENCODING and key == "t_s"):
        return np.frombuffer(base64.b64decode(value), dtype="<f8").astype(float)
    if encoding == B64_F4_ENCODING:
        return np.frombuffer(base64.b64decode(value), dtype="<f4").astype(float)
    return np.array([np.nan if v is None else v for v in value], dtype=float)


class _Content:
    """Everything read from an MCAP (complete or recovered up to its damage)."""

    def __init__(self):
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.messages: list[Message] = []
        self.metadata: list[Metadata] = []
        self.attachments: list[Attachment] = []
        self.complete = False
        self.error: str | None = None
        self.header = None
        self.counts: dict[int, int] = {}
        self.t_range: dict[int, tuple[int, int]] = {}

    def topic_of(self, msg: Message) -> str:
        ch = self.channels.get(msg.channel_id)
        return ch.topic if ch else f"#{msg.channel_id}"


def _read_stream(path: Path, topics: set[str] | None = None) -> _Content:
    """Read every record up to the end or the damaged point (never raises for damage).

    ``topics``: keep only these channels' messages (all when None); every
    message is still counted in ``c.counts`` with its time range in ``c.t_range``.
    """
    from mcap.records import Footer, Header

    c = _Content()
    keep_ids: set[int] = set()
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, record_size_limit=1 << 31).records:
                if isinstance(rec, Message):
                    cid = rec.channel_id
                    c.counts[cid] = c.counts.get(cid, 0) + 1
                    lo, hi = c.t_range.get(cid, (rec.log_time, rec.log_time))
                    c.t_range[cid] = (min(lo, rec.log_time), max(hi, rec.log_time))
                    if topics is None or cid in keep_ids:
                        c.messages.append(rec)
                elif isinstance(rec, Header):
                    c.header = rec
                elif isinstance(rec, Schema):
                    c.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    c.channels[rec.id] = rec
                    if topics is not None and rec.topic in topics:
                        keep_ids.add(rec.id)
                elif isinstance(rec, Metadata):
                    c.metadata.append(rec)
                elif isinstance(rec, Attachment):
                    c.attachments.append(rec)
                elif isinstance(rec, Footer):
                    c.complete = True
        except Exception as exc:  # the damaged point: keep everything before it
            name = type(exc).__name__
            if name == "EndOfFile":
                c.error = "file ends in the middle of a record (truncated)"
            else:
                c.error = f"{name}: {exc}" if str(exc) else name
    if c.header is None and c.error:
        raise DataFormatError(path, None, f"not an MCAP file ({c.error})")
    return c


def _read_complete(path: Path, topics: set[str] | None = None) -> _Content:
    """Read a complete MCAP (with footer); a truncated one raises a DataFormatError naming ``rig recover``."""
    try:
        with open(path, "rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            if summary is None:
                raise ValueError("no summary section")
    except FileNotFoundError:
        raise DataFormatError(path, None, "no such file") from None
    except Exception as exc:
        raise DataFormatError(path, None, f"damaged or truncated MCAP ({type(exc).__name__}: {exc}); "
                                          f"rewrite it with `rig recover {path} --out FIXED.mcap`") from None
    c = _read_stream(path, topics)
    if c.error or not c.complete:
        raise DataFormatError(path, None, f"damaged MCAP ({c.error or 'no footer'}); "
                                          f"rewrite it with `rig recover {path} --out FIXED.mcap`")
    return c


def _metadata_dict(c: _Content) -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    for m in c.metadata:
        out.setdefault(m.name, {}).update(m.metadata)
    return out


def _events(c: _Content) -> list[dict]:
    ev = [json.loads(m.data) for m in c.messages if c.topic_of(m) == EVENTS_TOPIC]
    ev.sort(key=lambda e: e["t_s"])
    return ev


def read_metadata(path: str | os.PathLike) -> dict[str, dict[str, str]]:
    """All metadata records of a (complete) trial log, by record name."""
    return _metadata_dict(_read_complete(Path(path), topics=set()))


def _flat_metadata(records: dict[str, dict[str, str]], channel: str) -> dict[str, str]:
    meta: dict[str, str] = {}
    meta.update(records.get("trial", {}))
    if "recipe" in records and "name" in records["recipe"]:
        meta.setdefault("recipe", records["recipe"]["name"])
    end = records.get("trial_end", {})
    if "status" in end:
        meta["status"] = end["status"]
    rec = records.get("recovery")
    if rec:
        meta["recovered"] = "true"
        for k in ("recovered_from", "recovery_error"):
            if k in rec:
                meta[k] = rec[k]
    meta["channel"] = channel
    return meta


def read_trial(path: str | os.PathLike, channel: str = "25hz") -> TrialData:
    """Read a trial log into :class:`TrialData` (events and metadata included).

    ``channel="25hz"`` (the default) gives the decimated per-sample channel: the
    paper's logged data (25 Hz, section 4.2), which the identification's
    200-point windows assume. ``channel="raw"`` gives every loop sample; the
    block keys beyond the measured-data columns (``pid_*``, ``dither``,
    ``true_*``) go to ``extra``. A truncated file raises :class:`DataFormatError`
    pointing at ``rig recover``.
    """
    path = Path(path)
    ch = channel.lower().replace(" ", "")
    if ch in ("25", "25hz", "log25", "decimated"):
        ch = "25hz"
    elif ch in ("raw", "1khz", "loop"):
        ch = "raw"
    else:
        raise ValueError(f"channel must be 'raw' or '25hz', not {channel!r}")
    c = _read_complete(path, topics={RAW_TOPIC if ch == "raw" else LOG25_TOPIC, EVENTS_TOPIC})
    records = _metadata_dict(c)
    if ch == "raw":
        cols: dict[str, list[np.ndarray]] = {}
        for m in c.messages:
            if c.topic_of(m) != RAW_TOPIC:
                continue
            blk = json.loads(m.data)
            enc = blk["encoding"]
            n = int(blk["n"])
            for k, v in blk["fields"].items():
                arr = _decode_array(v, enc, k)
                if arr.size != n:
                    raise DataFormatError(path, None, f"raw block at t={blk['t0_s']} s: field {k} has "
                                                      f"{arr.size} samples, expected {n}")
                cols.setdefault(k, []).append(arr)
        arrays = {k: np.concatenate(v) for k, v in cols.items()}
    else:
        rows = [json.loads(m.data) for m in c.messages if c.topic_of(m) == LOG25_TOPIC]
        names: list[str] = []
        for r in rows[:1]:
            names = list(r)
        arrays = {nm: np.array([np.nan if r.get(nm) is None else r[nm] for r in rows], dtype=float)
                  for nm in names}
    if "t_s" not in arrays or arrays["t_s"].size == 0:
        raise DataFormatError(path, None, f"no samples on the {ch} channel")
    order = np.argsort(arrays["t_s"], kind="stable")
    if np.any(np.diff(order) < 0):
        arrays = {k: v[order] for k, v in arrays.items()}
    std = ("time_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd")
    get = {k: arrays.get(k) for k in std[1:]}
    for req in ("position_um", "friction_N"):
        if get[req] is None:
            raise DataFormatError(path, None, f"the {ch} channel has no {req}")
    extra = {k: v for k, v in arrays.items() if k not in std and k != "t_s"}
    return TrialData(time_s=arrays["t_s"], position_um=get["position_um"], friction_N=get["friction_N"],
                     normal_1_N=get["normal_1_N"], normal_2_N=get["normal_2_N"],
                     position_ref_um=get["position_ref_um"], valve_cmd=get["valve_cmd"], extra=extra,
                     metadata=_flat_metadata(records, ch), events=_events(c), source=str(path))


def trial_info(path: str | os.PathLike) -> dict:
    """What ``rig info`` shows: channels and counts, duration, metadata, events, recovered, damage."""
    path = Path(path)
    if not path.exists():
        raise DataFormatError(path, None, "no such file")
    c = _read_stream(path, topics={EVENTS_TOPIC})
    counts: dict[str, int] = {}
    t_min, t_max = None, None
    for cid, n in c.counts.items():
        chn = c.channels.get(cid)
        topic = chn.topic if chn else f"#{cid}"
        counts[topic] = counts.get(topic, 0) + n
        if topic in (RAW_TOPIC, LOG25_TOPIC):
            lo, hi = (v / 1e9 for v in c.t_range[cid])
            t_min = lo if t_min is None else min(t_min, lo)
            t_max = hi if t_max is None else max(t_max, hi)
    records = _metadata_dict(c)
    events = [json.loads(m.data) for m in c.messages if c.topic_of(m) == EVENTS_TOPIC]
    events.sort(key=lambda e: e["t_s"])
    channels = []
    for cid, chn in sorted(c.channels.items()):
        schema = c.schemas.get(chn.schema_id)
        channels.append({"topic": chn.topic, "schema": schema.name if schema else "",
                         "encoding": chn.message_encoding, "messages": counts.get(chn.topic, 0)})
    dur = None
    if t_max is not None:
        dur = t_max - (t_min or 0.0)
        # the last raw block covers ~0.1 s beyond its log_time
        end = records.get("trial_end", {}).get("duration_s")
        if end is not None:
            try:
                dur = max(dur, float(end))
            except ValueError:
                pass
    return {"path": str(path), "size_bytes": path.stat().st_size, "complete": c.complete and not c.error,
            "damage": c.error if (c.error or not c.complete) else None,
            "recovered": "recovery" in records, "channels": channels, "duration_s": dur,
            "metadata": records, "events": events,
            "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data)}
                            for a in c.attachments]}


# ---------------------------------------------------------------------------
# Recovery
# ---------------------------------------------------------------------------

def recover(path_in: str | os.PathLike, path_out: str | os.PathLike) -> dict:
    """Rewrite a truncated/damaged trial log (no footer) into a readable one.

    Reads with a stream reader up to the damaged point (every complete chunk and
    record before it), writes a new, complete MCAP atomically (temporary file,
    then rename) with the same channels, messages, metadata and attachments, a
    ``recovery`` metadata record (``recovered: true``, source, error, counts) and
    a ``trial_end`` record with status ``recovered`` when the original had none.
    Returns a summary dict.
    """
    path_in, path_out = Path(path_in), Path(path_out)
    if not path_in.exists():
        raise DataFormatError(path_in, None, "no such file")
    if path_in.resolve() == path_out.resolve():
        raise ValueError("recover writes a new file: --out must differ from the input")
    c = _read_stream(path_in)
    if not c.channels:
        raise DataFormatError(path_in, None, f"nothing recoverable: no complete chunk before the damage "
                                             f"({c.error or 'empty'})")
    records = _metadata_dict(c)
    path_out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path_out.name}.", suffix=".tmp", dir=path_out.parent)
    counts: dict[str, int] = {}
    last_t = 0.0
    try:
        with os.fdopen(fd, "wb") as fh:
            w = Writer(fh, compression=CompressionType.ZSTD)
            w.start(profile=(c.header.profile if c.header else MCAP_PROFILE), library=f"rig {__version__} (recover)")
            sid_map: dict[int, int] = {}
            for sid, s in sorted(c.schemas.items()):
                sid_map[sid] = w.register_schema(s.name, s.encoding, s.data)
            cid_map: dict[int, int] = {}
            for cid, chn in sorted(c.channels.items()):
                cid_map[cid] = w.register_channel(chn.topic, chn.message_encoding,
                                                  sid_map.get(chn.schema_id, 0), dict(chn.metadata))
            for m in c.messages:
                if m.channel_id not in cid_map:
                    continue
                w.add_message(cid_map[m.channel_id], log_time=m.log_time, data=m.data,
                              publish_time=m.publish_time, sequence=m.sequence)
                topic = c.topic_of(m)
                counts[topic] = counts.get(topic, 0) + 1
                last_t = max(last_t, m.log_time / 1e9)
            for md in c.metadata:
                w.add_metadata(md.name, dict(md.metadata))
            for a in c.attachments:
                w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                 media_type=a.media_type, data=a.data)
            info = {"recovered": "true", "recovered_from": str(path_in),
                    "recovery_error": c.error or ("no footer" if not c.complete else "none"),
                    "original_complete": str(bool(c.complete and not c.error)).lower(),
                    "messages": str(sum(counts.values())),
                    "recovered_utc": _dt.datetime.now(_dt.timezone.utc).isoformat()}
            info.update({f"messages{t.replace('/', '_')}": str(n) for t, n in counts.items()})
            w.add_metadata("recovery", info)
            if "trial_end" not in records:
                w.add_metadata("trial_end", {"status": "recovered", "duration_s": repr(last_t)})
            w.finish()
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path_out)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return {"messages": counts, "error": c.error, "complete_before": c.complete and not c.error,
            "last_t_s": last_t, "path": str(path_out)}


def write_trial_data(trial: TrialData, path: str | os.PathLike, *, decimated_rate_hz: float | None = None,
                     extra_metadata: dict | None = None) -> Path:
    """Write a :class:`TrialData` (e.g. an imported CSV) as a trial log, atomically.

    The samples go to the raw channel as blocks of 100 and, one message per
    sample, to the per-sample channel (``decimated_rate_hz`` metadata: the
    median sample rate); the CSV metadata goes to the ``trial`` record.
    """
    path = Path(path)
    t = np.asarray(trial.time_s, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    rate = 1.0 / dt if dt > 0 else 1.0
    meta = dict(trial.metadata)
    meta.update(extra_metadata or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        w = TrialLogWriter(tmp, loop_rate_hz=rate, decimated_rate_hz=decimated_rate_hz or rate,
                           metadata=meta, raw_encoding="base64", flush_interval_s=1e9, fsync=False)
        cols = trial.columns()
        block = {"t_s": t}
        for name, arr in cols.items():
            if name != "time_s":
                block[name] = np.asarray(arr, dtype=float)
        w._dec_every = 1  # every imported sample goes to the per-sample channel
        for i in range(0, t.size, 100):
            w.write_block({k: v[i:i + 100] for k, v in block.items()})
        for e in trial.events:
            e = dict(e)
            w.event(e.pop("t_s", 0.0), e.pop("kind", "marker"), **e)
        w.close("imported")
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


__all__ = ["TrialLogWriter", "read_trial", "read_metadata", "trial_info", "recover", "write_trial_data",
           "RAW_TOPIC", "LOG25_TOPIC", "EVENTS_TOPIC", "STATS_TOPIC", "SAMPLE_FIELDS", "BLOCK_KEYS"]
