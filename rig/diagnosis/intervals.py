"""Honest intervals for the parameters a record does not determine: a profile likelihood over the
parameter's domain, not a Jacobian at a bound.

When a load-point coupling's fit runs to a bound of its domain (``core._couple``: A on a spring's
floor, B on +-0.2, k on the record's stiffness floor), the final model's Jacobian describes one
corner of a flat valley: on Leeman's record trimmed past its only step, A sits on its floor 1e-4
with a Jacobian error of 1.7e-4, which says "A is 1e-4 +- 2e-4" where the record says "A is
anything up to about the original's". Here each such parameter is held at points stepping away
from the fit (geometric offsets, to the edge of its domain), every other parameter refitted
(continued from the neighbouring point), and the interval is where the rise of the sum of
squares stays under one residual variance (with the autocorrelation's inflation, as
:func:`rig.diagnosis.fit.profile` and the reported errors use): Wilks' +-1 sd, open to the
domain's edge where the profile stays flat. Its half-width is the parameter's ``params_sd``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .fit import FitResult, _cov_internal, fit, param, profile_crossing
from .prep import Grid

HELD_NFEV = 40  # evaluations per held point and start (the valley is flat: a few more than a local profile's)
STOP_RISE = 4.0  # a side ends once it rises this many residual variances above the lowest point (2 sd)
# the points of a profile: the fit's value moved by these offsets on each side (linear parameters:
# times the parameter's scale of one unit; ln-fitted ones: factors), clipped to the domain
OFFSETS_LINEAR = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # x 1e-3 for A and B (their fit scale)
FACTORS_LOG = (1.5, 2.25, 3.4, 5.1, 7.6, 11.4, 17.1)


def _points(name: str, v: float, grid: Grid, cap: float) -> tuple[list[float], list[float]]:
    """The held values below and above ``v``, nearest first, inside the fit's domain for ``name``
    (a spring's floor of A, the record's stiffness floor), linear ones within +-``cap``."""
    prm = param(name, grid, spring=True)
    lo, hi = prm.lo * (1.0 + 1e-9), prm.hi * (1.0 - 1e-9)
    if prm.log:
        below = [v / f for f in FACTORS_LOG]
        above = [v * f for f in FACTORS_LOG]
    else:
        lo, hi = max(lo, -cap), min(hi, cap)
        below = [v - d * prm.scale for d in OFFSETS_LINEAR]
        above = [v + d * prm.scale for d in OFFSETS_LINEAR]
    below = [x for x in below if x > lo] + ([lo] if v > lo * (1.0 + 1e-6) + 1e-12 else [])
    above = [x for x in above if x < hi] + ([hi] if v < hi else [])
    return below, above


def _held_sse(grid: Grid, res: FitResult, name: str, v: float, starts: list[dict], mask) -> tuple[float, dict]:
    """The least sum of squares (on ``mask``, weighted) with ``name`` held at ``v``, every other
    parameter refitted from each of ``starts``; (inf, {}) where no fit ends."""
    best = (math.inf, {})
    g = replace(grid, known={**grid.known, name: float(v)})
    for st in starts:
        rv = fit(g, res.baseline, res.extensions, dict(st, **{name: float(v)}), max_nfev=HELD_NFEV, mask=mask)
        if "jac" in rv.extra and math.isfinite(rv.sse_fit):
            r = rv.extra["jac"][3]
            best = min(best, (float(np.dot(r, r)), rv.params), key=lambda b: b[0])
    return best


def _edge(vs: np.ndarray, rise: np.ndarray, thr: float, idx: list[int]) -> float:
    """:func:`rig.diagnosis.fit.profile_crossing` in the parameter itself; the last point where the
    profile never rises that far (open to the domain's edge)."""
    e = profile_crossing(vs, rise, thr, idx)
    return float(vs[idx[-1]]) if e is None else e


def domain_interval(grid: Grid, res: FitResult, name: str, cap: float) -> tuple[float, float] | None:
    """The +-1 sd profile-likelihood interval of ``name`` for ``res``'s model on its fit's data (the
    module's docstring), always holding ``res``'s own value (a profile lower elsewhere says the fit
    sat in one corner of the valley); None where ``res`` has no Jacobian to scale the residual
    variance. Each held point is refitted from its neighbour (continuation) and from ``res`` itself,
    the lower kept: a profile point is an upper bound of the true profile, so more starts only widen it."""
    if name not in res.params or "jac" not in res.extra:
        return None
    ci = _cov_internal(grid, res)
    if ci is None:
        return None
    pset, _, _, tau, s2 = ci
    thr = s2 * float(tau[pset.names.index(name)] if name in pset.names else np.max(tau))
    r0, mask = res.extra["jac"][3], res.extra["jac"][4]
    v0 = float(res.params[name])
    pts = {v0: float(np.dot(r0, r0))}
    fixed = [dict(res.params)]
    if "v_init_um_s" in res.params and grid.sliding.any():
        # the start's state is a nuisance with valleys of its own (Leeman trimmed: 1e-5 um/s, or 0.1-0.3)
        fixed.append(dict(res.params, v_init_um_s=0.1 * float(max(grid.v[grid.sliding][0], 0.01))))
    for side in _points(name, v0, grid, cap):
        start = dict(res.params)
        for v in side:
            sse, p = _held_sse(grid, res, name, v, [start, *fixed], mask)
            if not math.isfinite(sse):
                break
            pts[float(v)] = sse
            start = p
            if sse - min(pts.values()) > STOP_RISE * thr:
                break  # well past one sd from the lowest point yet
    vs = np.array(sorted(pts))
    ss = np.array([pts[v] for v in vs])
    i0 = int(np.argmin(ss))
    rise = ss - ss[i0]
    lo, hi = _edge(vs, rise, thr, list(range(i0, -1, -1))), _edge(vs, rise, thr, list(range(i0, vs.size)))
    return min(lo, v0), max(hi, v0)


def undetermined_intervals(grid: Grid, res: FitResult, names: list[str], cap: float) -> dict[str, tuple[float, float]]:
    """:func:`domain_interval` of each of ``names`` that ``res`` fits (not one the file states)."""
    out = {}
    for nm in names:
        if nm in res.params and nm not in grid.known:
            iv = domain_interval(grid, res, nm, cap)
            if iv is not None:
                out[nm] = iv
    return out


__all__ = ["domain_interval", "undetermined_intervals"]
