"""Reading a trial log, verified: every chunk's CRC is checked.

A chunk whose CRC does not match (or that does not decompress) is dropped with
a :class:`LogDamageWarning` naming its time range and the channels it held;
the other chunks' data is kept. ``strict=True`` turns the damage into a
:class:`rig.data.DataFormatError`. A file cut off (no footer) is an error that
names ``rig recover``, which rewrites it from every intact chunk.
Reads the protobuf ``rig.LoopBlock`` raw channel (:mod:`rig.log.loopblock`), v2 (``rig.columns.v2``), v1
and the older JSON raw blocks alike.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
import zlib
from io import BytesIO
from pathlib import Path
from typing import TYPE_CHECKING

from mcap.records import (Attachment, Channel, Chunk, Footer, Header, Message, MessageIndex, Metadata, Schema)
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.stream_reader import StreamReader

from rig.errors import DataFormatError
from rig.log.topics import EVENTS_TOPIC, LOG25_TOPIC, RAW_TOPIC

if TYPE_CHECKING:
    import numpy as np

    from rig.data import TrialData
# numpy, the data layer and the raw codecs are imported where a trial's samples are read (read_trial), not
# at import: `rig info` (trial_info) reads a log's records only, and numpy's import was a quarter of its time


class LogDamageWarning(UserWarning):
    """Part of a trial log is damaged (a chunk failed its CRC); the rest was read."""


_MAGICS = {b"\x89PNG": "a PNG image", b"%PDF": "a PDF document", b"PK\x03\x04": "a ZIP archive",
           b"\x1f\x8b": "a gzip file", b"# rig-trial-csv": "a measured-data CSV (use `rig import`)"}


def _sniff(path: Path) -> None:
    """Clear errors for what is not an MCAP log at all (a directory, an image, a CSV, ...)."""
    if not path.exists():
        raise DataFormatError(path, None, "no such file")
    if path.is_dir():
        raise DataFormatError(path, None, "is a directory, not an MCAP trial log")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise DataFormatError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    if head[:8] == b"\x89MCAP0\r\n":
        return
    if not head:
        raise DataFormatError(path, None, "empty file, not an MCAP trial log")
    for magic, what in _MAGICS.items():
        if head.startswith(magic):
            raise DataFormatError(path, None, f"this is {what}, not an MCAP trial log")
    raise DataFormatError(path, None, "not an MCAP trial log (it does not start with the MCAP magic bytes)")


class LogContent:
    """Everything read from an MCAP: intact records, and what was damaged."""

    def __init__(self):
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.messages: list[Message] = []
        self.metadata: list[Metadata] = []
        self.attachments: list[Attachment] = []
        self.complete = False
        self.error: str | None = None  # where reading stopped (truncation / broken framing)
        self.damage: list[dict] = []   # corrupt chunks: {t_start_s, t_end_s, channels, error}
        self.header = None
        self.counts: dict[int, int] = {}
        self.t_range: dict[int, tuple[int, int]] = {}

    def topic_of(self, msg: Message) -> str:
        ch = self.channels.get(msg.channel_id)
        return ch.topic if ch else f"#{msg.channel_id}"

    def metadata_dict(self) -> dict[str, dict[str, str]]:
        out: dict[str, dict[str, str]] = {}
        for m in self.metadata:
            out.setdefault(m.name, {}).update(m.metadata)
        return out

    @property
    def start_time_ns(self) -> int:
        """Wall-clock ns of trial time 0 (0 in logs before log_time was the epoch)."""
        try:
            return int(self.metadata_dict().get("trial", {}).get("start_time_ns", 0))
        except ValueError:
            return 0

    def damage_text(self) -> str:
        parts = []
        for d in self.damage:
            parts.append(f"{d['error']} in the chunk covering t = {d['t_start_s']:.3f}..{d['t_end_s']:.3f} s "
                         f"(channels lost there: {', '.join(d['channels']) or 'unknown'})")
        return "; ".join(parts)


_MSG_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log_time, publish_time
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x03, 0x04, 0x05


def _chunk_data(chunk: Chunk) -> bytes:
    """A chunk's records, decompressed and checked against its CRC (ValueError naming what is wrong)."""
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("CRC mismatch")
    return data


