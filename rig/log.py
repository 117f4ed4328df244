"""The trial log: one MCAP file per trial.

Layout (chunked, zstd (level -1 by default), message index and summary kept;
written by :class:`_McapFile`, a minimal MCAP writer for this hot path, and
read with the ``mcap`` package):

``/raw`` (no schema; message encoding ``rig.columns.v1``)
    The 1 kHz loop data as blocks of samples (1 s each by default): every key of
    the loop's block dict (``t_s, position_ref_um, position_um, friction_N,
    normal_1_N, normal_2_N, valve_cmd, pid_p, pid_i, pid_d, dither`` and, from the
    simulation, ``true_position_um, true_velocity_um_s, true_mu``) as binary
    columns: ``b"RIGC"``, a little-endian u32 header length H, H bytes of JSON
    header ``{t0_s, n, rate_hz, fields: [key, ...], dtypes: ["<f8" | "<f4", ...]}``
    padded with spaces so the columns start at a multiple of 8, then each key's
    ``n`` little-endian floats in order (``RAW_BINARY_LAYOUT``, also in the
    channel's metadata). ``log_time`` = the block's first sample time. Older or
    optional encodings (``raw_encoding``): ``base64`` (JSON with base64 arrays,
    schema ``rig.RawBlock``) and ``json`` (number lists); all are read back.
``/log25`` (schema ``rig.Sample``, ``jsonschema`` / ``json``)
    One message per sample at the decimated rate (25 Hz like the paper's log,
    section 4.2): ``t_s, position_um, friction_N, normal_1_N, normal_2_N,
    position_ref_um, valve_cmd``; ``log_time`` = the sample time, so Foxglove
    plots it over time. Decimation takes every n-th loop sample (the paper's
    logger sampled the analog-filtered signals; the rig's sensors are filtered
    at 100 Hz / 10 Hz upstream), no extra averaging.
``/events`` (schema ``rig.Event``, json)
    ``{t_s, kind, ...}``: segment start/end, velocity steps, stepped-pass levels,
    trial start/end, interruption, operator markers.
``/loop_stats`` (schema ``rig.LoopStats``, json)
    ``{t_s, ...}`` numbers: period statistics, tracking error, real-time factor.

JSON channels are written with ``allow_nan=False`` (non-finite numbers become
``null``). Metadata records: ``trial`` (recipe name, lubricant, normal_force_N,
seed, software_version, trial index, loop and log rates, start time), ``recipe``
(the validated recipe as JSON), ``rig_profile`` (the profile as JSON),
``trial_end`` (status ``completed`` / ``interrupted`` / ``failed``, counts), and,
in a file rewritten by :func:`recover`, ``recovery``. The recipe YAML is attached
as ``recipe.yaml``. Time zero is the start of the trial (log_time in ns since then).

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
import struct
import time
import zlib
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Attachment, AttachmentIndex, Channel, ChunkIndex, DataEnd, Footer, Header, Message,
                          Metadata, MetadataIndex, Schema, Statistics, SummaryOffset)

from rig import __version__
from rig.data import DataFormatError, TrialData, atomic_path

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
RAW_ENCODINGS = ("binary", "base64", "json")
RAW_BINARY_ENCODING = "rig.columns.v1"  # message encoding of the /raw channel in the binary layout
RAW_BINARY_MAGIC = b"RIGC"
RAW_BINARY_LAYOUT = (
    "b'RIGC', u32 LE header length H, H bytes of UTF-8 JSON header {t0_s, n, rate_hz, fields: [key, ...], "
    "dtypes: ['<f8' | '<f4', ...]} padded with spaces so the columns start at a multiple of 8, then for each "
    "key in order its n values as little-endian floats of its dtype (t_s always <f8)")

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


def _block_stats_py(ref, pos, f, n1, n2, valve, acc):  # pragma: no cover - compiled
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


_block_stats_jit = None


def _block_stats(ref, pos, f, n1, n2, valve, acc) -> None:
    """numba-compiled :func:`_block_stats_py` (compiled/loaded from the cache on first use, so that
    reading a log does not import numba)."""
    global _block_stats_jit
    if _block_stats_jit is None:
        from numba import njit

        _block_stats_jit = njit(cache=True)(_block_stats_py)
    _block_stats_jit(ref, pos, f, n1, n2, valve, acc)


_MAGIC = b"\x89MCAP0\r\n"
# a Message record: opcode 0x05, record length, channel id, sequence, log_time, publish_time, then the data
_MSG_HEAD = struct.Struct("<BQHIQQ")
_MSG_HEAD_LEN = 22  # channel id + sequence + two times


class _McapFile:
    """A minimal MCAP writer (https://mcap.dev/spec) for the trial log's hot path.

    The file is standard MCAP, read by ``mcap``'s readers and Foxglove: header;
    schemas and channels as records in the data section; messages in chunks
    (``zstd`` at a chosen level, ``lz4`` or none) each followed by its message
    indexes; metadata and attachments between chunks; then a summary section
    (schemas, channels, statistics, chunk / attachment / metadata indexes,
    summary offsets) and the footer. The records other than messages and chunks
    are serialised by ``mcap.records``. Compared to ``mcap.writer.Writer`` it adds
    a batch of messages in one call (one ``struct`` pack per message instead of
    a dozen Python calls) and lets the compression level be chosen: noisy
    float64 loop data compresses only 1.3-1.5x whatever the level, and zstd's
    default level 3 costs about 3x the CPU time of level -1.
    """

    def __init__(self, fh, *, compression: str = "zstd", level: int = -1, chunk_size: int = 1 << 20,
                 crc: bool = True):
        self.fh = fh
        self.pos = 0
        if compression == "zstd":
            import zstandard
            self._compress = zstandard.ZstdCompressor(level=level).compress
        elif compression == "lz4":
            import lz4.frame
            self._compress = lambda data: lz4.frame.compress(data, compression_level=level)
        elif compression in ("", "none"):
            compression, self._compress = "", None
        else:
            raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', not {compression!r}")
        self.compression = compression
        self._comp_b = struct.pack("<I", len(compression)) + compression.encode()
        self.chunk_size = int(chunk_size)
        self.crc = crc
        self.schemas: list = []
        self.channels: list = []
        self.chunk_indexes: list = []
        self.attachment_indexes: list = []
        self.metadata_indexes: list = []
        self.channel_counts: dict[int, int] = {}
        self.message_count = 0
        self.t_start: int | None = None
        self.t_end = 0
        self._reset_chunk()

    def _reset_chunk(self) -> None:
        self._parts: list = []
        self._len = 0
        self._index: dict[int, list] = {}
        self._c_start: int | None = None
        self._c_end = 0

    def _write(self, data: bytes) -> None:
        self.fh.write(data)
        self.pos += len(data)

    def _record(self, rec) -> tuple[int, int]:
        rb = RecordBuilder()
        rec.write(rb)
        data = rb.end()
        offset = self.pos
        self._write(data)
        return offset, len(data)

    def start(self, profile: str, library: str) -> None:
        self._write(_MAGIC)
        self._record(Header(profile=profile, library=library))

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        s = Schema(id=len(self.schemas) + 1, name=name, encoding=encoding, data=data)
        self.schemas.append(s)
        self._record(s)
        return s.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict | None = None) -> int:
        c = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=message_encoding,
                    schema_id=schema_id, metadata=dict(metadata or {}))
        self.channels.append(c)
        self.channel_counts[c.id] = 0
        self._record(c)
        return c.id

    def add_messages(self, items) -> None:
        """``items``: ``(channel_id, log_time_ns, data, sequence)``; publish_time = log_time."""
        pack = _MSG_HEAD.pack
        parts = self._parts
        index = self._index
        counts = self.channel_counts
        off = self._len
        lo = self._c_start
        hi = self._c_end
        for cid, ns, data, seq in items:
            head = pack(5, _MSG_HEAD_LEN + len(data), cid, seq, ns, ns)
            ix = index.get(cid)
            if ix is None:
                ix = index[cid] = []
            ix.append((ns, off))
            parts.append(head)
            parts.append(data)
            off += 31 + len(data)
            counts[cid] += 1
            if lo is None or ns < lo:
                lo = ns
            if ns > hi:
                hi = ns
        self.message_count += len(items)
        self._len = off
        self._c_start = lo
        self._c_end = hi
        if off >= self.chunk_size:
            self._finalize_chunk()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset, length = self._record(Metadata(name=name, metadata=data))
        self.metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_attachment(self, create_time: int, log_time: int, name: str, media_type: str, data: bytes) -> None:
        offset, length = self._record(Attachment(create_time=create_time, log_time=log_time, name=name,
                                                 media_type=media_type, data=data))
        self.attachment_indexes.append(AttachmentIndex(offset=offset, length=length, log_time=log_time,
                                                       create_time=create_time, data_size=len(data), name=name,
                                                       media_type=media_type))

    def _finalize_chunk(self) -> None:
        if not self._parts:
            return
        raw = b"".join(self._parts)
        comp = self._compress(raw) if self._compress is not None else raw
        crc = zlib.crc32(raw) if self.crc else 0
        start, end = self._c_start or 0, self._c_end
        # Chunk record: start, end, uncompressed size, uncompressed crc, compression, records (u64 length)
        body = struct.pack("<QQQI", start, end, len(raw), crc) + self._comp_b + struct.pack("<Q", len(comp))
        chunk_offset = self.pos
        self._write(struct.pack("<BQ", 0x06, len(body) + len(comp)) + body)
        self._write(comp)
        chunk_length = self.pos - chunk_offset
        mi_offsets: dict[int, int] = {}
        mi_start = self.pos
        for cid, entries in self._index.items():
            # Message Index record: channel id, then (log_time, offset) pairs as a u32-length-prefixed array
            mi_offsets[cid] = self.pos
            flat = [v for pair in entries for v in pair]
            self._write(struct.pack("<BQHI%dQ" % len(flat), 0x07, 6 + 8 * len(flat), cid, 8 * len(flat), *flat))
        self.chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_offset,
            chunk_length=chunk_length, message_index_offsets=mi_offsets, message_index_length=self.pos - mi_start,
            compression=self.compression, compressed_size=len(comp), uncompressed_size=len(raw)))
        if self.t_start is None or start < self.t_start:
            self.t_start = start
        self.t_end = max(self.t_end, end)
        self._reset_chunk()

    def flush(self) -> None:
        """Close the chunk in progress and write everything to the file object (no fsync)."""
        self._finalize_chunk()
        self.fh.flush()

    def finish(self) -> None:
        """Last chunk, data end, summary section, footer, closing magic."""
        self._finalize_chunk()
        self._record(DataEnd(data_section_crc=0))
        summary_start = self.pos
        rb = RecordBuilder()
        offsets = []

        def group(opcode, records):
            g0 = rb.count
            for r in records:
                r.write(rb)
            if rb.count > g0:
                offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + g0,
                                             group_length=rb.count - g0))

        stats = Statistics(message_count=self.message_count, schema_count=len(self.schemas),
                           channel_count=len(self.channels), attachment_count=len(self.attachment_indexes),
                           metadata_count=len(self.metadata_indexes), chunk_count=len(self.chunk_indexes),
                           message_start_time=self.t_start or 0, message_end_time=self.t_end,
                           channel_message_counts={k: v for k, v in self.channel_counts.items() if v})
        group(Opcode.SCHEMA, self.schemas)
        group(Opcode.CHANNEL, self.channels)
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self.chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self.attachment_indexes)
        group(Opcode.METADATA_INDEX, self.metadata_indexes)
        summary_offset_start = summary_start + rb.count
        for o in offsets:
            o.write(rb)
        summary = rb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._write(summary)
        self._record(Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
                            summary_crc=crc))
        self._write(_MAGIC)
        self.fh.flush()


class _Sink:
    """Owns the MCAP writer and the file: adds messages/metadata, flushes (+fsync), finishes."""

    def __init__(self, writer: _McapFile, fh, fsync: bool):
        self.w = writer
        self.fh = fh
        self.fsync = fsync

    def messages(self, items: list) -> None:
        self.w.add_messages(items)

    def metadata(self, name: str, data: dict) -> None:
        self.w.add_metadata(name, data)

    def flush(self) -> None:
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

    ``threaded`` (default): the MCAP writer (chunk compression, file I/O,
    fsync) runs in a background thread, fed in order through a bounded queue;
    the caller's thread only encodes.

    ``raw_encoding``: ``binary`` (default, ``rig.columns.v1``), ``base64`` or
    ``json``; ``raw_dtype``: ``float64`` (exact) or ``float32`` (``t_s`` stays
    float64); ``compression``: ``zstd`` (default, at ``compression_level`` -1),
    ``lz4`` or ``none``. Each ``write_block`` call is one raw message, so the
    caller's block size is the message size (``rig run``: ``log.block_s``, 1 s).
    """

    def __init__(self, path: str | os.PathLike, *, loop_rate_hz: float = 1000.0,
                 decimated_rate_hz: float = 25.0, raw_rate_hz: float | None = None,
                 metadata: dict[str, Any] | None = None, recipe_yaml: str | None = None,
                 recipe: dict | None = None, profile: dict | None = None,
                 raw_encoding: str = "binary", raw_dtype: str = "float64", flush_interval_s: float = 1.0,
                 chunk_size: int = 1 << 20, fsync: bool = True, threaded: bool = True,
                 compression: str = "zstd", compression_level: int = -1):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.loop_rate_hz = float(loop_rate_hz)
        self.raw_rate_hz = float(raw_rate_hz or loop_rate_hz)
        self.decimated_rate_hz = float(decimated_rate_hz)
        self._raw_every = max(1, int(round(self.loop_rate_hz / self.raw_rate_hz)))
        self._dec_every = max(1, int(round(self.loop_rate_hz / self.decimated_rate_hz)))
        if raw_encoding not in RAW_ENCODINGS:
            raise ValueError(f"raw_encoding must be one of {', '.join(RAW_ENCODINGS)}, not {raw_encoding!r}")
        self.raw_encoding = raw_encoding
        if raw_dtype not in ("float64", "float32"):
            raise ValueError(f"raw_dtype must be 'float64' or 'float32', not {raw_dtype!r}")
        self._raw_dtype = np.dtype("<f8" if raw_dtype == "float64" else "<f4")
        self._raw_enc_name = B64_ENCODING if raw_dtype == "float64" else B64_F4_ENCODING
        self._col_head: tuple | None = None  # (keys, cached header tail) of the binary raw blocks
        self.flush_interval_s = float(flush_interval_s)
        self._fsync = fsync
        self._fh = open(self.path, "wb")
        try:
            self._w = _McapFile(self._fh, compression=compression, level=compression_level, chunk_size=chunk_size)
        except BaseException:
            self._fh.close()
            raise
        self._w.start(profile=MCAP_PROFILE, library=f"rig {__version__}")
        self._chan: dict[str, int] = {}
        for topic, schema_name in TOPICS:
            if topic == RAW_TOPIC and raw_encoding == "binary":
                # no schema: the message encoding names the documented binary layout
                self._chan[topic] = self._w.add_channel(topic, RAW_BINARY_ENCODING, 0,
                                                        {"layout": RAW_BINARY_LAYOUT})
                continue
            sid = self._w.add_schema(schema_name, "jsonschema", _dumps(SCHEMAS[schema_name]))
            self._chan[topic] = self._w.add_channel(topic, "json", sid)
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
            if self.raw_encoding == "binary":
                payload = self._columns_payload(raw, t0, int(tr.size))
            elif self.raw_encoding == "base64":
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
                payloads = [(fmt % tuple(row)).encode() for row in rows]
            else:
                payloads = [_dumps({k: (v if math.isfinite(v) else None) for k, v in zip(names, row)})
                            for row in rows]
            k = len(payloads)
            ns = np.maximum(np.rint(m[0] * 1e9), 0).astype(np.int64).tolist()
            seq0 = self._seq[LOG25_TOPIC]
            cid = self._chan[LOG25_TOPIC]
            self._batch.extend(zip([cid] * k, ns, payloads, range(seq0, seq0 + k)))
            self._seq[LOG25_TOPIC] = seq0 + k
            self.counts[LOG25_TOPIC] += k
        self.ticks += n
        self.last_t_s = float(t[-1])
        self._running_stats(arrays)
        if self._pending and self._pending[0]["t_s"] <= self.last_t_s + 0.5 / self.loop_rate_hz:
            self._emit_pending(self.last_t_s + 0.5 / self.loop_rate_hz)
        self._send()
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def _columns_payload(self, raw: dict[str, np.ndarray], t0: float, n: int) -> bytes:
        """One raw block in the binary column layout (see RAW_BINARY_LAYOUT)."""
        keys = tuple(raw)
        head = self._col_head
        if head is None or head[0] != keys:
            dtypes = ["<f8" if k == "t_s" else self._raw_dtype.str for k in keys]
            tail = ('"rate_hz":%s,"fields":%s,"dtypes":%s}' % (
                json.dumps(self.raw_rate_hz), json.dumps(list(keys)), json.dumps(dtypes)))
            head = self._col_head = (keys, tail, [np.dtype(d) for d in dtypes])
        text = ('{"t0_s":%r,"n":%d,' % (t0, n) + head[1]).encode()
        text += b" " * (-(8 + len(text)) % 8)  # columns start 8-byte aligned
        parts = [RAW_BINARY_MAGIC, struct.pack("<I", len(text)), text]
        for v, dt in zip(raw.values(), head[2]):
            parts.append((v if v.dtype == dt else v.astype(dt)).tobytes())
        return b"".join(parts)

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


def _decode_columns(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """Decode a binary raw block (RAW_BINARY_LAYOUT) -> (header, {key: float64 array})."""
    if data[:4] != RAW_BINARY_MAGIC or len(data) < 8:
        raise ValueError("not a rig.columns.v1 block (bad magic)")
    (hlen,) = struct.unpack_from("<I", data, 4)
    head = json.loads(data[8:8 + hlen])
    n = int(head["n"])
    off = 8 + hlen
    out: dict[str, np.ndarray] = {}
    for key, dt in zip(head["fields"], head["dtypes"]):
        dt = np.dtype(dt)
        end = off + n * dt.itemsize
        if end > len(data):
            raise ValueError(f"block truncated in field {key}")
        out[key] = np.frombuffer(data, dtype=dt, count=n, offset=off).astype(np.float64)
        off = end
    if off != len(data):
        raise ValueError(f"{len(data) - off} bytes after the last field")
    return head, out


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
    from mcap.stream_reader import StreamReader

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
    from mcap.reader import make_reader

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
            chn = c.channels.get(m.channel_id)
            if chn is not None and chn.message_encoding == RAW_BINARY_ENCODING:
                try:
                    head, fields = _decode_columns(m.data)
                except (ValueError, KeyError, TypeError) as exc:
                    raise DataFormatError(path, None, f"raw block at log_time {m.log_time} ns: {exc}") from None
                for k, arr in fields.items():
                    cols.setdefault(k, []).append(arr)
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
        # the last raw block covers up to block_s (1 s) beyond its log_time
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
    from mcap.writer import CompressionType, Writer

    counts: dict[str, int] = {}
    last_t = 0.0
    with atomic_path(path_out) as tmp, open(tmp, "wb") as fh:
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
    with atomic_path(path) as tmp:
        w = TrialLogWriter(tmp, loop_rate_hz=rate, decimated_rate_hz=decimated_rate_hz or rate,
                           metadata=meta, flush_interval_s=1e9, fsync=False)
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
    return path


__all__ = ["TrialLogWriter", "read_trial", "read_metadata", "trial_info", "recover", "write_trial_data",
           "RAW_TOPIC", "LOG25_TOPIC", "EVENTS_TOPIC", "STATS_TOPIC", "SAMPLE_FIELDS", "BLOCK_KEYS"]
