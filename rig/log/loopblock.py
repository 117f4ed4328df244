"""The 1 kHz ``/raw`` channel in protobuf (``rig.LoopBlock``), schema in the file, plottable in Foxglove.

One message per block of loop samples (1 s by default), message encoding
``protobuf``, schema encoding ``protobuf`` with a ``FileDescriptorSet`` built
from the block's keys, so any MCAP tool decodes it without ``rig`` (Foxglove,
``mcap cat --json``, ``mcap_protobuf.decoder``). Every column is a packed
repeated field, one value per sample, in the unit its name ends with:

================================  ==========  ============================================
field                             type        value (one stored unit = the quantization step)
================================  ==========  ============================================
``t0_s`` (1)                      double      trial time of the block's first sample, s
``rate_hz`` (2)                   double      sample rate of the block, Hz
``nonfinite_field`` (3)           uint32      field numbers of samples that were NaN/inf ...
``nonfinite_index`` (4)           uint32      ... and their sample indexes (stored as 0)
``t_s`` (5)                       double      trial time of every sample, s
``position_ref_um``               double      controller reference, µm (1 nm grid)
``position_nm``                   sint64      LVDT, nm (a multiple of the 76 nm count)
``friction_cN``                   sint64      friction load cell, cN (10 mN count)
``normal_1_cN``, ``_2_cN``        sint64      rider load cells, cN (10 mN count)
``valve_cmd_per_32767``           sint64      valve command as the int16 on CAN (32767 = full)
``pid_p_mN``, ``pid_i_mN``        sint64      PID proportional and integral terms, mN
``pid_d_N``                       float       PID derivative term, N (float32)
``dither_uN``                     sint64      dither, µN
``spool_per_32767``               sint64      spool position (simulation), valve command steps
``true_position_10nm``            sint64      simulation truth, 10 nm
``true_velocity_10nm_per_s``      sint64      simulation truth, 10 nm/s (0.01 µm/s)
``true_mu_per_100000``            sint64      simulation truth, 1e-5 of mu
any other key (import)            double      the value as given, its own unit
================================  ==========  ============================================

Every integer field but ``position_nm`` stores the count of its quantization step (the
unit is the step): values stored as multiples of a finer unit (the integral term in µN
on a 0.1 mN grid, until this layout) cost zstd about 5 MB more per hour; ``position_nm``
(76 x the LVDT count, read in nm) costs 0.6 MB/h. The steps and why they are enough:
:data:`rig.log.schemas.DEVICE_COLUMNS`.

Columns are numbered from 16 in the block's key order. The stored integers are
the device counts of :data:`rig.log.schemas.DEVICE_COLUMNS` times a whole
factor (``position_nm`` = 76 x LVDT counts), so ``rig`` reads back exactly the
values the ``rig.columns.v2`` layout stored (``rig export`` gives the same
CSV). The channel's metadata ``rig_columns`` maps each key to its field
(``[key, number, name, kind, unit_scale, quantum, offset]``: value =
``rint((stored * unit_scale - offset) / quantum) * quantum + offset``).

In Foxglove's Plot panel (x-axis "Message path", time range "All"): x
``/raw.t_s[:]``, y e.g. ``/raw.friction_cN[:]`` (docs/trial.md lists them all).

Size: packed zigzag varints and doubles in zstd chunks (benchmarks/bench_run.py).
Encoding is one numba pass over the block's integer columns (compiled once and
cached); decoding is vectorized numpy over the whole channel (no numba).
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass

import numpy as np

from rig.log.schemas import EXACT, Column

PROTO_ENCODING = "protobuf"
LOOP_BLOCK_SCHEMA = "rig.LoopBlock"
F_T0, F_RATE, F_NAN_FIELD, F_NAN_INDEX, F_T = 1, 2, 3, 4, 5
FIRST_COLUMN_FIELD = 16

#: per device key: protobuf field name (unit in the name), kind, value of one stored unit
DISPLAY: dict[str, tuple[str, str, float]] = {
    "position_ref_um": ("position_ref_um", "double", 1.0),
    "position_um": ("position_nm", "sint64", 1e-3),
    "friction_N": ("friction_cN", "sint64", 1e-2),
    "normal_1_N": ("normal_1_cN", "sint64", 1e-2),
    "normal_2_N": ("normal_2_cN", "sint64", 1e-2),
    "valve_cmd": ("valve_cmd_per_32767", "sint64", 1.0 / 32767),
    "pid_p": ("pid_p_mN", "sint64", 1e-3),
    "pid_i": ("pid_i_mN", "sint64", 1e-3),
    "pid_d": ("pid_d_N", "float", 1.0),
    "dither": ("dither_uN", "sint64", 1e-6),
    "spool": ("spool_per_32767", "sint64", 1.0 / 32767),
    "true_position_um": ("true_position_10nm", "sint64", 1e-2),
    "true_velocity_um_s": ("true_velocity_10nm_per_s", "sint64", 1e-2),
    "true_mu": ("true_mu_per_100000", "sint64", 1e-5),
}


@dataclass(frozen=True)
class ProtoField:
    """One column of ``rig.LoopBlock``: ``key`` (rig's name, physical unit) stored as field ``name``."""

    key: str
    number: int
    name: str
    kind: str            # "sint64" | "double" | "float"
    unit_scale: float    # physical value of one stored unit (sint64)
    quantum: float       # the device count (rig.columns.v2 scale) the value lies on; 0: none
    offset: float
    lo: int = 0          # the device count's range (as rig.columns.v2 clips it)
    hi: int = 0

    def as_meta(self) -> list:
        return [self.key, self.number, self.name, self.kind, self.unit_scale, self.quantum, self.offset]


def _field_name(key: str, used: set) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", key)
    if not name or not (name[0].isalpha() or name[0] == "_"):
        name = "c_" + name
    base, k = name, 2
    while name in used or name in ("t0_s", "rate_hz", "t_s", "nonfinite_field", "nonfinite_index"):
        name = f"{base}_{k}"
        k += 1
    return name


def plan_fields(keys, column) -> list[ProtoField]:
    """The fields of a block with ``keys`` (``t_s`` first or anywhere; it is field 5), ``column(key)``
    giving its :class:`rig.log.schemas.Column` (device counts) or ``EXACT``."""
    out: list[ProtoField] = []
    used: set = set()
    num = FIRST_COLUMN_FIELD
    for key in keys:
        if key == "t_s":
            continue
        col: Column = column(key)
        kind_int = np.dtype(col.dtype).kind == "i"
        disp = DISPLAY.get(key)
        if disp is not None and col is not EXACT and (kind_int or disp[1] != "sint64"):
            name, kind, unit = disp
            if kind == "sint64" and col.scale < unit * (1 - 1e-9):  # a finer count than the display unit
                kind, unit = "double", 1.0
        else:
            name, kind, unit = _field_name(key, used), ("double" if col.dtype == "<f8" else "float"), 1.0
        if kind == "sint64":
            info = np.iinfo(np.dtype(col.dtype))
            f = ProtoField(key, num, name, kind, unit, float(col.scale), float(col.offset), info.min + 1, info.max)
        elif kind == "double" and kind_int:  # on the device grid, as a double
            info = np.iinfo(np.dtype(col.dtype))
            f = ProtoField(key, num, name, kind, 1.0, float(col.scale), float(col.offset), info.min + 1, info.max)
        else:
            f = ProtoField(key, num, name, kind, 1.0, 0.0, 0.0)
        used.add(name)
        out.append(f)
        num += 1
    return out


# google/protobuf/descriptor.proto's numbers: FieldDescriptorProto's types and labels
_PB_TYPES = {"double": 1, "float": 2, "uint32": 13, "sint64": 18}
_PB_OPTIONAL, _PB_REPEATED = 1, 3


def _pb_len(num: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field (wire type 2)."""
    return _varint((num << 3) | 2) + _varint(len(payload)) + payload


def file_descriptor_set(fields: list[ProtoField]) -> bytes:
    """The serialized ``google.protobuf.FileDescriptorSet`` of ``rig.LoopBlock`` with these columns: written
    here field by field (the bytes ``descriptor_pb2`` serializes: ``tests/unit/log/test_log_protobuf.py``),
    so that a trial does not import the protobuf package (20-40 ms of its start-up) to write its schema.

    FileDescriptorSet{file(1): FileDescriptorProto{name(1), package(2), message_type(4): DescriptorProto{
    name(1), field(2): FieldDescriptorProto{name(1), number(3), label(4), type(5), json_name(10)}}, syntax(12)}}."""
    def field(name: str, num: int, kind: str, label: int) -> bytes:
        b = name.encode()
        return _pb_len(2, _pb_len(1, b) + b"\x18" + _varint(num) + b"\x20" + _varint(label) + b"\x28"
                       + _varint(_PB_TYPES[kind]) + _pb_len(10, b))

    cols = (("nonfinite_field", F_NAN_FIELD, "uint32"), ("nonfinite_index", F_NAN_INDEX, "uint32"),
            ("t_s", F_T, "double")) + tuple((p.name, p.number, p.kind) for p in fields)
    msg = (_pb_len(1, b"LoopBlock") + field("t0_s", F_T0, "double", _PB_OPTIONAL)
           + field("rate_hz", F_RATE, "double", _PB_OPTIONAL)
           + b"".join(field(name, num, kind, _PB_REPEATED) for name, num, kind in cols))
    return _pb_len(1, _pb_len(1, b"rig/loop_block.proto") + _pb_len(2, b"rig") + _pb_len(4, msg)
                   + _pb_len(12, b"proto3"))


def channel_metadata(fields: list[ProtoField], rate_hz: float) -> dict[str, str]:
    """The ``/raw`` channel's metadata: the field map rig reads back, and units for a person."""
    units = {p.name: p.key for p in fields}
    return {"rig_columns": json.dumps([p.as_meta() for p in fields]), "rate_hz": repr(float(rate_hz)),
            "layout": "rig.LoopBlock: packed repeated fields, one value per sample; x = t_s[:]; units in the "
                      "field names; rig_columns: [key, number, name, kind, unit_scale, quantum, offset]",
            "fields": json.dumps(units)}


# -- encoding -----------------------------------------------------------------------------------------------
def _varint(v: int) -> bytes:
    out = bytearray()
    while v >= 0x80:
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def _quant_pack_py(m, off, inv_q, lo, hi, ratio_i, ratio_f, unit_off, ratio_int, out, ends):  # pragma: no cover
    """Each row of ``m`` (float64, rows x n) on its grid and packed as zigzag varints into ``out``
    (``ends[r]`` = end of row r), in one pass without the GIL: the count ``rint((x - off) * inv_q)``
    clipped to ``lo..hi``, stored times ``ratio_i`` (``ratio_int``) or as ``rint(count * ratio_f +
    unit_off)``: the float operations, in their order, of the numpy encoder this replaced (its bytes:
    ``tests/unit/log/test_log_protobuf.py``). Returns the bytes written, or -1 at the first non-finite
    value (the caller then finds where: :meth:`LoopBlockEncoder._pack_nonfinite`)."""
    pos = 0
    for r in range(m.shape[0]):
        for i in range(m.shape[1]):
            y = (m[r, i] - off[r]) * inv_q[r]
            if not np.isfinite(y):
                return -1
            y = min(max(np.rint(y), lo[r]), hi[r])
            qi = np.int64(y)
            v = qi * ratio_i[r] if ratio_int else np.int64(np.rint(np.float64(qi) * ratio_f[r] + unit_off[r]))
            z = np.uint64((v << 1) ^ (v >> 63))
            while z >= np.uint64(0x80):
                out[pos] = np.uint8((z & np.uint64(0x7F)) | np.uint64(0x80))
                z = z >> np.uint64(7)
                pos += 1
            out[pos] = np.uint8(z)
            pos += 1
        ends[r] = pos
    return pos


_PACK: dict = {}


def _jit(name: str, fn):
    """numba-compiled ``fn`` (compiled on first use and cached, without the GIL: the writer's thread
    encodes beside the loop; reading needs no numba)."""
    jf = _PACK.get(name)
    if jf is None:
        from rig.jitstart import kernel

        jf = _PACK[name] = kernel(fn, nogil=True)
    return jf


def warm_up() -> None:
    """Compile (or load from the cache) the encoder's kernel now."""
    one, z1 = np.ones(1), np.zeros(1)
    _jit("quant", _quant_pack_py)(np.zeros((1, 1)), z1, one, z1, one, np.ones(1, np.int64), one, z1, True,
                                  np.zeros(10, np.uint8), np.zeros(1, np.int64))


class LoopBlockEncoder:
    """Encodes loop blocks as ``rig.LoopBlock`` messages (the field plan is fixed by the first block's keys)."""

    def __init__(self, column, rate_hz: float):
        self.column = column
        self.rate_hz = float(rate_hz)
        self.keys: tuple | None = None
        self.fields: list[ProtoField] = []

    def plan(self, keys: tuple) -> list[ProtoField]:
        self.keys = tuple(keys)
        self.fields = plan_fields(keys, self.column)
        ints = [p for p in self.fields if p.kind == "sint64"]
        self._ints = ints
        self._int_tags = [_varint((p.number << 3) | 2) for p in ints]
        self._others = [p for p in self.fields if p.kind != "sint64"]
        self._other_tags = [_varint((p.number << 3) | 2) for p in self._others]
        if ints:  # the grids of the integer fields, one value per row (the kernel's arguments)
            self._off = np.array([p.offset for p in ints], dtype=float)
            self._inv_q = np.array([1.0 / p.quantum for p in ints])
            self._lo = np.array([p.lo for p in ints], dtype=float)
            self._hi = np.array([p.hi for p in ints], dtype=float)
            self._ratio_f = np.array([p.quantum / p.unit_scale for p in ints])
            self._unit_off = np.array([p.offset / p.unit_scale for p in ints])
            self._ratio_int = bool(np.allclose(self._ratio_f, np.rint(self._ratio_f), rtol=0, atol=1e-9)
                                   and not self._unit_off.any())
            self._ratio_i = np.rint(self._ratio_f).astype(np.int64) if self._ratio_int \
                else np.zeros(len(ints), np.int64)
        return self.fields

    def schema(self) -> bytes:
        return file_descriptor_set(self.fields)

    def metadata(self) -> dict[str, str]:
        return channel_metadata(self.fields, self.rate_hz)

    def encode(self, block: dict[str, np.ndarray], t0: float) -> bytes:
        t = np.asarray(block["t_s"], dtype="<f8")
        n = int(t.size)
        if not math.isfinite(t0):
            raise ValueError(f"block time t0_s = {t0} is not finite")
        parts = [b"\x09", struct.pack("<d", t0), b"\x11", struct.pack("<d", self.rate_hz)]
        nan_f: list[np.ndarray] = []
        nan_i: list[np.ndarray] = []
        tail = [_varint((F_T << 3) | 2), _varint(8 * n), t.tobytes()]
        for p, tag in zip(self._others, self._other_tags):
            x = np.asarray(block[p.key], dtype=np.float64)
            if p.quantum:  # a device column kept as a double on its grid (exactly what v2 decoded)
                with np.errstate(invalid="ignore"):
                    q = np.clip(np.rint((x - p.offset) / p.quantum), p.lo, p.hi)
                x = q * p.quantum + p.offset
            b = x.astype("<f8" if p.kind == "double" else "<f4").tobytes()
            tail += [tag, _varint(len(b)), b]
        if self._ints:
            m = np.stack([block[p.key] for p in self._ints]).astype(np.float64, copy=False)
            out = np.empty(m.size * 10, np.uint8)
            ends = np.empty(m.shape[0], np.int64)
            if self._quant(m, out, ends) < 0:
                self._pack_nonfinite(m, out, ends, nan_f, nan_i)
            start = 0
            for r, tag in enumerate(self._int_tags):
                e = int(ends[r])
                tail += [tag, _varint(e - start), out[start:e].tobytes()]
                start = e
        if nan_f:
            for num, arr in ((F_NAN_FIELD, np.concatenate(nan_f)), (F_NAN_INDEX, np.concatenate(nan_i))):
                b = b"".join(_varint(int(v)) for v in arr)
                parts += [_varint((num << 3) | 2), _varint(len(b)), b]
        return b"".join(parts + tail)

    def _quant(self, m: np.ndarray, out: np.ndarray, ends: np.ndarray) -> int:
        """:func:`_quant_pack_py` of the integer rows ``m`` with this plan's grids."""
        return _jit("quant", _quant_pack_py)(m, self._off, self._inv_q, self._lo, self._hi, self._ratio_i,
                                             self._ratio_f, self._unit_off, self._ratio_int, out, ends)

    def _pack_nonfinite(self, m: np.ndarray, out: np.ndarray, ends: np.ndarray, nan_f: list, nan_i: list) -> None:
        """The integer rows of a block with a non-finite count: its positions go to ``nan_f``/``nan_i``
        (field numbers, sample indexes) and those samples are stored as count 0."""
        with np.errstate(invalid="ignore", over="ignore"):
            finite = np.isfinite(np.rint((m - self._off[:, None]) * self._inv_q[:, None]))
        bad_r, bad_i = np.nonzero(~finite)
        nan_f.append(np.array([self._ints[r].number for r in bad_r], dtype=np.int64))
        nan_i.append(bad_i.astype(np.int64))
        self._quant(np.where(finite, m, self._off[:, None]), out, ends)  # x = offset: count 0


# -- decoding -----------------------------------------------------------------------------------------------
def _read_varint(buf, pos: int) -> tuple[int, int]:
    v = 0
    shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("message ends inside a varint")
        b = buf[pos]
        pos += 1
        v |= (b & 0x7F) << shift
        if b < 0x80:
            return v, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint longer than 10 bytes")


def unpack_varints(b: bytes | np.ndarray, zigzag: bool) -> np.ndarray:
    """Packed varints -> int64 (zigzag-decoded with ``zigzag``), vectorized."""
    a = np.frombuffer(b, np.uint8) if not isinstance(b, np.ndarray) else b
    if a.size == 0:
        return np.zeros(0, np.int64)
    ends = a < 0x80
    if not ends[-1]:
        raise ValueError("packed varints end inside a value")
    idx = np.flatnonzero(ends)
    starts = np.empty(idx.size, np.int64)
    starts[0] = 0
    starts[1:] = idx[:-1] + 1
    if (idx - starts).max(initial=0) > 9:
        raise ValueError("varint longer than 10 bytes")
    gid = np.repeat(np.arange(idx.size), idx - starts + 1)
    shift = ((np.arange(a.size) - starts[gid]) * 7).astype(np.uint64)
    vals = (a & 0x7F).astype(np.uint64) << shift
    z = np.add.reduceat(vals, starts)
    if not zigzag:
        return z.astype(np.int64)
    return ((z >> np.uint64(1)).astype(np.int64)) ^ -((z & np.uint64(1)).astype(np.int64))


def split_message(data: bytes) -> dict[int, list]:
    """Top-level fields of one message: ``{number: [payload (bytes) or fixed64 value bytes, ...]}``."""
    out: dict[int, list] = {}
    mv = memoryview(data)
    pos, end = 0, len(data)
    while pos < end:
        key, pos = _read_varint(mv, pos)
        num, wt = key >> 3, key & 7
        if wt == 2:
            ln, pos = _read_varint(mv, pos)
            if pos + ln > end:
                raise ValueError(f"field {num} runs past the end of the message")
            out.setdefault(num, []).append(mv[pos:pos + ln])
            pos += ln
        elif wt == 1:
            out.setdefault(num, []).append(mv[pos:pos + 8])
            pos += 8
        elif wt == 5:
            out.setdefault(num, []).append(mv[pos:pos + 4])
            pos += 4
        elif wt == 0:
            v, pos = _read_varint(mv, pos)
            out.setdefault(num, []).append(v)
        else:
            raise ValueError(f"unsupported wire type {wt} in field {num}")
    if pos != end:
        raise ValueError("message ends inside a field")
    return out


def decode_loop_blocks(payloads: list[bytes], rig_columns: str) -> dict[str, np.ndarray]:
    """``rig.LoopBlock`` messages of one channel (its metadata ``rig_columns``) -> {key: float64 array}
    in physical units, the blocks concatenated in the given order; NaN where a sample was not finite."""
    fields = [ProtoField(k, int(num), name, kind, float(us), float(q), float(off))
              for k, num, name, kind, us, q, off in json.loads(rig_columns)]
    parts: dict[int, list] = {F_T: [], F_NAN_FIELD: [], F_NAN_INDEX: [], **{p.number: [] for p in fields}}
    counts = []
    nan_base = []
    n_total = 0
    for data in payloads:
        msg = split_message(data)
        t = b"".join(msg.get(F_T, []))
        if len(t) % 8:
            raise ValueError("t_s is not a whole number of doubles")
        n = len(t) // 8
        parts[F_T].append(t)
        for p in fields:
            parts[p.number].append(b"".join(msg.get(p.number, [])))
        if F_NAN_FIELD in msg:
            parts[F_NAN_FIELD].append(b"".join(msg[F_NAN_FIELD]))
            parts[F_NAN_INDEX].append(b"".join(msg.get(F_NAN_INDEX, [])))
            nan_base.append(n_total)
        counts.append(n)
        n_total += n
    out = {"t_s": np.frombuffer(b"".join(parts[F_T]), "<f8").astype(np.float64)}
    for p in fields:
        b = b"".join(parts[p.number])
        if p.kind == "sint64":
            st = unpack_varints(b, zigzag=True).astype(np.float64)
            x = st * p.unit_scale
            if p.quantum:
                x = np.rint((x - p.offset) / p.quantum) * p.quantum + p.offset
        elif p.kind == "double":
            x = np.frombuffer(b, "<f8").astype(np.float64)
        else:
            x = np.frombuffer(b, "<f4").astype(np.float64)
        if x.size != n_total:
            raise ValueError(f"field {p.name} has {x.size} samples, t_s {n_total}")
        out[p.key] = x
    if nan_base:
        by_num = {p.number: p.key for p in fields}
        for base, bf, bi in zip(nan_base, parts[F_NAN_FIELD], parts[F_NAN_INDEX]):
            nums = unpack_varints(bf, zigzag=False)
            idx = unpack_varints(bi, zigzag=False)
            if nums.size != idx.size:
                raise ValueError("nonfinite_field and nonfinite_index differ in length")
            for num, i in zip(nums.tolist(), idx.tolist()):
                if num in by_num and base + i < n_total:
                    out[by_num[num]][base + i] = np.nan
    return out
