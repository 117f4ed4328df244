"""Honest intervals for the parameters a record does not determine: a profile likelihood over the
parameter's domain, not a Jacobian at a bound.

When a load-point coupling's fit runs to a bound of its domain (``core._couple``: A on a spring's
floor, B on +-0.2, k on the record's stiffness floor), the final model's Jacobian describes one
corner of a flat valley: on Leeman's record trimmed past its only step, A sits on its floor 1e-4
with a Jacobian error of 1.7e-4, which says "A is 1e-4 +- 2e-4" where the record says "A is
anything up to 0.0019"; where the final model's refit on all the data ran to a bound (velstep1
trimmed), it has no Jacobian at all. Here each parameter is held at points stepping away from
the fit (geometric offsets, to the edge of its domain), every other parameter refitted (the
nuisances too: the offset, the start's state; continued from the neighbouring point), and the
interval is the hull of the values where the rise of the sum of squares stays under one residual
variance (with the autocorrelation's inflation, as :func:`rig.diagnosis.fit.profile` and the
reported errors use): Wilks' +-1 sd set, a second valley within it included, open to the
domain's edge where the profile stays flat. Its half-width is the parameter's ``params_sd``.
Where no profile is computed (a grid too large for it) or none ends, the interval is the
parameter's whole searched domain (:func:`whole_domain`), and the summary says so.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .fit import FitResult, _cov_internal, fit, param, profile_crossing
from .parallel import fork_map
from .prep import Grid

HELD_NFEV = 20  # evaluations per held point and start, warm-started from the neighbour (40: the same intervals on
# Leeman trimmed to 4 digits, at 1.6x the cost)
STOP_RISE = 4.0  # a side ends once it rises this many residual variances above the lowest point (2 sd)
# the points of a profile: the fit's value moved by these offsets on each side (linear parameters:
# times the parameter's scale of one unit; ln-fitted ones: factors), clipped to the domain
OFFSETS_LINEAR = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # x 1e-3 for A and B (their fit scale)
FACTORS_LOG = (1.5, 2.25, 3.4, 5.1, 7.6, 11.4, 17.1)
CAPPED = ("A_mu", "B_mu", "B2_mu")  # the rate coefficients, searched within +-cap (core.COEF_MAX_MU)


def _points(name: str, v: float, grid: Grid, cap: float) -> tuple[list[float], list[float]]:
    """The held values below and above ``v``, nearest first, inside the fit's domain for ``name``
    (a spring's floor of A, the record's stiffness floor), the rate coefficients within +-``cap``."""
    prm = param(name, grid, spring=True)
    lo, hi = prm.lo * (1.0 + 1e-9), prm.hi * (1.0 - 1e-9)
    if prm.log:
        below = [v / f for f in FACTORS_LOG]
        above = [v * f for f in FACTORS_LOG]
    else:
        if name in CAPPED:
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
    """The outermost point of the profile within ``thr`` walking ``idx`` out from the minimum (a second
    valley within it, past a rise between, belongs to the interval: Wilks' set is every value within
    ``thr``, and its hull is reported), to :func:`rig.diagnosis.fit.profile_crossing` beyond it; the
    last point where the profile never rises that far again (open to the domain's edge)."""
    last = max(i for i, j in enumerate(idx) if rise[j] <= thr)
    e = profile_crossing(vs, rise, thr, idx[last:])
    return float(vs[idx[-1]]) if e is None else e


def _reference(grid: Grid, res: FitResult) -> FitResult | None:
    """``res`` where it has its fit's Jacobian; else (a split fit kept where the refit on all the data
    ran to a bound: velstep1) its model refitted on all sliding bins from its values, the profile's
    reference (its residual variance and inflation); None where no fit ends."""
    if "jac" in res.extra:
        return res
    try:
        r = fit(grid, res.baseline, res.extensions, dict(res.params), max_nfev=2 * HELD_NFEV, mask=grid.sliding)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return None
    return r if "jac" in r.extra and math.isfinite(r.sse_fit) else None


def domain_interval(grid: Grid, res: FitResult, name: str, cap: float,
                    others: list[dict] = ()) -> tuple[float, float] | None:
    """The +-1 sd profile-likelihood interval of ``name`` for ``res``'s model on all sliding data (the
    module's docstring), always holding ``res``'s own value (a profile lower elsewhere says the fit
    sat in one corner of the valley); None where no fit gives a Jacobian to scale the residual
    variance. Each held point is refitted from its neighbour (continuation), from ``res`` itself and
    from each of ``others`` (the same model's other valleys: the coupling's fit on the fit blocks),
    the lowest kept: a profile point is an upper bound of the true profile, so more starts only widen
    it; each of ``others``' own values of ``name`` is a held point too."""
    ref = _reference(grid, res) if name in res.params else None
    ci = None if ref is None else _cov_internal(grid, ref)
    if ci is None:
        return None
    pset, _, _, tau, s2 = ci
    thr = s2 * float(tau[pset.names.index(name)] if name in pset.names else np.max(tau))
    r0, mask = ref.extra["jac"][3], ref.extra["jac"][4]
    v0, vr = float(res.params[name]), float(ref.params[name])
    pts = {vr: float(np.dot(r0, r0))}
    fixed = [dict(ref.params)] + ([dict(res.params)] if ref is not res else [])
    if "v_init_um_s" in ref.params and grid.sliding.any():
        # the start's state is a nuisance with valleys of its own (Leeman trimmed: 1e-5 um/s, or 0.1-0.3)
        fixed.append(dict(ref.params, v_init_um_s=0.1 * float(max(grid.v[grid.sliding][0], 0.01))))
    prm = param(name, grid, spring=True)
    held = [(v0, fixed)] + [(float(o[name]), [dict(o), *fixed]) for o in others if name in o]
    for v, starts in held:
        if v != vr and prm.lo <= v <= prm.hi:
            sse, _ = _held_sse(grid, ref, name, v, starts, mask)
            if math.isfinite(sse):
                pts[v] = min(sse, pts.get(v, math.inf))
    for side in _points(name, vr, grid, cap):
        start = dict(ref.params)
        for v in side:
            sse, p = _held_sse(grid, ref, name, v, [start, *fixed], mask)
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


def whole_domain(grid: Grid, name: str, cap: float) -> tuple[float, float]:
    """The domain the fits search for ``name`` (the rate coefficients within +-``cap``): what a record that does
    not determine it, and whose profile is not computed, says about it."""
    prm = param(name, grid, spring=True)
    return (max(prm.lo, -cap), min(prm.hi, cap)) if name in CAPPED else (prm.lo, prm.hi)


def _one(job) -> tuple[float, float] | None:
    """:func:`domain_interval` of one parameter; None (its whole domain) where a held fit cannot be
    set up or fails (a parameter fitted through others, as a periodic term's amplitude and phase)."""
    try:
        return domain_interval(*job)
    except (ValueError, KeyError, IndexError, ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError):
        return None


def undetermined_intervals(grid: Grid, res: FitResult, names: list[str], cap: float, others: list[dict] = (),
                           max_bins: int | None = None, parallel: bool = False) -> tuple[dict, list[str]]:
    """(:func:`domain_interval` of each of ``names`` that ``res`` fits (not one the file states), the
    names given their :func:`whole_domain` instead): the profiles side by side on the cores
    (``parallel``: each is seconds on a long record), the whole domain where the grid has more than
    ``max_bins`` bins (the profile's cost grows with it) or no profile ends."""
    want = [nm for nm in names if nm in res.params and nm not in grid.known]
    if max_bins is not None and grid.t.size > max_bins:
        ivs = [None] * len(want)
    else:
        ivs = fork_map(_one, [(grid, res, nm, cap, list(others)) for nm in want], parallel)
    out, whole = {}, []
    for nm, iv in zip(want, ivs):
        if iv is None:
            iv = whole_domain(grid, nm, cap)
            whole.append(nm)
        out[nm] = iv
    return out, whole


__all__ = ["domain_interval", "undetermined_intervals", "whole_domain"]