def _chunk_records(data: bytes, ids: set[int] | None, topics: set[str] | None = None
                   ) -> tuple[list, dict[int, list[int]]]:
    """A chunk's records: the schemas, channels and the messages of channels ``ids`` (None: all; a channel
    of ``topics`` met in the chunk joins ``ids``) as
    records, and for every channel ``[messages, first log_time, last log_time]`` from the message headers
    alone, so the 25 Hz and raw messages cost no Python objects unless asked for. ValueError for a
    broken record (the chunk is then dropped whole)."""
    recs: list = []
    stats: dict[int, list[int]] = {}
    pos, end = 0, len(data)
    unpack = _MSG_HEAD.unpack_from
    while pos < end:
        if end - pos < 9:
            raise ValueError("chunk ends inside a record header")
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        body = pos + 9
        nxt = body + length
        if nxt > end:
            raise ValueError("record runs past the end of its chunk")
        if op == _OP_MESSAGE:
            if length < 22:
                raise ValueError("message record too short")
            _, _, cid, seq, log_time, pub = unpack(data, pos)
            st = stats.get(cid)
            if st is None:
                stats[cid] = [1, log_time, log_time]
            else:
                st[0] += 1
                if log_time < st[1]:
                    st[1] = log_time
                elif log_time > st[2]:
                    st[2] = log_time
            if ids is None or cid in ids:
                recs.append(Message(channel_id=cid, sequence=seq, log_time=log_time, publish_time=pub,
                                    data=data[body + 22:nxt]))
        elif op in (_OP_SCHEMA, _OP_CHANNEL):
            stream = ReadDataStream(BytesIO(data[body:nxt]))
            rec = Schema.read(stream) if op == _OP_SCHEMA else Channel.read(stream)
            recs.append(rec)
            if ids is not None and topics and isinstance(rec, Channel) and rec.topic in topics:
                ids.add(rec.id)
        pos = nxt
    return recs, stats


class _Scan:
    """The state of one :func:`scan`: what is kept, what is counted, the chunk that failed last."""

    def __init__(self, topics: set[str] | None):
        self.c = LogContent()
        self.topics = topics
        self.keep_ids: set[int] = set()
        self.bad_chunk: dict | None = None

    def count(self, cid: int, n: int, lo: int, hi: int) -> None:
        c = self.c
        c.counts[cid] = c.counts.get(cid, 0) + n
        r = c.t_range.get(cid)
        c.t_range[cid] = (lo, hi) if r is None else (min(r[0], lo), max(r[1], hi))

    def take(self, rec) -> None:
        if isinstance(rec, Message):
            if self.topics is None or rec.channel_id in self.keep_ids:
                self.c.messages.append(rec)
        elif isinstance(rec, Schema):
            self.c.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.c.channels[rec.id] = rec
            if self.topics is not None and rec.topic in self.topics:
                self.keep_ids.add(rec.id)

    def _damaged(self, chunk: Chunk, error: str) -> None:
        self.bad_chunk = {"start_ns": chunk.message_start_time, "end_ns": chunk.message_end_time,
                          "channel_ids": [], "error": error}
        self.c.damage.append(self.bad_chunk)

    def chunk(self, rec: Chunk) -> None:
        """A chunk: CRC and decompression checked, its records taken and counted; else it is damage."""
        self.bad_chunk = None
        try:
            data = _chunk_data(rec)
        except Exception as exc:  # CRC mismatch, a decompression error
            self._damaged(rec, "CRC mismatch" if "crc" in str(exc).lower() else f"{type(exc).__name__}: {exc}")
            return
        try:
            recs, stats = _chunk_records(data, None if self.topics is None else self.keep_ids, self.topics)
        except Exception as exc:  # broken records inside a chunk whose CRC matched
            self._damaged(rec, f"{type(exc).__name__}: {exc}")
            return
        for r in recs:
            self.take(r)
        for cid, (n, lo, hi) in stats.items():
            self.count(cid, n, lo, hi)

    def record(self, rec) -> None:
        c = self.c
        if isinstance(rec, Chunk):
            self.chunk(rec)
        elif isinstance(rec, Message):
            self.count(rec.channel_id, 1, rec.log_time, rec.log_time)
            self.take(rec)
        elif isinstance(rec, MessageIndex):
            if self.bad_chunk is not None:
                self.bad_chunk["channel_ids"].append(rec.channel_id)
        elif isinstance(rec, (Schema, Channel)):
            self.take(rec)
        elif isinstance(rec, Header):
            c.header = rec
        elif isinstance(rec, Metadata):
            c.metadata.append(rec)
        elif isinstance(rec, Attachment):
            c.attachments.append(rec)
        elif isinstance(rec, Footer):
            c.complete = True


