"""Honest results: warnings for fitted parameters that hit a fit bound or are not physical.

One place for the checks every output uses (``rig identify``, ``rig diagnose``, ``rig
reproduce``: their tables, JSON and plots). The bounds are those declared with the
parameters in :mod:`rig.model.spec`: the fit bounds (:data:`~rig.model.spec.PARAMS`) and the
physically plausible ranges (:data:`~rig.model.spec.PLAUSIBLE`). A warning is a dict (the
JSON form)::

    {"param": "L_um", "value": 1e5, "kind": "at_bound", "where": "whole-record fit",
     "message": "L_um = 1e+05 µm is at the fit's upper bound (1e+05 µm): not determined by the data"}

``kind`` is one of ``at_bound`` (the solver stopped at a bound of :data:`PARAMS`),
``not_physical`` (outside :data:`PLAUSIBLE`, or a negative k_cr), ``undetermined`` (the
standard error is larger than the value).
"""

from __future__ import annotations

import math

from rig.model.spec import PARAMS, PLAUSIBLE

#: a value within this fraction of the fit's span (in the fitted coordinate: ln for log
#: parameters) of a bound is "at the bound"
AT_BOUND_REL = 1e-4

#: the marker tables and plots put beside a flagged value
MARK = "(!)"


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def _unit(name: str) -> str:
    d = PARAMS.get(name)
    return "" if d is None or d.unit == "1" else f" {d.unit}"


def at_bound(name: str, value: float) -> str | None:
    """'lower' or 'upper' if ``value`` sits on a fit bound of :data:`PARAMS` (else None: inside the
    bounds, or beyond one, which :func:`check_param` judges by :data:`PLAUSIBLE`)."""
    d = PARAMS.get(name)
    if d is None or not math.isfinite(value):
        return None
    if d.log:
        if value <= 0:
            return None  # beyond the bound, not on it: no fit stopped there (PLAUSIBLE says what it is)
        lo, hi, v = math.log(d.lo), math.log(d.hi), math.log(value)
    else:
        lo, hi, v = d.lo, d.hi, value
    tol = AT_BOUND_REL * (hi - lo)
    if lo - tol <= v <= lo + tol:
        return "lower"
    if hi - tol <= v <= hi + tol:
        return "upper"
    return None  # inside, or beyond a bound (a value no fit made, e.g. eq. 10's A of one step)


def check_param(name: str, value, err=None, where: str = "") -> dict | None:
    """The one warning (the strongest) for one parameter, or None."""
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value):
        return None
    u = _unit(name)
    b = at_bound(name, value)
    msg = kind = None
    if b is not None:
        d = PARAMS[name]
        kind = "at_bound"
        msg = (f"{name} = {_fmt(value)}{u} is at the fit's {b} bound ({_fmt(d.lo if b == 'lower' else d.hi)}{u}): "
               "not determined by the data")
    elif name in PLAUSIBLE and not (PLAUSIBLE[name].lo <= value <= PLAUSIBLE[name].hi):
        p = PLAUSIBLE[name]
        kind = "not_physical"
        side = f"below {_fmt(p.lo)}" if value < p.lo else f"above {_fmt(p.hi)}"
        msg = f"{name} = {_fmt(value)}{u} is {side}{u}: {p.why}"
    elif err is not None and math.isfinite(float(err)) and value != 0 and float(err) >= abs(value):
        kind = "undetermined"
        msg = f"{name} = {_fmt(value)} ± {_fmt(float(err))}{u}: the error exceeds the value; not determined by the data"
    if msg is None:
        return None
    return {"param": name, "value": value, "kind": kind, "where": where, "message": msg}


def check_k_cr(k_cr_kN_per_m, where: str = "") -> dict | None:
    """Eq. (13)'s k_cr = (B - A) N / L is a stiffness only when B > A; a negative one is not."""
    if k_cr_kN_per_m is None or not math.isfinite(float(k_cr_kN_per_m)) or k_cr_kN_per_m >= 0:
        return None
    return {"param": "k_cr_kN_per_m", "value": float(k_cr_kN_per_m), "kind": "not_physical", "where": where,
            "message": f"k_cr (eq. 13) = {_fmt(float(k_cr_kN_per_m))} kN/m is no stiffness: A > B (velocity "
                       "strengthening), so steady sliding is stable at any stiffness (no critical stiffness)"}


def check_params(params: dict, err: dict | None = None, where: str = "") -> list[dict]:
    """Warnings for every parameter of a result (``k_cr_kN_per_m`` included when present)."""
    out = []
    err = err or {}
    for name, v in params.items():
        w = check_k_cr(v, where) if name == "k_cr_kN_per_m" else check_param(name, v, err.get(name), where)
        if w is not None:
            out.append(w)
    return out


def flagged(warnings: list[dict], where: str | None = None) -> set[str]:
    """The parameter names that carry a warning (optionally only those of ``where``)."""
    return {w["param"] for w in warnings if where is None or w.get("where") == where}


def line(w: dict) -> str:
    """One-line form for tables and plot footnotes."""
    return f"{w['where']}: {w['message']}" if w.get("where") else w["message"]
