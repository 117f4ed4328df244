"""The per-file tasks the batch engine runs: top-level functions of plain values.

Each takes a path (and options by value), reads the file itself on the worker
and returns a JSON-able dict; none touches the database (the caller writes the
results, in one process, so DuckDB's single writer is never contended).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

TRIAL_SUFFIXES = (".mcap", ".csv", ".parquet")

# the log's trial_end status -> the catalogue's status
_STATUS = {"completed": "completed", "interrupted": "aborted", "aborted": "aborted", "failed": "tripped",
           "tripped": "tripped", "recovered": "recovered", "imported": "completed"}


def sha256_file(path: str | os.PathLike, bufsize: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(bufsize):
            h.update(chunk)
    return h.hexdigest()


def file_cost(item) -> float:
    """A per-file task's cost estimate for longest-first ordering (rig.catalog.batch): the
    file's size in bytes (reading and fitting scale with the samples); 0 when it cannot be
    stat'ed (the task itself will report why). ``item`` is a path or a (path, options) pair."""
    path = item[0] if isinstance(item, (tuple, list)) else item
    try:
        return float(os.path.getsize(path))
    except OSError:
        return 0.0


def _float(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _int(v) -> int | None:
    try:
        return int(float(v))
    except (TypeError, ValueError):
        return None


def catalog_status(meta: dict[str, str], events: list[dict]) -> str:
    """completed | aborted | tripped | recovered (docs/catalog.md, column ``status``).

    A file rewritten by ``rig recover`` is ``recovered``; otherwise the log's
    ``trial_end`` status: ``interrupted`` (operator abort) is ``aborted``,
    ``failed`` (an interlock trip or a lost device ends a trial that way) is
    ``tripped``. A CSV has no trial_end: its own ``status`` key, else ``completed``.
    """
    if str(meta.get("recovered", "")).lower() == "true":
        return "recovered"
    raw = str(meta.get("status", "") or "").strip().lower()
    if raw in _STATUS:
        return _STATUS[raw]
    if any(e.get("kind") in ("interrupted",) for e in events):
        return "aborted"
    if any(e.get("kind") in ("trial_failed", "interlock", "trip") for e in events):
        return "tripped"
    return "completed" if not raw else raw


def index_file(path: str) -> dict[str, Any]:
    """Read one trial file: hash, metadata and summary figures (one ``trials`` row)."""
    from rig.log import load_trial

    p = Path(path)
    st = p.stat()
    digest = sha256_file(p)
    row: dict[str, Any] = {"path": str(p), "size_bytes": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": digest,
                           "kind": p.suffix.lower().lstrip(".")}
    tr = load_trial(p)
    meta = {str(k): str(v) for k, v in tr.metadata.items()}
    t = np.asarray(tr.time_s, dtype=float)
    dur = _float(meta.get("duration_s"))
    if dur is None:
        dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
    try:
        nf = tr.normal_force_N
    except ValueError:
        nf = _float(meta.get("normal_force_N"))
    started = meta.get("started_utc") or meta.get("start_time") or meta.get("started") or meta.get("date")
    row.update({
        "recipe": meta.get("recipe") or meta.get("recipe_name"),
        "lubricant": meta.get("lubricant"),
        "rig_profile": meta.get("profile_name") or meta.get("profile") or meta.get("rig_profile") or meta.get("rig"),
        "backend": meta.get("backend") or ("imported" if meta.get("imported_from") or p.suffix.lower() in (".csv", ".parquet")
                                           else None),
        "started_utc": started,
        "duration_s": _float(dur),
        "status": catalog_status(meta, tr.events),
        "log_status": meta.get("status"),
        "normal_force_N": _float(nf),
        "seed": _int(meta.get("seed")),
        "n_samples": int(t.size),
        "n_events": len(tr.events),
        "written_by": meta.get("software_version"),
        "metadata": json.dumps(meta, sort_keys=True),
        # who and what (issue 21): the trial's identity, test piece, operator, sliding distance
        "trial_uid": meta.get("trial_uid"), "specimen": meta.get("specimen"), "operator": meta.get("operator"),
        "note": meta.get("note"), "slip_mm": slip_mm(tr),
    })
    return row


def slip_mm(tr) -> float | None:
    """Sliding distance of a trial (mm): the path length of the commanded position when logged (free
    of the LVDT's noise), else of the measured position; what wears a test piece."""
    x = tr.position_ref_um if tr.position_ref_um is not None else tr.position_um
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.abs(np.diff(x)).sum() / 1000.0) if x.size > 1 else None


def identify_file(item: tuple[str, dict]) -> dict[str, Any]:
    """``rig identify`` on one file: the rig.identify/1 report (``options`` are identify_trials'
    keyword arguments); raises when the file cannot be read or has no velocity step."""
    from rig.analysis.identify import identify_trials
    from rig.log import load_trial

    path, options = item
    tr = load_trial(path)
    rep = identify_trials([tr], names=[str(path)], **(options or {})).report()
    if not rep["steps"]:
        raise ValueError(f"{path}: no velocity steps found (ratio >= {options.get('min_ratio', 1.25)})")
    return {"path": str(path), "sha256": sha256_file(path), "report": _jsonable(rep)}


def diagnose_file(item: tuple[str, dict]) -> dict[str, Any]:
    """``rig diagnose`` on one file: the rig.diagnosis/1 report (``options``: ``baseline``)."""
    from rig.log import load_trial
    from rig.diagnosis import diagnose

    path, options = item
    tr = load_trial(path)
    d = diagnose(tr, baseline=(options or {}).get("baseline", "rate_state"))
    rep = d.report()
    rep["data"] = str(path)
    return {"path": str(path), "sha256": sha256_file(path), "report": _jsonable(rep),
            "noise_N": _float(getattr(d.grid, "noise_N", None))}


def _jsonable(x):
    """Plain JSON types only, non-finite numbers as None (the catalogue stores JSON)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return [_jsonable(v) for v in x.tolist()]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        f = float(x)
        return f if math.isfinite(f) else None
    if x is None or isinstance(x, str):
        return x
    return str(x)
