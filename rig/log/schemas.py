"""The trial log's layout: topics, JSON schemas, and the raw-block codecs (rig.columns.v1 / v2).

``/raw`` carries the 1 kHz loop data as blocks of samples (one message per
block, 1 s by default). Since version 2 (``rig.columns.v2``) each column is
stored as the device delivers it: integer counts with a scale and an offset
(LVDT counts of 0.076 µm, load-cell counts of 10 mN, the valve command as the
int16 sent on CAN); the derived terms (PID terms, dither, simulation truths)
in fixed point far below what the valve resolves (PID P and I terms 1 mN, dither
1 µN; the int16 valve step is 0.31 N of a 10 kN actuator; truths 10 nm, 0.01 µm/s,
1e-5 of mu) or float32, and each
column filtered (delta and/or byte shuffle) where that pays for zstd. A column
decodes as ``value = stored * scale + offset``; NaN is the dtype's minimum.

``RAW_V2_LAYOUT`` (also in the channel's schema and metadata) documents the bytes:

    b"RIG2", u32 LE header length H, H bytes of UTF-8 JSON header
    {"t0_s", "n", "rate_hz", "columns": [[key, dtype, filter, scale, offset, nbytes], ...]}
    padded with spaces to a multiple of 8, then each column's nbytes in order.
    dtype: "<i2" | "<i4" | "<i8" | "<f4" | "<f8"; filter: "none" | "delta" |
    "shuffle" | "delta+shuffle" (delta: first value absolute, then differences,
    modulo the integer width; shuffle: the bytes of the n values regrouped by
    byte position, byte 0 of every value first).

Version 1 (``rig.columns.v1``, written until this layout) stored every column
as float64/float32; it is still read, as are the JSON (``base64``/``json``)
raw blocks of older logs.
"""

from __future__ import annotations

import base64
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from rig.log.topics import EVENTS_TOPIC, LOG25_TOPIC, MCAP_PROFILE, RAW_TOPIC, STATS_TOPIC  # noqa: F401 - re-exported
#: the /log25 message fields (mu = friction / (normal_1 + normal_2), null where undefined)
SAMPLE_FIELDS = ("t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd",
                 "mu")
BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N", "valve_cmd",
              "pid_p", "pid_i", "pid_d", "dither", "true_position_um", "true_velocity_um_s", "true_mu", "spool")

RAW_V1_ENCODING = "rig.columns.v1"
RAW_V1_MAGIC = b"RIGC"
RAW_V2_ENCODING = "rig.columns.v2"
RAW_V2_MAGIC = b"RIG2"
RAW_V2_LAYOUT = (
    "b'RIG2', u32 LE header length H, H bytes of UTF-8 JSON header {t0_s, n, rate_hz, columns: [[key, dtype, "
    "filter, scale, offset, nbytes], ...]} padded with spaces to a multiple of 8, then each column's nbytes. "
    "value = stored * scale + offset; NaN = the integer dtype's minimum; filter 'delta' = first value then "
    "differences (modulo the width), 'shuffle' = bytes regrouped by byte position (byte 0 of all values first)")
B64_ENCODING = "base64-f8le"
B64_F4_ENCODING = "base64-f4le"


@dataclass(frozen=True)
class Column:
    """How one raw column is stored: ``value = stored * scale + offset`` (unit)."""

    dtype: str
    scale: float = 1.0
    offset: float = 0.0
    unit: str = ""
    filter: str = "none"
    description: str = ""

    def as_schema(self) -> dict:
        return {"dtype": self.dtype, "scale": self.scale, "offset": self.offset, "unit": self.unit,
                "filter": self.filter, "description": self.description}


LVDT_UM_PER_COUNT = 0.076      # paper: LVDT quantization step 0.076 µm
#: 10 mN: 25x finer than the friction load cell's ±0.25 N and 60x finer than the rider cells' ±0.6 N
#: (paper, section 3; measured-data.md); its rounding error (10/sqrt(12) = 2.9 mN rms) adds 0.05 % to
#: the variance of the 125 mN noise. A 1 mN count stored about 3.3 bits of noise per force sample
#: (7.8 MB per hour of the three forces, benchmarks/bench_run.py --phases).
LOAD_CELL_N_PER_COUNT = 0.01
VALVE_FULL_SCALE = 32767       # the int16 valve command on CAN (drivers/valve.py)

