"""Writing a trial log: :class:`TrialLogWriter` over the ``mcap`` package's Writer.

The file is chunked (zstd), with message indexes, statistics and a summary, as
``mcap.writer.Writer`` writes it. ``log_time`` is wall-clock nanoseconds since
the Unix epoch: the trial's start (``start_time_ns``, the time the writer was
opened unless given, then the wall-clock time of the first sample once the
backend reports it: :meth:`TrialLogWriter.anchor`) plus the sample's trial time
``t_s``, which stays a field of every message. A backend that reports the
wall-clock time of its blocks (the hardware loop's tick, a paced simulation)
re-anchors the clock at every block, so ``log_time`` is the time each sample was
taken even after a stall of the loop. Crash safety: the writer closes the chunk in progress,
flushes and ``os.fsync``s at least every ``flush_interval_s`` of wall time
(1 s), so a crash loses at most the last second; ``rig recover`` rewrites a
file cut off anywhere.

Listeners (``add_listener``) receive what a live view needs, in the caller's
thread, after it is queued for the file: ``("samples", {field: array})`` at the
decimated rate, ``("event", {t_s, kind, ...})`` and ``("loop_stats", {t_s,
...})``. A listener that raises is detached (``listener_errors``), never the log.
"""

from __future__ import annotations

import collections
import datetime as _dt
import json
import math
import os
import queue
import struct
import threading
import time
import uuid
import zlib
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from mcap.writer import CompressionType, Writer

from rig import __version__
from rig.jitstart import preload_cython_blas
from rig.log import decimate as _decimate_mod
from rig.log.decimate import MatrixBlockMean, decimation_factor
from rig.log.loopblock import LOOP_BLOCK_SCHEMA, PROTO_ENCODING, LoopBlockEncoder
from rig.log import loopblock as _loopblock
from rig.log.schemas import (EVENTS_TOPIC, JSON_TOPICS, LOG25_TOPIC, MCAP_PROFILE, RAW_TOPIC, RAW_V2_ENCODING,
                             RAW_V2_LAYOUT, SAMPLE_FIELDS, SCHEMAS, STATS_TOPIC, EXACT, ColumnsV2Encoder,
                             device_columns, dumps, jsonable, meta_str)

_U64_MAX = (1 << 64) - 1
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE,
                "": CompressionType.NONE}




_MI: dict = {}


def _message_index_class():
    """``mcap``'s MessageIndex record, its records written in one call (the Writer writes them
    with two ``write8`` calls per message: a quarter of the writer's time on the 25 Hz channel)."""
    cls = _MI.get("cls")
    if cls is not None:
        return cls
    from mcap.opcode import Opcode
    from mcap.records import MessageIndex

    class _MessageIndex(MessageIndex):
        def write(self, stream) -> None:
            stream.start_record(Opcode.MESSAGE_INDEX)
            stream.write2(self.channel_id)
            stream.write4(len(self.records) * 16)
            stream.write(np.array(self.records, dtype="<u8").tobytes() if self.records else b"")
            stream.finish_record()

    _MI["cls"] = _MessageIndex
    return _MessageIndex


def _log25_messages(names: list, specs: list, m: np.ndarray, cid: int, origin_ns: int, seq0: int
                    ) -> tuple[list, np.ndarray]:
    """The /log25 messages ``(channel, log_time, JSON, sequence)`` of decimated samples (columns of ``m``;
    its rows the fields ``names`` but a last ``mu``, computed here) printed with ``specs``: one printf
    template for the block's samples (one ``%`` and one split), or per sample with a non-finite value
    (null); and ``m`` with its mu row. The block's fixed costs kept low (no ``errstate``, no NaN pass over
    finite times): the writer's thread runs this for every block."""
    if names[-1] == "mu":
        nn = m[names.index("normal_1_N")] + m[names.index("normal_2_N")]
        mu = np.full(nn.shape, np.nan)
        np.divide(m[names.index("friction_N")], nn, out=mu, where=nn != 0.0)
        m = np.vstack((m, mu))
    k = m.shape[1]
    t = m[0]
    if np.isfinite(m).all():
        fmt = "{" + ",".join(f'"{nm}":{sp}' for nm, sp in zip(names, specs)) + "}"
        payloads = ("\n".join([fmt] * k) % tuple(m.T.ravel().tolist())).encode().split(b"\n")
    else:
        payloads = [("{" + ",".join(f'"{nm}":' + (sp % v if math.isfinite(v) else "null")
                                    for nm, sp, v in zip(names, specs, row)) + "}").encode() for row in m.T.tolist()]
        t = np.nan_to_num(t)
    # integer arithmetic: float64 cannot hold epoch ns exactly
    rel = np.minimum(np.maximum(np.rint(t * 1e9), -4e18), 4e18).astype(np.int64)
    rel += np.int64(origin_ns)
    ns = np.maximum(rel, 0).tolist()
    return list(zip([cid] * k, ns, payloads, range(seq0, seq0 + k))), m


#: zstd's level 3 (the ``mcap`` Writer's) with hash and chain tables of 2**14 entries instead of 2**17 / 2**16:
#: the tables stay in the core's cache; measured on a simulated hour's 1 MB chunks (docs/trial.md, "third
#: pass"): 31 % less CPU for 1.8 % more bytes (51.3 against 50.4 MB per hour, load 10.8)
ZSTD_LEVEL = 3
ZSTD_HASH_LOG = 14


