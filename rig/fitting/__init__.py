"""One fitting core: parameters with units, bounds and log scaling; least squares with
Jacobian standard errors and several starts (scipy.optimize.least_squares, trust region).

    params = ParamSet([Param("mu0", "1", -10, 10, scale=0.01), Param("L_um", "µm", 0.05, 1e5, log=True)])
    fit = least_squares_fit(lambda p: model(p) - data, params, starts=[{"mu0": 0.1, "L_um": 20}])
    fit.params, fit.stderr, fit.cost

A ``log`` parameter is fitted as ln(value) (positive, scale-free); the others as
value / scale (so every internal variable is O(1)). Standard errors come from the Jacobian
at the solution, ``cov = (J^T J)^-1 s^2`` with ``s^2 = SSR / (n - p)``, mapped back to
the parameter's units (a log parameter's error is value * error of its ln).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares


@dataclass(frozen=True)
class Param:
    """A fitted parameter: name, unit, bounds [lo, hi] in its unit, ln scaling or a scale."""
    name: str
    unit: str
    lo: float
    hi: float
    log: bool = False
    scale: float = 1.0

    @classmethod
    def of(cls, name: str, decl) -> "Param":
        """From a declaration with ``unit, lo, hi, log, scale`` (rig.model.spec.PARAMS entries)."""
        return cls(name, decl.unit, decl.lo, decl.hi, decl.log, decl.scale)

    def to_internal(self, value: float) -> float:
        if self.log:
            return math.log(min(max(value, self.lo * 1.0001), self.hi / 1.0001))
        return min(max(value, self.lo + 1e-12), self.hi - 1e-12) / self.scale

    def to_value(self, z: float) -> float:
        return math.exp(z) if self.log else z * self.scale

    @property
    def internal_bounds(self) -> tuple[float, float]:
        if self.log:
            return math.log(self.lo), math.log(self.hi)
        return self.lo / self.scale, self.hi / self.scale

    def at_bound(self, value: float) -> bool:
        """True when ``value`` sits on a bound (within 1 % for log, 1e-3 scale otherwise)."""
        if self.log:
            return value <= self.lo * 1.01 or value >= self.hi / 1.01
        return value <= self.lo + 1e-3 * self.scale or value >= self.hi - 1e-3 * self.scale


@dataclass
class ParamSet:
    params: list[Param]

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    def pack(self, values: dict[str, float]) -> np.ndarray:
        return np.array([p.to_internal(float(values[p.name])) for p in self.params])

    def unpack(self, z: np.ndarray) -> dict[str, float]:
        return {p.name: p.to_value(float(zi)) for p, zi in zip(self.params, z)}

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.array([p.internal_bounds for p in self.params], dtype=float).reshape(-1, 2)
        return b[:, 0], b[:, 1]


@dataclass
class FitOutcome:
    params: dict[str, float]
    stderr: dict[str, float]
    cost: float                 # 0.5 * sum of squared residuals
    residuals: np.ndarray
    nfev: int
    success: bool
    jac: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


def jacobian_stderr(pset: ParamSet, z: np.ndarray, jac: np.ndarray, resid: np.ndarray,
                    free: np.ndarray | None = None) -> dict[str, float]:
    """Standard errors in each parameter's unit from the Jacobian of the internal variables."""
    n = resid.size
    free = np.ones(z.size, bool) if free is None else free
    p = int(free.sum())
    s2 = float(np.dot(resid, resid) / max(n - p, 1))
    err_z = np.zeros(z.size)
    try:
        J = jac[:, free]
        cov = np.linalg.pinv(J.T @ J) * s2
        err_z[free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except (np.linalg.LinAlgError, ValueError):
        err_z[free] = np.nan
    out = {}
    for prm, zi, ez in zip(pset.params, z, err_z):
        out[prm.name] = prm.to_value(zi) * ez if prm.log else ez * prm.scale
    return out


def least_squares_fit(residual: Callable[[dict[str, float]], np.ndarray], pset: ParamSet,
                      starts: list[dict[str, float]], *, max_nfev: int = 400, diff_step: float | None = 1e-6,
                      xtol: float = 1e-8, ftol: float = 1e-9, x_scale="jac", keep: int | None = None,
                      bad_value: float = 1e6,
                      jac: Callable[[dict[str, float]], np.ndarray | None] | None = None) -> FitOutcome | None:
    """Minimise ``sum(residual(params)**2)`` from several starts; the best fit, or None.

    ``residual`` takes named params in their units; a start whose residual is not finite or
    raises ValueError/ZeroDivisionError/OverflowError is penalised with ``bad_value``. With
    ``keep``, the starts are ranked by their initial cost and only the best ``keep`` fitted.

    ``jac`` (optional) gives the residual's exact derivatives: ``jac(params)`` returns an
    (n_residuals, n_params) array of d residual / d param in each parameter's unit (columns in
    ``pset`` order); a column of NaN (or None for all) asks for a forward difference of that
    parameter alone (step ``diff_step`` in the internal variable, as scipy's)."""
    lo, hi = pset.bounds()
    n_res = [0]
    ncall = [0]
    last = [None, None]  # the last (z, residual), reused by the finite-difference columns

    def fun(z):
        ncall[0] += 1
        try:
            r = np.asarray(residual(pset.unpack(z)), dtype=float)
        except (ValueError, ZeroDivisionError, OverflowError):
            r = np.full(max(n_res[0], 1), bad_value)
        else:
            n_res[0] = r.size
            if not np.all(np.isfinite(r)):
                r = np.full(r.size, bad_value)
        last[0], last[1] = np.array(z, dtype=float), r
        return r

    def jac_fun(z):
        try:
            J = jac(pset.unpack(z))
        except (ValueError, ZeroDivisionError, OverflowError):
            J = None
        if last[0] is None or not np.array_equal(last[0], z):
            fun(z)
        r0 = last[1]
        J = np.full((r0.size, z.size), np.nan) if J is None else np.array(J, dtype=float)
        if J.shape != (r0.size, z.size) or (r0 == bad_value).all():
            J = np.full((r0.size, z.size), np.nan)
        for i, prm in enumerate(pset.params):
            col = J[:, i]
            if np.isnan(col).all() or not np.all(np.isfinite(col)):
                h = (diff_step or 1e-8) * max(1.0, abs(float(z[i])))
                if z[i] + h > hi[i]:
                    h = -h
                zh = np.array(z, dtype=float)
                zh[i] += h
                rh = fun(zh)
                last[0], last[1] = np.array(z, dtype=float), r0
                J[:, i] = (rh - r0) / h
            else:
                J[:, i] = col * (prm.to_value(float(z[i])) if prm.log else prm.scale)
        return J

    z0s = [np.clip(pset.pack(s), lo + 1e-9, hi - 1e-9) for s in starts]
    if keep is not None and len(z0s) > keep:
        costs = [float(np.sum(fun(z) ** 2)) for z in z0s]
        z0s = [z0s[i] for i in np.argsort(costs)[:keep]]
    best = None
    for z0 in z0s:
        try:
            sol = least_squares(fun, z0, bounds=(lo, hi), method="trf", x_scale=x_scale, diff_step=diff_step,
                                max_nfev=max_nfev, xtol=xtol, ftol=ftol, jac=jac_fun if jac is not None else "2-point")
        except (ValueError, np.linalg.LinAlgError):
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        return None
    return FitOutcome(params=pset.unpack(best.x), stderr=jacobian_stderr(pset, best.x, best.jac, best.fun),
                      cost=float(best.cost), residuals=best.fun, nfev=ncall[0],
                      success=bool(best.success) or best.status > 0, jac=best.jac, extra={"z": best.x})


__all__ = ["FitOutcome", "Param", "ParamSet", "jacobian_stderr", "least_squares_fit"]