class _Records(StreamReader):
    """``mcap``'s StreamReader, but a MessageIndex record is read as its channel id only (all the scan
    uses: the channels of a damaged chunk); its entries, 16 bytes per message read two ``read8`` calls
    each, were 40 % of ``rig info``'s time, and the reader skips them in one read (its padding)."""

    def _read_record(self, opcode: int, length: int):
        if opcode == Opcode.MESSAGE_INDEX:
            return MessageIndex(self._stream.read2(), [])
        return super()._read_record(opcode, length)


def _framing_error(exc: Exception) -> str:
    """What broke the file's framing, in one line."""
    name = type(exc).__name__
    if name in ("EndOfFile", "RecordLengthLimitExceeded"):  # a record runs past the end of the file
        return "file ends in the middle of a record (truncated)"
    return f"{name}: {exc}" if str(exc) else name


def scan(path: str | os.PathLike, topics: set[str] | None = None) -> LogContent:
    """Read every record up to the end or to where the framing breaks (never raises for damage).

    Chunks are checked against their CRC; a bad one goes to ``damage`` and its
    messages are dropped. ``topics``: keep only these channels' messages (every
    message is still counted in ``counts`` / ``t_range``).
    """
    path = Path(path)
    _sniff(path)
    sc = _Scan(topics)
    c = sc.c
    # one thread: decompressing and CRC-checking the chunks on a second thread ahead of the parser was tried
    # and cost more than it saved (the scan of the main job's log: 0.12 s of CPU and 0.19-0.22 s of wall
    # against 0.07 s and 0.09-0.15 s, load 9.5); zstd and zlib are the bulk of it (68 and 10 ms)
    with open(path, "rb") as fh:
        try:
            for rec in _Records(fh, emit_chunks=True, record_size_limit=max(64, path.stat().st_size)).records:
                sc.record(rec)
        except Exception as exc:  # the point where the framing broke: keep everything before it
            c.error = _framing_error(exc)
    if c.header is None:
        raise DataFormatError(path, None, f"not a readable MCAP trial log ({c.error or 'no header'})")
    t0 = c.start_time_ns
    for d in c.damage:
        d["t_start_s"] = (d.pop("start_ns") - t0) / 1e9
        d["t_end_s"] = (d.pop("end_ns") - t0) / 1e9
        ids = d.pop("channel_ids")
        d["channels"] = sorted({c.channels[i].topic if i in c.channels else f"#{i}" for i in ids})
    return c


def read_log(path: str | os.PathLike, topics: set[str] | None = None, *, strict: bool = False) -> LogContent:
    """A complete log, verified. Truncated -> DataFormatError naming ``rig recover``; corrupt chunks ->
    a LogDamageWarning (DataFormatError under ``strict``)."""
    path = Path(path)
    c = scan(path, topics)
    if c.error or not c.complete:
        raise DataFormatError(path, None, f"damaged or truncated MCAP ({c.error or 'no footer'}); rewrite it "
                                          f"with `rig recover {path} --out FIXED.mcap`")
    if c.damage:
        msg = f"{len(c.damage)} damaged chunk(s) skipped: {c.damage_text()}"
        if strict:
            raise DataFormatError(path, None, msg)
        warnings.warn(f"{path}: {msg}", LogDamageWarning, stacklevel=3)
    return c


