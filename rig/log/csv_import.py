"""Measured data (a CSV's :class:`TrialData`) into a trial log, and out to Parquet."""

from __future__ import annotations

import datetime as _dt
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
    extra), float64, with the metadata as the file's key-value metadata (``rig.`` prefix)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    cols = trial.columns()
    table = pa.table({k: pa.array(np.asarray(v, dtype=float)) for k, v in cols.items()})
    meta = {f"rig.{k}": str(v) for k, v in trial.metadata.items()}
    meta["rig.format"] = "rig-trial-csv columns (../shared/specs/measured-data.md), units in the names"
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
    with atomic_path(path, overwrite=overwrite) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path
