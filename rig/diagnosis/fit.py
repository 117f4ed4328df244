"""Least-squares fits of a model (baseline + extensions) against the measured friction force.

The fit minimises the raw-sample sum of squares of the friction residual on
the *fit* blocks of the record (even-numbered blocks of :mod:`.prep`); the
*hold-out* blocks (odd) are only predicted. Parameters that must be positive
(``L_um``, ``L2_um``, ``tau_s``, ``delay_s``, ``stiffness_kN_per_m``,
``wavelength_um``) are fitted in ``ln``; the periodic term is fitted as a
sine and cosine amplitude (linear) and reported as ``amplitude_mu`` and
``phase_rad``. All other parameters are fitted as they are, scaled to O(1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .models import model_params, predict_force
from .prep import Grid

LOG_PARAMS = {
    "L_um": (0.05, 1e5), "L2_um": (0.05, 1e6), "tau_s": (1e-4, 300.0), "delay_s": (1e-4, 300.0),
    "stiffness_kN_per_m": (0.5, 1e7), "wavelength_um": (1.0, 1e6),
    # nuisance: the velocity whose steady state the record starts in (records starting from rest)
    "v_init_um_s": (1e-5, 1e3),
}
LIN_PARAMS = {
    "mu0": (0.01, -10.0, 10.0), "A_mu": (1e-3, 0.0, 0.2), "B_mu": (1e-3, -0.2, 0.2), "c_mu": (1e-3, -0.2, 0.2),
    "B2_mu": (1e-3, -0.2, 0.2), "rate_mu_per_mm": (1e-4, -1.0, 1.0), "rate_N_per_s": (1e-4, -10.0, 10.0),
    "_pc": (1e-3, -0.5, 0.5), "_ps": (1e-3, -0.5, 0.5),
}


@dataclass
class FitResult:
    baseline: str
    extensions: list[str]
    params: dict[str, float]
    pred: np.ndarray                 # per bin (N)
    sse_fit: float                   # raw-sample SSE on fit blocks (N²)
    sse_hold: float                  # raw-sample SSE on hold-out blocks (N²)
    n_fit: int
    n_hold: int
    n_par: int
    nfev: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def holdout_rms_N(self) -> float:
        return math.sqrt(self.sse_hold / max(self.n_hold, 1))

    @property
    def fit_rms_N(self) -> float:
        return math.sqrt(self.sse_fit / max(self.n_fit, 1))

    @property
    def bic(self) -> float:
        """Gaussian BIC on the fit blocks' raw samples: n ln(SSE/n) + k ln n."""
        n = max(self.n_fit, 1)
        return n * math.log(max(self.sse_fit, 1e-300) / n) + self.n_par * math.log(n)


def _free_names(baseline: str, extensions: list[str], init: dict | None = None) -> list[str]:
    names = model_params(baseline, extensions)
    if init is not None and "v_init_um_s" in init:
        names = names + ["v_init_um_s"]
    out = []
    for nm in names:
        if nm == "amplitude_mu":
            out += ["_pc", "_ps"]
        elif nm == "phase_rad":
            continue
        else:
            out.append(nm)
    return out


def _to_internal(names, params):
    z = np.empty(len(names))
    lo = np.empty(len(names))
    hi = np.empty(len(names))
    for i, nm in enumerate(names):
        if nm in LOG_PARAMS:
            a, b = LOG_PARAMS[nm]
            val = min(max(params[nm], a * 1.0001), b / 1.0001)
            z[i] = math.log(val)
            lo[i], hi[i] = math.log(a), math.log(b)
        else:
            sc, a, b = LIN_PARAMS[nm]
            val = min(max(params[nm], a + 1e-12), b - 1e-12)
            z[i] = val / sc
            lo[i], hi[i] = a / sc, b / sc
    return z, lo, hi


def _to_params(names, z, fixed):
    p = dict(fixed)
    for i, nm in enumerate(names):
        if nm in LOG_PARAMS:
            p[nm] = math.exp(z[i])
        else:
            p[nm] = z[i] * LIN_PARAMS[nm][0]
    if "_pc" in p:
        pc, ps = p.pop("_pc"), p.pop("_ps")
        p["amplitude_mu"] = math.hypot(pc, ps)
        p["phase_rad"] = math.atan2(pc, ps)
    return p