def _zstd_chunk(comp, data: bytes) -> tuple[bytes, int]:
    """A chunk's zstd frame and its uncompressed CRC (both without the GIL: the compressing thread runs
    beside the writer's)."""
    return comp.compress(data), zlib.crc32(data)


class _Sink:
    """Owns the ``mcap`` Writer and the file: messages, metadata, flush (+fsync), finish.

    A full zstd chunk is compressed in a thread of its own (``rig-log-zstd``) while the caller goes on
    filling the next one, and written, in order, once compressed (:meth:`_finalize_async`): the
    Writer's records, the compression (half the log's CPU) beside the encoding, with tables that stay
    in cache (``ZSTD_HASH_LOG``). Everything that
    writes a record outside the chunks (metadata, flush, finish) first writes the chunks in flight."""

    #: compressed chunks in flight at most (1 MB each); the caller waits for the oldest beyond that
    MAX_IN_FLIGHT = 4

    def __init__(self, fh, fsync: bool, compression: str, chunk_size: int):
        self.fh = fh
        self.fsync = fsync
        self.w = Writer(fh, chunk_size=chunk_size, compression=_COMPRESSION[compression])
        self._zstd = compression == "zstd"
        self._pool = None  # the compressing thread, started with the first full chunk
        self._in_flight: collections.deque = collections.deque()

    def messages(self, items: list) -> None:
        """Add a batch of ``(channel_id, log_time, data, sequence)`` (``data`` may be a callable: a raw block
        encoded here; an item may be a callable returning such tuples: a block's 25 Hz messages). Into the
        open chunk in one pass (:meth:`_add_batch`) where this ``mcap`` version's
        Writer has the expected internals, else message by message through its public ``add_message``."""
        if any(type(it) is not tuple or callable(it[2]) for it in items):
            flat: list = []
            for it in items:
                if type(it) is not tuple:  # the messages of a block's 25 Hz samples, printed here
                    flat += it()
                else:
                    cid, ns, data, seq = it
                    flat.append((cid, ns, data() if callable(data) else data, seq))
            items = flat
        if self._fast:
            self._add_batch(items)
            return
        add = self.w.add_message
        for cid, ns, data, seq in items:
            add(cid, log_time=ns, data=data, publish_time=ns, sequence=seq)

    _HEAD = struct.Struct("<BQHIQQ")  # message record: opcode 5, length, channel, sequence, log/publish time

    @property
    def _fast(self) -> bool:
        ok = getattr(self, "_fast_ok", None)
        if ok is None:
            w = self.w
            ok = all(hasattr(w, a) for a in ("_Writer__chunk_builder", "_Writer__statistics",
                                            "_Writer__chunk_size", "_Writer__finalize_chunk",
                                            "_Writer__record_builder", "_Writer__stream",
                                            "_Writer__chunk_indices", "_Writer__index_types", "_Writer__flush"))
            ok = ok and w._Writer__chunk_builder is not None and hasattr(w._Writer__chunk_builder, "record_writer")
            self._fast_ok = ok
        return ok

    def _add_batch(self, items: list) -> None:
        """What ``Writer.add_message`` does for each message (statistics, the chunk's message index, the
        record), without a record object per message; the chunk is closed when it passes the chunk size,
        as the Writer does."""
        w = self.w
        _MessageIndex = _message_index_class()
        stats = w._Writer__statistics
        counts = stats.channel_message_counts
        limit = w._Writer__chunk_size
        pack = self._HEAD.pack
        i, n = 0, len(items)
        while i < n:
            cb = w._Writer__chunk_builder
            buf = cb.record_writer._buffer
            idx = cb.message_indices
            pos = buf.tell()
            parts = []
            t_lo = t_hi = None
            while i < n and (pos <= limit or not parts):  # as add_message: one at least, then the size check
                cid, ns, data, seq = items[i]
                i += 1
                mi = idx.get(cid)
                if mi is None:
                    mi = idx[cid] = _MessageIndex(channel_id=cid, records=[])
                mi.records.append((ns, pos))
                head = pack(5, 22 + len(data), cid, seq, ns, ns)
                parts.append(head)
                parts.append(data)
                pos += 31 + len(data)
                counts[cid] += 1
                if t_lo is None:
                    t_lo = t_hi = ns
                elif ns < t_lo:
                    t_lo = ns
                elif ns > t_hi:
                    t_hi = ns
            buf.write(b"".join(parts))
            k = len(parts) // 2
            if cb.num_messages == 0:
                cb.message_start_time, cb.message_end_time = t_lo, t_hi
            else:
                cb.message_start_time = min(cb.message_start_time, t_lo)
                cb.message_end_time = max(cb.message_end_time, t_hi)
            cb.num_messages += k
            if stats.message_count == 0:
                stats.message_start_time = t_lo
            else:
                stats.message_start_time = min(stats.message_start_time, t_lo)
            stats.message_end_time = max(stats.message_end_time, t_hi)
            stats.message_count += k
            if cb.count > limit:
                self._finalize_async() if self._zstd else w._Writer__finalize_chunk()

    def _finalize_async(self) -> None:
        """What ``Writer.__finalize_chunk`` does, with the compression and the CRC handed to the
        compressing thread: the chunk's records are taken (the builder starts the next chunk at once)
        and written by :meth:`_write_ready` once compressed, in order."""
        w = self.w
        cb = w._Writer__chunk_builder
        if cb.num_messages == 0:
            return
        w._Writer__statistics.chunk_count += 1
        data = cb.end()
        indexes = list(cb.message_indices.items())
        times = (cb.message_start_time, cb.message_end_time)
        cb.reset()
        if self._pool is None:
            import concurrent.futures

            import zstandard

            self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rig-log-zstd")
            self._comp = zstandard.ZstdCompressor(compression_params=zstandard.ZstdCompressionParameters.from_level(
                ZSTD_LEVEL, hash_log=ZSTD_HASH_LOG, chain_log=ZSTD_HASH_LOG))
        self._in_flight.append((self._pool.submit(_zstd_chunk, self._comp, data), len(data), times, indexes))
        self._write_ready(wait=len(self._in_flight) > self.MAX_IN_FLIGHT)

    def _write_ready(self, wait: bool = False, every: bool = False) -> None:
        """Write the compressed chunks in flight that are ready, in order (``wait``: at least the oldest;
        ``every``: all of them); as ``Writer.__finalize_chunk`` writes a chunk, its index and its
        message indexes."""
        from mcap.records import Chunk, ChunkIndex
        from mcap.writer import IndexType

        w = self.w
        q = self._in_flight
        while q and (every or wait or q[0][0].done()):
            wait = False
            fut, size, (t0, t1), indexes = q.popleft()
            comp, crc = fut.result()
            rb, stream = w._Writer__record_builder, w._Writer__stream
            w._Writer__flush()
            start = stream.tell()
            Chunk(compression="zstd", data=comp, message_start_time=t0, message_end_time=t1, uncompressed_crc=crc,
                  uncompressed_size=size).write(rb)
            ci = ChunkIndex(message_start_time=t0, message_end_time=t1, chunk_start_offset=start,
                            chunk_length=rb.count, message_index_offsets={}, message_index_length=0,
                            compression="zstd", compressed_size=len(comp), uncompressed_size=size)
            w._Writer__flush()
            mi_start = stream.tell()
            if w._Writer__index_types & IndexType.MESSAGE:
                for cid, index in indexes:
                    ci.message_index_offsets[cid] = mi_start + rb.count
                    index.write(rb)
            ci.message_index_length = rb.count
            w._Writer__flush()
            w._Writer__chunk_indices.append(ci)

    def _drain(self) -> None:
        """Every chunk in flight written (before a record outside the chunks, a flush, the finish)."""
        if self._in_flight:
            self._write_ready(every=True)

    def _stop_pool(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def call(self, fn: Callable, *args) -> None:
        self._drain()
        fn(self.w, *args)

    def flush(self) -> None:
        if self._zstd and self._fast:
            self._finalize_async()  # the open chunk with the same compressor as the full ones
        self._drain()
        self.w.flush()
        self._sync()

    def _sync(self) -> None:
        self.fh.flush()
        if self.fsync:
            try:
                os.fsync(self.fh.fileno())
            except OSError:
                pass

    def finish(self) -> None:
        try:
            self._drain()
            self.w.finish()
            self._sync()
        finally:
            self._stop_pool()
        self.fh.close()

    def abort(self) -> None:
        self._stop_pool()
        self.fh.close()


class _ThreadedSink:
    """Runs a :class:`_Sink` in a background thread, in order.

    Chunk compression (zstd releases the GIL) and file I/O overlap the loop. A
    bounded queue keeps the backlog small; an error in the thread is raised in
    the caller at its next call.
    """

    _STOP = object()

    def __init__(self, sink: _Sink, maxsize: int = 64):
        self._sink = sink
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._exc: BaseException | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="rig-log-writer", daemon=True)
        self._thread.start()

    def failure(self) -> BaseException | None:
        """The exception that stopped the thread (it drains the rest), or one saying it died; else None."""
        if self._exc is not None:
            return self._exc
        if not self._stopping and not self._thread.is_alive():
            return RuntimeError("the log writer thread died")
        return None

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

    def _check(self) -> None:
        if self._exc is not None:
            raise RuntimeError(f"the log writer thread failed: {self._exc!r}") from self._exc

    def _put(self, fn, *args) -> None:
        self._check()
        self._q.put((fn, args))

    def messages(self, items: list) -> None:
        self._put(self._sink.messages, items)

    def call(self, fn: Callable, *args) -> None:
        self._put(self._sink.call, fn, *args)

    def flush(self) -> None:
        self._put(self._sink.flush)

    def _stop(self, last, timeout_s: float | None = None) -> None:
        """Queue ``last`` and the stop, wait for the thread; TimeoutError after ``timeout_s`` (a hung
        write: the daemon thread is left behind, the caller goes on)."""
        self._stopping = True
        t_end = None if timeout_s is None else time.monotonic() + timeout_s

        def left() -> float | None:
            return None if t_end is None else max(0.0, t_end - time.monotonic())

        try:
            self._q.put((last, ()), timeout=left())
            self._q.put(self._STOP, timeout=left())
        except queue.Full:
            raise TimeoutError(f"the log writer did not take its last records within {timeout_s:g} s "
                               "(a write hangs: the disk?)") from None
        while True:  # a second Ctrl-C must not leave the file unfinished
            try:
                self._thread.join(left())
                break
            except KeyboardInterrupt:
                continue
        if self._thread.is_alive():
            raise TimeoutError(f"the log writer did not finish within {timeout_s:g} s (a write hangs: the disk?)")
        self._check()

    def finish(self, timeout_s: float | None = None) -> None:
        self._stop(self._sink.finish, timeout_s)

    def abort(self, timeout_s: float | None = None) -> None:
        self._stop(self._sink.abort, timeout_s)