#: the loop's columns as the devices deliver them (the measured filters, benchmarks/bench_run.py)
DEVICE_COLUMNS: dict[str, Column] = {
    "t_s": Column("<i8", 1e-9, 0.0, "s", "delta+zstd", "trial time; offset = the block's first sample"),
    "position_ref_um": Column("<i4", 0.001, 0.0, "µm", "delta+zstd", "controller reference, 1 nm steps"),
    "position_um": Column("<i4", LVDT_UM_PER_COUNT, 0.0, "µm", "shuffle+zstd", "LVDT counts"),
    "friction_N": Column("<i4", LOAD_CELL_N_PER_COUNT, 0.0, "N", "shuffle+zstd", "friction load-cell counts"),
    "normal_1_N": Column("<i4", LOAD_CELL_N_PER_COUNT, 0.0, "N", "shuffle+zstd", "rider 1 load-cell counts"),
    "normal_2_N": Column("<i4", LOAD_CELL_N_PER_COUNT, 0.0, "N", "shuffle+zstd", "rider 2 load-cell counts"),
    "valve_cmd": Column("<i2", 1.0 / VALVE_FULL_SCALE, 0.0, "1", "shuffle+zstd", "valve command, int16 as on CAN"),
    "pid_p": Column("<i4", 0.001, 0.0, "N", "shuffle+zstd", "PID proportional term, 1 mN steps"),
    "pid_i": Column("<i4", 0.001, 0.0, "N", "delta+shuffle+zstd", "PID integral term, 1 mN steps"),
    "pid_d": Column("<f4", unit="N", filter="zstd", description="PID derivative term, float32"),
    "dither": Column("<i4", 1e-6, 0.0, "N", "shuffle+zstd", "dither added to the PID output, 1 µN steps"),
    "true_position_um": Column("<i4", 0.01, 0.0, "µm", "delta+shuffle+zstd",
                               "simulation truth, 10 nm steps (7.6x finer than the LVDT's count)"),
    "true_velocity_um_s": Column("<i4", 0.01, 0.0, "µm/s", "shuffle+zstd", "simulation truth, 0.01 µm/s steps"),
    "true_mu": Column("<i4", 1e-5, 0.0, "1", "shuffle+zstd", "simulation truth, 1e-5 steps"),
    "spool": Column("<i4", 1.0 / VALVE_FULL_SCALE, 0.0, "1", "shuffle+zstd",
                    "servovalve spool position (simulation), in the valve command's int16 steps"),
}
#: any other column, and every column of an imported CSV: exact float64
EXACT = Column("<f8", filter="shuffle+zstd", description="exact float64")


def device_columns(lvdt_um_per_count: float | None = None) -> dict[str, Column]:
    """The device columns, with the profile's LVDT step when it has one."""
    cols = dict(DEVICE_COLUMNS)
    if lvdt_um_per_count and lvdt_um_per_count > 0:
        c = cols["position_um"]
        cols["position_um"] = Column(c.dtype, float(lvdt_um_per_count), c.offset, c.unit, c.filter, c.description)
    return cols