def _events(c: LogContent) -> list[dict]:
    ev = [json.loads(m.data) for m in c.messages if c.topic_of(m) == EVENTS_TOPIC]
    ev.sort(key=lambda e: e["t_s"])
    return ev


def read_metadata(path: str | os.PathLike) -> dict[str, dict[str, str]]:
    """All metadata records of a (complete) trial log, by record name."""
    return read_log(path, topics=set()).metadata_dict()


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


def _channel_name(channel: str) -> str:
    ch = channel.lower().replace(" ", "")
    if ch in ("25", "25hz", "log25", "decimated"):
        return "25hz"
    if ch in ("raw", "1khz", "loop"):
        return "raw"
    raise ValueError(f"channel must be 'raw' or '25hz', not {channel!r}")


def _raw_arrays(c: LogContent, path: Path) -> dict[str, np.ndarray]:
    """The /raw channel's columns in physical units, in the loop's column order, whatever the layout
    (protobuf blocks decoded together per channel; v2 counts, v1 floats, JSON blocks)."""
    import numpy as np

    from rig.log.loopblock import PROTO_ENCODING, decode_loop_blocks
    from rig.log.schemas import BLOCK_KEYS, decode_raw

    cols: dict[str, list[np.ndarray]] = {}
    proto: dict[int, list[bytes]] = {}  # protobuf blocks, decoded together per channel
    for m in c.messages:
        if c.topic_of(m) != RAW_TOPIC:
            continue
        enc = c.channels[m.channel_id].message_encoding
        if enc == PROTO_ENCODING:
            proto.setdefault(m.channel_id, []).append(m.data)
            continue
        try:
            fields = decode_raw(enc, m.data)
        except (ValueError, KeyError, TypeError) as exc:
            raise DataFormatError(path, None, f"raw block at log_time {m.log_time} ns: {exc}") from None
        for k, arr in fields.items():
            cols.setdefault(k, []).append(arr)
    for cid, payloads in proto.items():
        try:
            fields = decode_loop_blocks(payloads, c.channels[cid].metadata["rig_columns"])
        except (ValueError, KeyError, TypeError) as exc:
            raise DataFormatError(path, None, f"raw channel ({RAW_TOPIC}, protobuf): {exc}") from None
        for k, arr in fields.items():
            cols.setdefault(k, []).append(arr)
    # one column order whatever the layout (v2 grouped its columns by dtype): the loop's, then the rest
    rank = {k: i for i, k in enumerate(BLOCK_KEYS)}
    order = sorted(cols, key=lambda k: (rank.get(k, len(rank)), list(cols).index(k)))
    return {k: np.concatenate(cols[k]) for k in order}