class TrialLogWriter:
    """Writes one trial to an MCAP file (layout: :mod:`rig.log.schemas`).

    ``write_block(block)`` takes the loop's block dict (numpy arrays, one entry
    per tick, ``t_s`` required); ``event(t_s, kind, **data)``;
    ``loop_stats(t_s, stats)``; ``add_metadata(name, dict)``;
    ``close(status=...)`` writes the ``trial_end`` record and the summary. As a
    context manager an exception marks the trial ``failed``, Ctrl-C ``interrupted``.

    ``start_time_ns``: wall-clock ns since the epoch of trial time 0 (default:
    now). ``raw_columns``: ``"device"`` (default: the devices' integer counts,
    :data:`rig.log.schemas.DEVICE_COLUMNS`) or ``"exact"`` (float64, for
    imported data). ``threaded``: the raw-block encoding and the ``mcap``
    Writer (compression, file I/O, fsync) run in a background thread. ``compression``: zstd, lz4 or none.
    ``raw_format``: ``"protobuf"`` (default: ``rig.LoopBlock``, :mod:`rig.log.loopblock`, which any MCAP
    tool decodes) or ``"v2"`` (``rig.columns.v2``, kept to compare with older logs). ``raw_encoding`` and
    ``raw_dtype`` are obsolete and ignored (older encodings are read, no longer written).
    ``exclusive``: create the file with ``O_EXCL`` (``FileExistsError`` when it exists: a trial log is
    never overwritten).
    ``compact`` (``rig run`` turns it on, :func:`rig.session.logfile.open_log`): a file finished in
    many small chunks (a trial logged in real time closes one every 0.5-1 s for crash safety) is
    rewritten at close into chunks of 1 MB
    (:func:`compact_log`), atomically: zstd then sees the columns of many blocks at once
    (the hardware's columns: 57 -> 42 MB per hour, docs/trial.md).
    """

    def __init__(self, path: str | os.PathLike, *, loop_rate_hz: float = 1000.0,
                 decimated_rate_hz: float = 25.0, raw_rate_hz: float | None = None,
                 metadata: dict[str, Any] | None = None, recipe_yaml: str | None = None,
                 recipe: dict | None = None, profile: dict | None = None,
                 raw_encoding: str = "binary", raw_dtype: str | None = None, flush_interval_s: float = 1.0,
                 chunk_size: int = 1 << 20, fsync: bool = True, threaded: bool = True,
                 compression: str = "zstd", start_time_ns: int | None = None, raw_columns: str = "device",
                 raw_format: str = "protobuf", exclusive: bool = False, compact: bool = False):
        if raw_encoding not in ("binary", "base64", "json"):
            raise ValueError(f"raw_encoding must be 'binary', not {raw_encoding!r}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', not {compression!r}")
        if raw_columns not in ("device", "exact"):
            raise ValueError(f"raw_columns must be 'device' or 'exact', not {raw_columns!r}")
        if raw_format not in ("protobuf", "v2"):
            raise ValueError(f"raw_format must be 'protobuf' or 'v2', not {raw_format!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.loop_rate_hz = float(loop_rate_hz)
        self.raw_rate_hz = float(raw_rate_hz or loop_rate_hz)
        self.decimated_rate_hz = float(decimated_rate_hz)
        self._raw_every = max(1, int(round(self.loop_rate_hz / self.raw_rate_hz)))
        self._dec_every = decimation_factor(self.loop_rate_hz, self.decimated_rate_hz)
        self._dec: MatrixBlockMean | None = None  # made with the first block's plan (_decimate)
        self.start_time_ns = int(time.time_ns() if start_time_ns is None else start_time_ns)
        self._origin_ns = self.start_time_ns  # wall-clock ns of trial time 0 (re-anchored by anchor())
        self._anchored = False
        lvdt_step = None
        try:
            lvdt_step = float(profile["sensors"]["lvdt"]["quantization_um"]) if profile else None
        except (KeyError, TypeError, ValueError):
            pass
        cols = device_columns(lvdt_step) if raw_columns == "device" else {}
        self._enc = ColumnsV2Encoder(cols, self.raw_rate_hz)
        self._raw_columns = raw_columns
        self._dec_fmt: dict[str, str] = {}
        if raw_columns == "exact":
            self._enc.column = lambda key: EXACT  # every column exact
        self._raw_format = raw_format
        # the /raw codec: rig.LoopBlock in protobuf (default), or rig.columns.v2 (comparisons, benchmarks)
        self._raw_enc = LoopBlockEncoder(self._enc.column, self.raw_rate_hz) if raw_format == "protobuf" \
            else self._enc
        self.flush_interval_s = float(flush_interval_s)
        self._compact = bool(compact)
        self._fh = open(self.path, "xb" if exclusive else "wb")
        sink = _Sink(self._fh, fsync, compression, int(chunk_size))
        sink.w.start(profile=MCAP_PROFILE, library=f"rig {__version__} (mcap {_mcap_version()})")
        self._chan: dict[str, int] = {}
        for topic, schema_name in JSON_TOPICS:
            sid = sink.w.register_schema(schema_name, "jsonschema", dumps(SCHEMAS[schema_name]))
            self._chan[topic] = sink.w.register_channel(topic, "json", sid)
        self._raw_keys: tuple | None = None
        self._seq: dict[str, int] = {RAW_TOPIC: 0, **{t: 0 for t, _ in JSON_TOPICS}}
        self.counts: dict[str, int] = dict.fromkeys(self._seq, 0)
        self.ticks = 0
        self.last_t_s = 0.0
        self.closed = False
        self.status: str | None = None
        self._pending: list[dict] = []
        self._listeners: list[Callable[[str, dict], None]] = []
        self.listener_errors: list[str] = []
        self._write_trial_records(sink.w, metadata, recipe, profile, recipe_yaml)
        self._batch: list = []
        self._failure: BaseException | None = None
        self._sink = _ThreadedSink(sink) if threaded else sink
        self._threaded = bool(threaded)
        # the first chunk carries the schemas and channels: get it on disk now
        self.event(0.0, "log_start")
        self.flush()

    def _write_trial_records(self, w: Writer, metadata, recipe, profile, recipe_yaml) -> None:
        """The file's first records: ``trial`` metadata (clock, rates, identity), the recipe and the
        rig profile (JSON), the recipe's YAML as an attachment."""
        started = _dt.datetime.fromtimestamp(self.start_time_ns / 1e9, _dt.timezone.utc)
        trial = {"software_version": __version__, "started_utc": started.isoformat(),
                 "start_time_ns": self.start_time_ns, "log_time": "unix_ns",
                 "loop_rate_hz": self.loop_rate_hz, "raw_rate_hz": self.raw_rate_hz,
                 "decimated_rate_hz": self.decimated_rate_hz}
        trial.update(metadata or {})
        if not str(trial.get("trial_uid", "") or "").strip():
            trial["trial_uid"] = str(uuid.uuid4())  # every trial log has an identity (issue 21)
        self.metadata = {k: meta_str(v) for k, v in trial.items()}
        w.add_metadata("trial", self.metadata)
        if recipe is not None:
            w.add_metadata("recipe", {"json": json.dumps(jsonable(recipe), allow_nan=False),
                                      "name": str(recipe.get("name", ""))})
        if profile is not None:
            w.add_metadata("rig_profile", {"json": json.dumps(jsonable(profile), allow_nan=False)})
        if recipe_yaml is not None:
            w.add_attachment(create_time=time.time_ns(), log_time=self.start_time_ns, name="recipe.yaml",
                             media_type="application/yaml", data=recipe_yaml.encode("utf-8"))

    # -- health ------------------------------------------------------------------
    def failure(self) -> BaseException | None:
        """The exception that stopped this writer (a failed write: disk full, an I/O error; its
        writer thread died), or None while it works. Safe to call from any thread."""
        if self._failure is not None:
            return self._failure
        return self._sink.failure() if self._threaded else None

    def warm_up(self) -> None:
        """Load and compile now what writing a block needs (numba and its cache for the /raw encoder),
        so that the first block of a run is written as fast as the rest: call before a real-time loop
        starts."""
        preload_cython_blas()  # numba's target without scipy.linalg, when this is the process's first kernel
        _loopblock.warm_up()
        _decimate_mod.warm_up()

    # -- listeners (live view hook) --------------------------------------------
    def add_listener(self, fn: Callable[[str, dict], None]) -> None:
        """Call ``fn(kind, payload)`` for every decimated sample block ("samples"), event and loop stats."""
        self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[str, dict], None]) -> None:
        if fn in self._listeners:
            self._listeners.remove(fn)

    def _notify(self, kind: str, payload: dict) -> None:
        for fn in list(self._listeners):
            try:
                fn(kind, payload)
            except Exception as exc:  # a live view must never break the log
                self.listener_errors.append(f"{getattr(fn, '__name__', fn)!s}: {type(exc).__name__}: {exc}")
                self._listeners.remove(fn)

    # -- the clock -------------------------------------------------------------
    def anchor(self, t_s: float, wall_ns: int) -> None:
        """The sample at trial time ``t_s`` was taken at wall-clock ``wall_ns`` (ns since the epoch).

        The first call fixes the trial's ``start_time_ns`` (the first sample's wall-clock time,
        written as an update of the ``trial`` metadata record and flushed at once); every call
        re-anchors ``log_time`` of what follows, never backwards (a stalled loop's trial time
        falls behind the wall clock; log_time stays the time each sample was taken)."""
        if not math.isfinite(t_s):
            return
        origin = int(wall_ns) - int(round(float(t_s) * 1e9))
        if not self._anchored:
            self._anchored = True
            self._origin_ns = origin
            self.start_time_ns = origin
            started = _dt.datetime.fromtimestamp(origin / 1e9, _dt.timezone.utc)
            upd = {"start_time_ns": origin, "started_utc": started.isoformat(), "clock": "first_sample"}
            self.metadata.update({k: meta_str(v) for k, v in upd.items()})
            self.add_metadata("trial", self.metadata)
            self.flush()
        elif origin > self._origin_ns:
            self._origin_ns = origin

    @property
    def origin_ns(self) -> int:
        """The wall-clock ns of trial time 0 that ``log_time`` counts from now (``start_time_ns`` until a block
        re-anchors it after a stall of the loop)."""
        return self._origin_ns

    # -- writing ---------------------------------------------------------------
    def _ns(self, t_s: float) -> int:
        ns = self._origin_ns + int(round(float(t_s) * 1e9)) if math.isfinite(t_s) else self._origin_ns
        return min(max(ns, 0), _U64_MAX)

    def _add(self, topic: str, t_s: float, payload: bytes) -> None:
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        self._batch.append((self._chan[topic], self._ns(t_s), payload, seq))
        self.counts[topic] += 1

    def _send(self) -> None:
        if self._batch:
            batch, self._batch = self._batch, []
            self._guard(self._sink.messages, batch)

    def _guard(self, fn, *args) -> None:
        """Call the sink; an exception is kept as :meth:`failure` (unthreaded: raised here too)."""
        try:
            fn(*args)
        except BaseException as exc:
            if self._failure is None and not isinstance(exc, KeyboardInterrupt):
                self._failure = exc.__cause__ if isinstance(exc.__cause__, Exception) else exc
            raise

    def _raw_channel(self, keys: tuple) -> None:
        """Register /raw on the first block: protobuf ``rig.LoopBlock`` with its FileDescriptorSet (units in
        the field names, the field map in the metadata), or the v2 schema (scale, offset, unit per column)."""
        if self._raw_format == "protobuf":
            self._raw_enc.plan(keys)
            schema_name, schema_enc, msg_enc = LOOP_BLOCK_SCHEMA, "protobuf", PROTO_ENCODING
            schema = self._raw_enc.schema()
            meta = {**self._raw_enc.metadata(), "json_twin": LOG25_TOPIC}
        else:
            schema_name, schema_enc, msg_enc = RAW_V2_ENCODING, "jsonschema+rig.columns.v2", RAW_V2_ENCODING
            schema = dumps(self._enc.schema(keys))
            meta = {"layout": RAW_V2_LAYOUT, "columns": json.dumps(list(keys)), "json_twin": LOG25_TOPIC}

        def register(w):
            sid = w.register_schema(schema_name, schema_enc, schema)
            self._chan[RAW_TOPIC] = w.register_channel(RAW_TOPIC, msg_enc, sid, meta)

        if isinstance(self._sink, _ThreadedSink):
            # the id is needed now: register synchronously, in order, through the queue
            self._send()
            self._sink.call(register)
            self._writer_barrier()
        else:
            self._send()
            register(self._sink.w)
        self._raw_keys = keys

    def write_block(self, block: dict[str, np.ndarray], *, frozen: bool = False) -> None:
        """Log one block of loop samples (all keys as arrays of equal length; ``t_s`` required). ``frozen``:
        the caller never writes these arrays again, so the writer's thread encodes them without a copy."""
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
            keys = tuple(raw)
            if keys != self._raw_keys:
                if self._raw_keys is not None:
                    raise ValueError(f"raw block keys changed: {self._raw_keys} -> {keys}")
                self._raw_channel(keys)
            t0 = float(tr[0])
            if self._threaded:  # encode in the writer thread, from a copy unless frozen (the loop may reuse its arrays)
                copy = raw if frozen and raw is block else {k: v.copy() for k, v in raw.items()}
                self._add(RAW_TOPIC, t0, lambda: self._raw_enc.encode(copy, t0))
            else:
                self._add(RAW_TOPIC, t0, self._raw_enc.encode(raw, t0))
        # decimated per-sample channel: block means of the device values over each interval of
        # _dec_every ticks counted from the trial's first (rig.log.decimate: the anti-aliased 25 Hz log)
        self._decimate(arrays, frozen and arrays is block)
        self.ticks += n
        self.last_t_s = float(t[-1])
        if self._pending and self._pending[0]["t_s"] <= self.last_t_s + 0.5 / self.loop_rate_hz:
            self._emit_pending(self.last_t_s + 0.5 / self.loop_rate_hz)
        self._send()
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    _dec_plan: tuple | None = None
    _dec_ticks = 0              # samples pushed into the decimation so far
    _dec_in_writer = False      # the decimation runs in the writer's thread (threaded, nobody listens)

    def _decimate(self, arrays: dict[str, np.ndarray], frozen: bool = False) -> None:
        """The /log25 samples of a block: the device columns on their /raw grid (integer count times the
        scale) and block means over each interval: one compiled pass over the stacked columns, without
        the GIL (:class:`rig.log.decimate.MatrixBlockMean`). Threaded and with no listener, the pass and
        the messages run in the writer's thread, in order (the loop's thread only stacks the block's
        columns: its copy; a frozen block is stacked there too); a listener (a live view) gets its samples
        in the loop's thread."""
        if self._dec_plan is None:
            names = tuple(nm for nm in SAMPLE_FIELDS[:-1] if nm in arrays)
            cols = [self._enc.column(nm) for nm in names]
            grid = [nm != "t_s" and np.dtype(c.dtype).kind == "i" for nm, c in zip(names, cols)]
            self._dec_plan = (names,)
            self._dec = MatrixBlockMean(self._dec_every, grid,
                                        [c.offset if g else 0.0 for c, g in zip(cols, grid)],
                                        [c.scale if g else 1.0 for c, g in zip(cols, grid)])
            self._dec_in_writer = self._threaded and not self._listeners
        elif self._dec_in_writer and self._listeners:  # a listener came: the writer's pushes first
            self._writer_barrier()
            self._dec_in_writer = False
        names = self._dec_plan[0]
        n0 = self._dec_ticks
        self._dec_ticks += arrays[names[0]].shape[0]
        if self._dec_in_writer:
            k = self._dec_ticks // self._dec_every - n0 // self._dec_every  # the intervals this block completes
            cols = [arrays[nm] for nm in names]
            m = None if frozen else np.stack(cols)  # a copy: its grid rows are rounded in place
            self._later_log25(names, k, lambda dec=self._dec: dec.push(np.stack(cols) if m is None else m))
            return
        m = np.stack([arrays[nm] for nm in names])
        dec = self._dec.push(m)
        if dec is not None:
            self._emit_log25(names, dec)

    def _log25_args(self, names: tuple, k: int) -> tuple:
        """``_log25_messages``'s arguments but the samples, for ``k`` samples from now (counted here)."""
        names = list(names)
        if "normal_1_N" in names and "normal_2_N" in names:
            names.append("mu")
        args = (names, [self._dec_format(nm) for nm in names], self._chan[LOG25_TOPIC], self._origin_ns,
                self._seq[LOG25_TOPIC])
        self._seq[LOG25_TOPIC] += k
        self.counts[LOG25_TOPIC] += k
        return args

    def _later_log25(self, names: tuple, k: int, means: Callable[[], np.ndarray | None]) -> None:
        """The /log25 messages of ``k`` samples whose means ``means()`` computes in the writer's thread."""
        names, specs, cid, origin, seq0 = self._log25_args(names, k)

        def messages() -> list:
            m = means()
            return [] if m is None else _log25_messages(names, specs, m, cid, origin, seq0)[0]
        self._batch.append(messages)

    def _writer_barrier(self) -> None:
        """Wait until the writer's thread has done everything queued so far."""
        done = threading.Event()
        self._send()
        self._sink.call(lambda _w: done.set())
        while not done.wait(0.01):
            self._sink._check()

    def _emit_log25(self, names: tuple, m: np.ndarray) -> None:
        """Write decimated samples (rows of ``m``: the fields ``names``; block means, see rig.log.decimate)
        as /log25 messages, with mu (:func:`_log25_messages`), and hand them to the listeners."""
        args = self._log25_args(names, m.shape[1])
        msgs, m = _log25_messages(args[0], args[1], m, *args[2:])
        self._batch.extend(msgs)
        if self._listeners:
            self._notify("samples", dict(zip(args[0], m)))

    def _dec_format(self, name: str) -> str:
        """printf format of a /log25 field: the raw column's resolution (the same values as /raw), else repr."""
        f = self._dec_fmt.get(name)
        if f is None:
            col = self._enc.column(name)
            f = "%r"
            if name == "t_s" and self._raw_columns == "device":
                f = "%.6f"  # 1 µs: the centre of a block of ticks, without float64's tail digits
            elif name == "mu" and self._raw_columns == "device":
                f = "%.6g"
            elif name != "t_s" and np.dtype(col.dtype).kind == "i" and col.offset == 0.0:
                f = "%.9g"  # e.g. the valve's k/32767
                for d in range(10):
                    if abs(round(col.scale, d) - col.scale) < 1e-12 * max(col.scale, 1e-300):
                        # a block mean of counts resolves 1/_dec_every of a count: 3 more digits hold
                        # it exactly for any _dec_every dividing 1000 (40: 0.025 of a count)
                        f = f"%.{d + (3 if self._dec_every > 1 else 0)}f"
                        break
            self._dec_fmt[name] = f
        return f

    def schedule_events(self, events: Iterable[dict]) -> None:
        """Queue planned events (``{t_s, kind, ...}``); each is logged once a block reaches its time."""
        self._pending.extend(dict(e) for e in events)
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
        rec.update(jsonable({k: v for k, v in data.items() if k not in ("t_s", "kind")}))
        self._add(EVENTS_TOPIC, t_s, dumps(rec))
        if not self._emitting:
            self._send()
        if self._listeners:
            self._notify("event", rec)

    def loop_stats(self, t_s: float, stats: dict[str, Any]) -> None:
        """Log loop statistics (numbers) at time ``t_s`` (threaded: printed as JSON in the writer's thread)."""
        rec = {"t_s": float(t_s)}
        for k, v in stats.items():
            if k == "t_s":
                continue
            v = jsonable(v)
            rec[str(k)] = v if isinstance(v, (int, float)) or v is None else None
        later = self._threaded and not self._listeners
        self._add(STATS_TOPIC, t_s, (lambda: dumps(rec)) if later else dumps(rec))
        if not later:  # threaded: sent with the next block's messages (one hand-over per block), or at a flush
            self._send()
        if self._listeners:
            self._notify("loop_stats", rec)

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        self._send()
        rec = {str(k): meta_str(v) for k, v in data.items()}
        self._sink.call(lambda w: w.add_metadata(name, rec))

    def flush(self) -> None:
        """Close the chunk in progress, write it and fsync: everything logged so far survives a crash."""
        self._send()
        self._guard(self._sink.flush)
        self._last_flush = time.monotonic()

    _last_flush = 0.0

    def close(self, status: str = "completed", *, timeout_s: float | None = None, **summary: Any) -> None:
        """Finish the file: ``trial_end`` metadata (status and summary), summary section, fsync.

        ``timeout_s``: never wait longer than this for the writer thread (a write that hangs on a
        dead disk): TimeoutError, the file left unfinished (``rig recover``). None: wait."""
        if self.closed:
            return
        self.status = status
        if self._dec is not None and self._dec_in_writer:  # the last, partial interval (mean of its ticks)
            self._later_log25(self._dec_plan[0], int(self._dec_ticks % self._dec_every > 0), self._dec.flush)
        elif self._dec is not None and (last := self._dec.flush()) is not None:
            self._emit_log25(self._dec_plan[0], last)
        self.event(self.last_t_s, "log_end", status=status)
        # the counts of what the file holds (log_end included: `rig info` counts the same messages)
        end = {"status": status, "ticks": self.ticks, "duration_s": self.last_t_s,
               "raw_blocks": self.counts[RAW_TOPIC], "samples_decimated": self.counts[LOG25_TOPIC],
               "events": self.counts[EVENTS_TOPIC],
               "ended_utc": _dt.datetime.now(_dt.timezone.utc).isoformat()}
        end.update(summary)
        self.add_metadata("trial_end", end)
        self.closed = True
        if self._threaded:
            self._sink.finish(timeout_s)
        else:
            self._guard(self._sink.finish)
        if self._compact:
            try:
                self.compacted = compact_log(self.path)
            except OSError as exc:  # e.g. no room for the copy: the complete original stays as written
                self.compacted = {"error": f"{type(exc).__name__}: {exc}"}

    compacted: dict | None = None

    def abort(self, timeout_s: float | None = None) -> None:
        """Stop without finishing: what was flushed stays, the open chunk is lost (a crash; for tests)."""
        if not self.closed:
            self._batch = []
            self.closed = True
            if self._threaded:
                self._sink.abort(timeout_s)
            else:
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