def _from_params(params):
    p = dict(params)
    if "amplitude_mu" in p:
        a = p["amplitude_mu"]
        ph = p.get("phase_rad", 0.0)
        p["_pc"] = a * math.sin(ph)
        p["_ps"] = a * math.cos(ph)
    return p


def evaluate(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float],
             pred: np.ndarray | None = None, nfev: int = 0) -> FitResult:
    if pred is None:
        pred = predict_force(baseline, extensions, params, grid.t, grid.x, grid.v, grid.N_tot, grid.N_nom)
    r2 = grid.count * (grid.F_mean - pred) ** 2 + grid.ss_within
    fm = grid.fit_mask()
    hm = grid.holdout_mask()
    bad = not np.all(np.isfinite(pred))
    sse_f = float(r2[fm].sum()) if not bad else math.inf
    sse_h = float(r2[hm].sum()) if not bad else math.inf
    npar = len(model_params(baseline, extensions))
    return FitResult(baseline, list(extensions), dict(params), pred, sse_f, sse_h, int(grid.count[fm].sum()),
                     int(grid.count[hm].sum()), npar, nfev)


def fit(grid: Grid, baseline: str, extensions: list[str], init: dict[str, float],
        max_nfev: int = 400, mask: np.ndarray | None = None) -> FitResult:
    """Least-squares fit of all the model's parameters from ``init`` on the fit blocks (or ``mask``)."""
    names = _free_names(baseline, extensions, init)
    internal = _from_params(init)
    z0, lo, hi = _to_internal(names, internal)
    fixed = {k: v for k, v in internal.items() if k not in names and not k.startswith("_")
             and k not in ("amplitude_mu", "phase_rad")}
    if "position_periodic" not in extensions:
        fixed.pop("phase_rad", None)
    m = grid.fit_mask() if mask is None else mask
    w = np.sqrt(grid.count[m])
    Fm = grid.F_mean[m]
    ncall = [0]

    def resid(z):
        ncall[0] += 1
        p = _to_params(names, z, fixed)
        try:
            pr = predict_force(baseline, extensions, p, grid.t, grid.x, grid.v, grid.N_tot, grid.N_nom)
        except (ValueError, ZeroDivisionError, OverflowError):
            return np.full(Fm.size, 1e6)
        r = w * (Fm - pr[m])
        if not np.all(np.isfinite(r)):
            return np.full(Fm.size, 1e6)
        return r

    z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
    try:
        sol = least_squares(resid, z0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-6,
                            max_nfev=max_nfev, xtol=1e-8, ftol=1e-9)
        z = sol.x
    except (ValueError, np.linalg.LinAlgError):
        z = z0
    params = _to_params(names, z, fixed)
    return evaluate(grid, baseline, extensions, params, nfev=ncall[0])


def cost_at(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float]) -> float:
    """Fit-block SSE of a parameter set (for choosing among starting points)."""
    return evaluate(grid, baseline, extensions, params).sse_fit


def multistart(grid: Grid, baseline: str, extensions: list[str], starts: list[dict[str, float]],
               keep: int = 2, max_nfev: int = 400) -> FitResult:
    """Rank starting points by cost, fit the best ``keep`` of them, return the best fit."""
    costs = []
    for s in starts:
        try:
            c = cost_at(grid, baseline, extensions, s)
        except (ValueError, ZeroDivisionError):
            c = math.inf
        costs.append(c if math.isfinite(c) else math.inf)
    order = np.argsort(costs)[:keep]
    best = None
    for i in order:
        r = fit(grid, baseline, extensions, starts[i], max_nfev=max_nfev)
        r.extra["at_bound"] = at_bound(r.params)
        if best is None or (r.extra["at_bound"], r.sse_fit) < (best.extra["at_bound"], best.sse_fit):
            best = r
    return best


def at_bound(params: dict) -> bool:
    """True when a fitted parameter sits on its bound (the fit then stands in for something else)."""
    for nm, v in params.items():
        if nm in LOG_PARAMS:
            lo, hi = LOG_PARAMS[nm]
            if v <= lo * 1.01 or v >= hi / 1.01:
                return True
        elif nm in LIN_PARAMS and nm not in ("mu0",):
            sc, lo, hi = LIN_PARAMS[nm]
            if nm == "A_mu" and v <= 1e-9:
                continue
            if v <= lo + 1e-3 * sc or v >= hi - 1e-3 * sc:
                return True
    return False
