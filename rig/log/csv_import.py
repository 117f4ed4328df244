"""Measured data (a CSV's :class:`TrialData`) into a trial log, and to and from Parquet."""

from __future__ import annotations

import datetime as _dt
import math
import os
import time
import uuid
from pathlib import Path

import numpy as np

from rig.data import DataFormatError, TrialData, atomic_path
from rig.log.writer import TrialLogWriter

#: log_time is u64 ns since the epoch: trial times must stay within about ±290 years of the anchor
_MAX_ABS_T_S = 9.0e9


def _anchor_ns(trial: TrialData) -> int:
    """Wall-clock ns of trial time 0: the CSV's ``started_utc`` / ``start_time_utc`` when it parses, else now."""
    for key in ("start_time_ns",):
        v = trial.metadata.get(key)
        if v is not None:
            try:
                return int(v)
            except ValueError:
                pass
    for key in ("started_utc", "start_time_utc", "date"):
        v = trial.metadata.get(key)
        if v:
            try:
                d = _dt.datetime.fromisoformat(str(v).replace("Z", "+00:00"))
                if d.tzinfo is None:
                    d = d.replace(tzinfo=_dt.timezone.utc)
                return int(d.timestamp() * 1e9)
            except ValueError:
                pass
    return time.time_ns()


def write_trial_data(trial: TrialData, path: str | os.PathLike, *, decimated_rate_hz: float | None = None,
                     extra_metadata: dict | None = None, overwrite: bool = True) -> Path:
    """Write a :class:`TrialData` (e.g. an imported CSV) as a trial log, atomically.

    Every sample goes to the raw channel (exact float64 columns, blocks of 100)
    and to the per-sample channel; the CSV metadata to the ``trial`` record;
    extra text columns to the attachment ``text_columns.json``.
    ``log_time`` is anchored at the CSV's ``started_utc`` metadata, else at the
    time of the import. Times too large for the log's clock are a DataFormatError.
    The trial keeps its ``trial_uid`` (a CSV exported from a log, a copy) or gets a new one.
    ``overwrite=False``: FileExistsError when ``path`` exists (left as it was).
    """
    path = Path(path)
    t = np.asarray(trial.time_s, dtype=float)
    if t.size and (not np.isfinite(t).all() or float(np.max(np.abs(t))) > _MAX_ABS_T_S):
        raise DataFormatError(trial.source or path, None,
                              f"time_s reaches {float(np.max(np.abs(t))):.6g} s: beyond the ±{_MAX_ABS_T_S:.0e} s "
                              "a trial log can place on its clock (are the times in seconds?)")
    anchor = _anchor_ns(trial)
    if t.size and t[0] < 0 and anchor + t[0] * 1e9 < 0:
        anchor = int(-t[0] * 1e9) + 1
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    rate = 1.0 / dt if dt > 0 else 1.0
    meta = dict(trial.metadata)
    meta.pop("start_time_ns", None)
    meta.update(extra_metadata or {})
    if not str(meta.get("trial_uid", "")).strip():
        meta["trial_uid"] = str(uuid.uuid4())
    with atomic_path(path, overwrite=overwrite) as tmp:
        w = TrialLogWriter(tmp, loop_rate_hz=rate, decimated_rate_hz=decimated_rate_hz or rate, metadata=meta,
                           flush_interval_s=1e9, fsync=False, raw_columns="exact", start_time_ns=anchor)
        try:
            block = {"t_s": t}
            text: dict[str, list] = {}
            for name, arr in trial.columns().items():
                if name == "time_s":
                    continue
                if np.asarray(arr).dtype.kind in "USO":
                    text[name] = [str(v) for v in arr]
                else:
                    block[name] = np.asarray(arr, dtype=float)
            if text:  # text columns are kept, beside the numeric raw channel
                import json
                w._sink.call(lambda mw: mw.add_attachment(
                    create_time=time.time_ns(), log_time=anchor, name="text_columns.json",
                    media_type="application/json",
                    data=json.dumps({"time_s": t.tolist(), **text}).encode()))
            w._dec_every = 1  # every imported sample goes to the per-sample channel
            for i in range(0, t.size, 100):
                w.write_block({k: v[i:i + 100] for k, v in block.items()})
            for e in trial.events:
                e = dict(e)
                w.event(e.pop("t_s", 0.0), e.pop("kind", "marker"), **e)
            w.close("imported")
        except BaseException:
            w.abort()
            raise
    return path


