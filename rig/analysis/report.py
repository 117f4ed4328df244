"""The edge of every analysis: numbers rounded once, for the JSON reports and for display.

The analyses compute with full floats and pass them to each other unrounded; a report is
rounded where it is written (:func:`rounded`, 6 significant figures in the JSON of
``rig identify``, ``stribeck``, ``reproduce``, ``stability``) or shown (:func:`fmt`, the
tables and texts of the commands)."""

from __future__ import annotations

import math


def rounded(x, nd: int = 6) -> float | None:
    """``x`` to ``nd`` significant figures, as a JSON number; None for a missing or non-finite value."""
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    return float(f"{x:.{nd}g}")


def fmt(v, nd: int = 4) -> str:
    """A number for a table or a sentence: ``nd`` significant figures; '-' when missing or non-finite."""
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.{nd}g}"
    return str(v)


def rounded_warnings(warnings: list[dict]) -> list[dict]:
    """Warnings (:mod:`rig.model.checks`: judged on unrounded values) for a report: each ``value`` rounded."""
    return [{**w, "value": rounded(w["value"])} if "value" in w else dict(w) for w in warnings]