def read_trial(path: str | os.PathLike, channel: str = "25hz", *, strict: bool = False) -> TrialData:
    """Read a trial log into :class:`TrialData` (events and metadata included).

    ``channel="25hz"`` (default): the decimated per-sample channel, the paper's
    logged data (25 Hz, section 4.2). ``channel="raw"``: every loop sample, in
    physical units whatever the raw layout (v2 counts, v1 floats, JSON); keys
    beyond the measured-data columns (``pid_*``, ``dither``, ``true_*``) go to
    ``extra``. Damaged chunks: see the module docstring; their description is
    also in ``TrialData.warnings``.
    """
    path = Path(path)
    ch = _channel_name(channel)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", LogDamageWarning)
        c = read_log(path, topics={RAW_TOPIC if ch == "raw" else LOG25_TOPIC, EVENTS_TOPIC}, strict=strict)
    notes = [str(w.message) for w in caught if issubclass(w.category, LogDamageWarning)]
    for note in notes:
        warnings.warn(note, LogDamageWarning, stacklevel=2)
    import numpy as np

    from rig.data import STANDARD_COLUMNS, TrialData

    records = c.metadata_dict()
    if ch == "raw":
        arrays = _raw_arrays(c, path)
    else:
        rows = [json.loads(m.data) for m in c.messages if c.topic_of(m) == LOG25_TOPIC]
        names: list[str] = list(rows[0]) if rows else []
        arrays = {nm: np.array([np.nan if r.get(nm) is None else r[nm] for r in rows], dtype=float)
                  for nm in names}
        arrays.pop("mu", None)  # derived: TrialData.mu recomputes it
    if "t_s" not in arrays or arrays["t_s"].size == 0:
        raise DataFormatError(path, None, f"no samples on the {ch} channel")
    order = np.argsort(arrays["t_s"], kind="stable")
    if np.any(np.diff(order) < 0):
        arrays = {k: v[order] for k, v in arrays.items()}
    get = {k: arrays.get(k) for k in STANDARD_COLUMNS[1:]}
    for req in ("position_um", "friction_N"):
        if get[req] is None:
            raise DataFormatError(path, None, f"the {ch} channel has no {req}")
    extra = {k: v for k, v in arrays.items() if k not in STANDARD_COLUMNS and k != "t_s"}
    return TrialData(time_s=arrays["t_s"], position_um=get["position_um"], friction_N=get["friction_N"],
                     normal_1_N=get["normal_1_N"], normal_2_N=get["normal_2_N"],
                     position_ref_um=get["position_ref_um"], valve_cmd=get["valve_cmd"], extra=extra,
                     metadata=_flat_metadata(records, ch), events=_events(c), source=str(path),
                     warnings=notes)


def trial_info(path: str | os.PathLike) -> dict:
    """What ``rig info`` shows: channels and counts, duration, metadata, events, recovered, damage."""
    path = Path(path)
    c = scan(path, topics={EVENTS_TOPIC})
    counts: dict[str, int] = {}
    t_min, t_max = None, None
    for cid, n in c.counts.items():
        chn = c.channels.get(cid)
        topic = chn.topic if chn else f"#{cid}"
        counts[topic] = counts.get(topic, 0) + n
        if topic in (RAW_TOPIC, LOG25_TOPIC):
            lo, hi = c.t_range[cid]
            t_min = lo if t_min is None else min(t_min, lo)
            t_max = hi if t_max is None else max(t_max, hi)
    records = c.metadata_dict()
    channels = []
    for cid, chn in sorted(c.channels.items()):
        schema = c.schemas.get(chn.schema_id)
        channels.append({"topic": chn.topic, "schema": schema.name if schema else "",
                         "encoding": chn.message_encoding, "messages": counts.get(chn.topic, 0)})
    dur = None
    if t_max is not None:
        dur = (t_max - t_min) / 1e9
        end = records.get("trial_end", {}).get("duration_s")  # the last raw block reaches beyond its log_time
        if end is not None:
            try:
                dur = max(dur, float(end))
            except ValueError:
                pass
    problems = []
    if c.error or not c.complete:
        problems.append(c.error or "no footer (cut off)")
    if c.damage:
        problems.append(f"{len(c.damage)} corrupt chunk(s): {c.damage_text()}")
    trial = records.get("trial", {})
    return {"path": str(path), "size_bytes": path.stat().st_size,
            # who and what (issue 21): the trial's identity, test piece, operator, note
            "trial_uid": trial.get("trial_uid"), "specimen": trial.get("specimen"),
            "operator": trial.get("operator"), "note": trial.get("note"),
            "complete": c.complete and not c.error and not c.damage,
            "damage": "; ".join(problems) or None, "corrupt_chunks": c.damage,
            "recovered": "recovery" in records, "channels": channels, "duration_s": dur,
            "start_time_ns": c.start_time_ns, "metadata": records, "events": _events(c),
            "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data)}
                            for a in c.attachments]}
