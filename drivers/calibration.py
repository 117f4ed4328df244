"""Calibration checks of the force channels (issue 21), as ASTM E4 / ISO 7500-1 practice has them.

Pure functions over readings and the channels' :class:`drivers.config.CalibrationRecord`:

* :func:`shunt_check`: each bridge's shunt-calibration reading against the reference recorded at
  calibration; a relative deviation beyond ``shunt_tolerance_fraction`` (default 0.1 %) means the
  cell, its cable or its amplifier drifted since (a failed check).
* :func:`verify_points`: the error of indication at reference loads the operator applied, relative
  (ISO 7500-1: ``q = (F_indicated - F_reference) / F_reference``), pass when ``|q|`` is within the
  class's allowed error (class 1: 1 %) and the point lies in the verified range.
"""

from __future__ import annotations

import math

from drivers.config import CalibrationRecord


def shunt_check(readings_N: dict[str, float], records: dict[str, CalibrationRecord | None]) -> list[dict]:
    """One row per channel read: reading, reference, relative deviation, tolerance, ``ok`` (False: drifted;
    None: no reference to compare with)."""
    rows = []
    for ch, value in readings_N.items():
        cal = records.get(ch)
        ref = cal.shunt_reference_N if cal is not None else None
        row = {"channel": ch, "serial": cal.serial if cal is not None else None, "reading_N": value,
               "reference_N": ref, "deviation_fraction": None,
               "tolerance_fraction": cal.shunt_tolerance_fraction if cal is not None else None, "ok": None}
        if ref:
            dev = (value - ref) / ref
            row["deviation_fraction"] = dev if math.isfinite(dev) else None
            # NaN (a dead bridge) is a failed check, never a pass
            row["ok"] = bool(math.isfinite(dev) and abs(dev) <= cal.shunt_tolerance_fraction)
        rows.append(row)
    return rows


def verify_points(points: list[tuple[float, float]], cal: CalibrationRecord | None) -> dict:
    """``points``: (reference N, indicated N) pairs. Returns the per-point relative error, whether each
    lies in the verified range, and pass/fail for the record's class (None without a class)."""
    allowed = cal.class_error_fraction if cal is not None else None
    lo, hi = cal.verified_range_N if cal is not None and cal.verified_range_N else (-math.inf, math.inf)
    rows = []
    for ref, ind in points:
        err = ind - ref
        q = err / ref if ref else None
        in_range = lo <= ref <= hi
        ok = None
        if allowed is not None and q is not None:
            ok = bool(math.isfinite(q) and abs(q) <= allowed)
        rows.append({"reference_N": ref, "indicated_N": ind, "error_N": err, "relative_error": q,
                     "in_verified_range": in_range, "ok": ok})
    judged = [r["ok"] for r in rows if r["ok"] is not None]
    return {"points": rows, "class": cal.class_ if cal is not None else None, "allowed_relative_error": allowed,
            "passed": (all(judged) if judged else None)}