def write_parquet(trial: TrialData, path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """Write ``trial`` as Parquet (pyarrow), atomically: the measured-data columns (standard first, then
    extra), float64 (text columns as strings), with the metadata as the file's key-value metadata (``rig.`` prefix)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    cols = trial.columns()
    table = pa.table({k: pa.array(np.asarray(v).astype(str) if np.asarray(v).dtype.kind in "USO"
                                  else np.asarray(v, dtype=float)) for k, v in cols.items()})  # text stays text
    meta = {f"rig.{k}": str(v) for k, v in trial.metadata.items()}
    meta["rig.format"] = "rig-trial-csv columns (../shared/specs/measured-data.md), units in the names"
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
    with atomic_path(path, overwrite=overwrite) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path


_PARQUET_FORMAT_KEY = "rig.format"


def read_parquet(path: str | os.PathLike) -> TrialData:
    """Read a Parquet file of the measured-data columns (as :func:`write_parquet` writes it, or any with a
    ``time_s``, ``position_um`` and ``friction_N`` column) into :class:`TrialData`, with the same rules as
    the CSV (``rig.data.read_csv``): the required columns numeric and finite, ``time_s`` strictly increasing,
    a positive ``normal_force_N``; other columns kept as extras (text as strings). The metadata are the
    file's key-value metadata with the ``rig.`` prefix. Bad input raises :class:`DataFormatError`."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from rig.data import OPTIONAL_COLUMNS, REQUIRED_COLUMNS, parse_number

    path = Path(path)
    try:
        table = pq.read_table(path)
    except OSError as exc:
        raise DataFormatError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except (pa.ArrowException, ValueError) as exc:
        raise DataFormatError(path, None, f"not a readable Parquet file ({exc})") from None
    names = table.column_names
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DataFormatError(path, None, f"duplicate column name(s): {', '.join(dup)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise DataFormatError(path, None, f"missing required column(s): {', '.join(missing)} "
                                          f"(the file has: {', '.join(names)})")
    if table.num_rows == 0:
        raise DataFormatError(path, None, "empty data: no rows")
    cols: dict[str, np.ndarray] = {}
    extra: dict[str, np.ndarray] = {}
    for name in names:
        col = table.column(name)
        numeric = pa.types.is_integer(col.type) or pa.types.is_floating(col.type) or pa.types.is_boolean(col.type)
        if name in REQUIRED_COLUMNS + OPTIONAL_COLUMNS:
            if not numeric:
                raise DataFormatError(path, None, f"column '{name}': {col.type} values, expected numbers")
            cols[name] = np.asarray(col.to_numpy(zero_copy_only=False), dtype=float)  # nulls -> NaN
        elif numeric:
            extra[name] = np.asarray(col.to_numpy(zero_copy_only=False), dtype=float)
        else:
            extra[name] = np.asarray([("" if v is None else str(v)) for v in col.to_pylist()], dtype=str)
    for name in REQUIRED_COLUMNS:
        bad = np.flatnonzero(~np.isfinite(cols[name]))
        if bad.size:
            raise DataFormatError(path, None, f"column '{name}', row {bad[0] + 1}: NaN, infinite or missing value")
    t = cols["time_s"]
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if bad.size:
        j = int(bad[0]) + 1
        raise DataFormatError(path, None, f"time_s not strictly increasing at row {j + 1} "
                                          f"({float(t[j - 1])!r} then {float(t[j])!r})")
    kv = table.schema.metadata or {}
    metadata = {}
    for k, v in kv.items():
        key = k.decode("utf-8", "replace")
        if key.startswith("rig.") and key != _PARQUET_FORMAT_KEY:
            metadata[key[4:]] = v.decode("utf-8", "replace")
    if "normal_force_N" in metadata:
        v = parse_number(metadata["normal_force_N"])
        if v is None or not math.isfinite(v) or v <= 0:
            raise DataFormatError(path, None, f"normal_force_N metadata must be a positive number of newtons, "
                                              f"found {metadata['normal_force_N']!r}")
    return TrialData(time_s=t, position_um=cols["position_um"], friction_N=cols["friction_N"],
                     normal_1_N=cols.get("normal_1_N"), normal_2_N=cols.get("normal_2_N"),
                     position_ref_um=cols.get("position_ref_um"), valve_cmd=cols.get("valve_cmd"),
                     extra=extra, metadata=metadata, source=str(path))