def _shuffle(b: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return b
    return np.frombuffer(b, np.uint8).reshape(-1, itemsize).T.tobytes()


def _unshuffle(b: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return b
    return np.frombuffer(b, np.uint8).reshape(itemsize, -1).T.tobytes()


_ZSTD: dict = {}
COLUMN_ZSTD_LEVEL = 3


def _zstd_c():
    c = _ZSTD.get("c")
    if c is None:
        import zstandard
        c = _ZSTD["c"] = zstandard.ZstdCompressor(level=COLUMN_ZSTD_LEVEL)
    return c


def _zstd_d(b: bytes, size: int) -> bytes:
    d = _ZSTD.get("d")
    if d is None:
        import zstandard
        d = _ZSTD["d"] = zstandard.ZstdDecompressor()
    return d.decompress(b, max_output_size=size)


def _decode_column(b: bytes, dtype: str, flt: str, scale: float, offset: float, n: int) -> np.ndarray:
    dt = np.dtype(dtype)
    if "zstd" in flt:
        b = _zstd_d(b, n * dt.itemsize)
    if len(b) != n * dt.itemsize:
        raise ValueError(f"{len(b)} bytes for {n} values of {dtype}")
    if "shuffle" in flt:
        b = _unshuffle(b, dt.itemsize)
    s = np.frombuffer(b, dt)
    if dt.kind == "f":
        out = s.astype(np.float64)
        return out * scale + offset if (scale != 1.0 or offset) else out
    if "delta" in flt:
        s = np.cumsum(s, dtype=dt)
    nan = s == np.iinfo(dt).min
    out = s.astype(np.float64) * scale + offset
    if nan.any():
        out[nan] = np.nan
    return out


_PREFIX: dict = {}


def _col_prefix(key: str, col: Column) -> str:
    """``[key, dtype, filter, scale,`` of a column's header entry, as JSON (cached)."""
    p = _PREFIX.get((key, col))
    if p is None:
        p = _PREFIX[(key, col)] = json.dumps([key, col.dtype, col.filter, col.scale])[:-1] + ","
    return p


class ColumnsV2Encoder:
    """Encodes loop blocks in ``rig.columns.v2`` (the header layout is cached per key set)."""

    def __init__(self, columns: dict[str, Column], rate_hz: float):
        self.columns = columns
        self.rate_hz = float(rate_hz)

    def column(self, key: str) -> Column:
        return self.columns.get(key, EXACT)

    def _plan(self, keys: tuple) -> list:
        """Columns grouped by dtype, so that a block is scaled, rounded and filtered in a few numpy calls."""
        plan = self._plans.get(keys)
        if plan is None:
            groups: dict[str, list] = {}
            for key in keys:
                groups.setdefault(self.column(key).dtype, []).append(key)
            plan = []
            for dtype, ks in groups.items():
                cols = [self.column(k) for k in ks]
                plan.append((np.dtype(dtype), ks, cols,
                             np.array([c.offset for c in cols])[:, None],
                             np.array([1.0 / c.scale for c in cols])[:, None],
                             [i for i, c in enumerate(cols) if "delta" in c.filter],
                             ks.index("t_s") if "t_s" in ks else -1))
            self._plans[keys] = plan
        return plan

    _plans: dict

    def encode(self, block: dict[str, np.ndarray], t0: float) -> bytes:
        n = int(block["t_s"].size)
        if not hasattr(self, "_plans"):
            self._plans = {}
        parts = []
        meta = []
        for dt, ks, cols, offsets, inv_scale, delta_rows, t_row in self._plan(tuple(block)):
            m = np.stack([block[k] for k in ks]).astype(np.float64, copy=False)
            if dt.kind == "i":
                if t_row >= 0:
                    offsets = offsets.copy()
                    offsets[t_row, 0] = t0
                m -= offsets  # m is a fresh array (np.stack)
                m *= inv_scale
                np.rint(m, out=m)
                info = np.iinfo(dt)
                all_finite = bool(np.isfinite(m).all())
                if all_finite:
                    np.clip(m, info.min + 1, info.max, out=m)
                    st = m.astype(dt)
                else:
                    finite = np.isfinite(m)
                    st = np.clip(np.where(finite, m, 0.0), info.min + 1, info.max).astype(dt)
                    st[~finite] = info.min  # NaN sentinel
                if delta_rows and n > 1:
                    st[delta_rows, 1:] = np.diff(st[delta_rows], axis=1)  # wraps modulo 2^bits
            else:
                st = m.astype(dt)
            size = dt.itemsize
            shuffled = st.view(np.uint8).reshape(len(ks), n, size).transpose(0, 2, 1).tobytes() if size > 1 \
                else st.tobytes()
            plain = st.tobytes()
            row = n * size
            for i, (k, c) in enumerate(zip(ks, cols)):
                b = (shuffled if "shuffle" in c.filter else plain)[i * row:(i + 1) * row]
                if "zstd" in c.filter:
                    b = _zstd_c().compress(b)
                parts.append(b)
                off = t0 if i == t_row and dt.kind == "i" else c.offset
                meta.append(f"{_col_prefix(k, c)}{off!r},{len(b)}]")
        if not math.isfinite(t0):
            raise ValueError(f"block time t0_s = {t0} is not finite")
        text = ('{"t0_s":%r,"n":%d,"rate_hz":%r,"columns":[%s]}' % (t0, n, self.rate_hz, ",".join(meta))).encode()
        text += b" " * (-(8 + len(text)) % 8)
        return b"".join([RAW_V2_MAGIC, struct.pack("<I", len(text)), text, *parts])

    def schema(self, keys) -> dict:
        """The channel's schema: the layout and, per column, dtype, scale, offset, unit, filter."""
        return {"title": RAW_V2_ENCODING, "layout": RAW_V2_LAYOUT, "rate_hz": self.rate_hz,
                "columns": {k: self.column(k).as_schema() for k in keys}}


def _block_header(data: bytes, magic: bytes, encoding: str) -> tuple[dict, int, int]:
    """The JSON header of a v1/v2 block (magic, u32 LE length, JSON): (header, n samples, offset after it)."""
    if len(data) < 8 or data[:4] != magic:
        raise ValueError(f"not a {encoding} block (bad magic)")
    (hlen,) = struct.unpack_from("<I", data, 4)
    head = json.loads(data[8:8 + hlen])
    return head, int(head["n"]), 8 + hlen


def decode_v2(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """A ``rig.columns.v2`` block -> (header, {key: float64 array in physical units})."""
    head, n, off = _block_header(data, RAW_V2_MAGIC, RAW_V2_ENCODING)
    out: dict[str, np.ndarray] = {}
    for key, dtype, flt, scale, offset, nbytes in head["columns"]:
        end = off + int(nbytes)
        if end > len(data):
            raise ValueError(f"block truncated in column {key}")
        out[key] = _decode_column(data[off:end], dtype, flt, float(scale), float(offset), n)
        off = end
    if off != len(data):
        raise ValueError(f"{len(data) - off} bytes after the last column")
    return head, out


def decode_v1(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """A ``rig.columns.v1`` block (float64/float32 columns) -> (header, {key: float64 array})."""
    head, n, off = _block_header(data, RAW_V1_MAGIC, RAW_V1_ENCODING)
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


def decode_json_block(data: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """An old JSON raw block (schema rig.RawBlock: base64-f8le / base64-f4le / json lists)."""
    blk = json.loads(data)
    enc = blk["encoding"]
    n = int(blk["n"])
    out = {}
    for k, v in blk["fields"].items():
        if enc == B64_ENCODING or (enc == B64_F4_ENCODING and k == "t_s"):
            arr = np.frombuffer(base64.b64decode(v), dtype="<f8").astype(float)
        elif enc == B64_F4_ENCODING:
            arr = np.frombuffer(base64.b64decode(v), dtype="<f4").astype(float)
        else:
            arr = np.array([np.nan if x is None else x for x in v], dtype=float)
        if arr.size != n:
            raise ValueError(f"field {k} has {arr.size} samples, expected {n}")
        out[k] = arr
    return blk, out


def decode_raw(encoding: str, data: bytes) -> dict[str, np.ndarray]:
    """Any raw block of the obsolete layouts (v2, v1 or the old JSON ones) by its channel's message encoding
    (protobuf blocks need their channel's field map: :func:`decode_loop_blocks`)."""
    if encoding == RAW_V2_ENCODING:
        return decode_v2(data)[1]
    if encoding == RAW_V1_ENCODING:
        return decode_v1(data)[1]
    return decode_json_block(data)[1]


_NUM_OR_NULL = {"type": ["number", "null"]}
_UNITS = {"t_s": "s", "position_um": "µm", "friction_N": "N", "normal_1_N": "N", "normal_2_N": "N",
          "position_ref_um": "µm", "valve_cmd": "1 (-1..1)", "mu": "1: friction / (normal_1 + normal_2)"}
#: JSON schemas of the JSON channels (Foxglove decodes and plots them)
SCHEMAS: dict[str, dict] = {
    "rig.Sample": {
        "title": "rig.Sample",
        "description": "One decimated sample (25 Hz like the paper's log). Units: s, µm, N, valve 1, mu 1.",
        "type": "object",
        "properties": {name: dict(({"type": "number"} if name == "t_s" else _NUM_OR_NULL),
                                  description=_UNITS[name]) for name in SAMPLE_FIELDS},
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
JSON_TOPICS = ((LOG25_TOPIC, "rig.Sample"), (EVENTS_TOPIC, "rig.Event"), (STATS_TOPIC, "rig.LoopStats"))


def jsonable(value: Any) -> Any:
    """Make ``value`` strict-JSON safe: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return str(value)


def dumps(obj: Any) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def meta_str(v: Any) -> str:
    """A metadata value as text: numbers as plain numbers (numpy scalars too: never 'np.float64(...)')."""
    if isinstance(v, str):
        return v
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, np.integer):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return repr(v) if math.isfinite(v) else str(v)
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(jsonable(v), allow_nan=False)
    return str(v)