#: compact a finished file whose chunks hold on average less than this (uncompressed; a real-time
#: trial's 0.5-1 s chunks hold 25-100 kB, a simulated trial's fill the writer's 1 MB) ...
COMPACT_BELOW_BYTES = 128 * 1024
#: and that has at least this many (a minute at the hardware's 0.5 s flushes: a short trial's size does
#: not matter, and its many chunks keep the most of it readable should the finished file be damaged)
COMPACT_MIN_CHUNKS = 120
#: ... into chunks of this size (zstd then sees many blocks' columns at once)
COMPACT_CHUNK_SIZE = 1 << 20


def compact_log(path: str | os.PathLike, chunk_size: int = COMPACT_CHUNK_SIZE) -> dict | None:
    """Rewrite a complete log written in many small chunks (real-time flushes) into chunks of
    ``chunk_size``: the same header, schemas, channels, messages (in file order), metadata and
    attachments, every chunk's CRC checked on the way; written to a temporary file, fsync'd and
    renamed over the original, so a crash leaves the original complete file. Returns
    ``{"bytes_before", "bytes_after", "chunks_before"}``, or None when the chunks are large
    enough already (or the file cannot be read whole: it is left as it is)."""
    from mcap.reader import make_reader

    from rig.data import atomic_path
    from rig.log.reader import scan

    path = Path(path)
    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception:  # noqa: BLE001 - not ours to judge here: the file stays as written
        return None
    if summary is None or len(summary.chunk_indexes) < COMPACT_MIN_CHUNKS:
        return None
    mean = sum(ci.uncompressed_size for ci in summary.chunk_indexes) / len(summary.chunk_indexes)
    if mean >= COMPACT_BELOW_BYTES:
        return None
    c = scan(path)
    if c.error or not c.complete or c.damage or c.header is None:
        return None
    before = path.stat().st_size
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        sink = _Sink(fh, False, "zstd", chunk_size)  # atomic_path fsyncs the finished copy
        w = sink.w
        w.start(profile=c.header.profile, library=c.header.library)
        sid = {i: w.register_schema(s.name, s.encoding, s.data) for i, s in sorted(c.schemas.items())}
        cid = {i: w.register_channel(ch.topic, ch.message_encoding, sid.get(ch.schema_id, 0), dict(ch.metadata))
               for i, ch in sorted(c.channels.items())}
        w.flush()  # the schemas and channels in a first chunk of their own, as the writer does
        for md in c.metadata:
            w.add_metadata(md.name, dict(md.metadata))
        for a in c.attachments:
            w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                             media_type=a.media_type, data=a.data)
        sink.messages([(cid[m.channel_id], m.log_time, m.data, m.sequence) for m in c.messages
                       if m.channel_id in cid])
        sink.finish()  # the chunks in flight, then the summary
    return {"bytes_before": before, "bytes_after": path.stat().st_size, "chunks_before": len(summary.chunk_indexes)}


def _mcap_version() -> str:
    try:
        from importlib.metadata import version

        return version("mcap")
    except Exception:  # pragma: no cover
        return "?"
