"""Honest uncertainty of a least-squares fit: effective sample size, information criterion,
correlation, intervals, a block bootstrap in time and an MCMC sampler (emcee, optional).

Every function here works on a fit of :mod:`rig.fitting` (named parameters with bounds and ln
scaling) and its residuals in time order. Statistics weigh time, not rows: the ``*_time``,
``score_inflation`` and ``comparison_n_eff`` functions sum the (time-weighted) residuals over
uniform cells in time, so a record that logs ten times faster after a step does not count that
part ten times; :func:`effective_n` and the bootstrap assume rows on a uniform time grid.

* :func:`effective_n`: ``n_eff = n / (1 + 2 sum rho_k)``, the sum over the initial positive
  sequence of the residuals' autocorrelation (Geyer 1992), so a residual that is correlated over
  ``tau`` samples holds ``n / tau`` independent ones (the lag-1 correction alone misses a slow
  structure).
* :func:`effective_n_time`: the same for residuals of irregular rows or bins weighted by the time
  they stand for: their sums over uniform cells in time, so a record logged ten times faster
  after a step has the ``n_eff`` of the uniformly sampled one.
* :func:`comparison_n_eff`: the effective sample size of two fits' comparison, the better
  fit's residual along the fits' difference.
* :func:`information_criterion`: Gaussian BIC on the effective sample size,
  ``n_eff ln(SSR / n) + p ln(n_eff)`` (Schwarz 1978; Kass & Raftery 1995: a difference above
  6 is strong evidence).
* :func:`inflated_cov`, :func:`jacobian_summary`: the Jacobian's covariance with each parameter's
  variance inflated by ``n / n_eff`` of its influence in time (:func:`score_inflation`: each
  parameter sees the residual correlation where its information is), mapped to each parameter's
  unit; a ln-scaled parameter's 68 % interval is ``exp(ln v +- sd_ln)``
  (asymmetric, as xlook reports Dc). :func:`profile_interval` gives a skewed interval.
* :func:`block_bootstrap`: the residuals resampled in blocks of about twice their correlation
  time (moving-block bootstrap, Kuensch 1989), added to the fitted curve and refitted N times.
* :func:`mcmc`: emcee's affine-invariant ensemble sampler (Foreman-Mackey et al. 2013) on the
  Gaussian likelihood tempered by ``n_eff / n`` (the same correlated-noise correction), flat
  priors within the fit bounds.

All three give ``params_sd`` (one standard error per parameter), ``intervals`` (the 68 %
interval, ``[lo, hi]`` in the parameter's unit) and ``correlation`` (``{"names", "matrix"}``).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from rig.fitting import FitOutcome, ParamSet, least_squares_fit

#: the central 68 % of a distribution (one sigma of a normal)
Q_LO, Q_HI = 15.865, 84.135


def autocorr(r: np.ndarray, max_lag: int | None = None) -> np.ndarray:
    """Autocorrelation of a series at lags 0..max_lag (FFT; the mean removed)."""
    r = np.asarray(r, dtype=float)
    r = r - r.mean()
    n = r.size
    if n < 3 or not np.any(r):
        return np.ones(1)
    m = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(r, m)
    ac = np.fft.irfft(f * np.conj(f), m)[:n]
    ac /= ac[0]
    return ac[: (n // 2 if max_lag is None else min(max_lag + 1, n))]


def correlation_time(r: np.ndarray) -> float:
    """Integrated correlation time in samples, ``1 + 2 sum rho_k`` over the initial positive
    sequence of pair sums (Geyer 1992): 1 for white noise."""
    ac = autocorr(r)
    tau = 1.0
    for k in range(1, ac.size - 1, 2):
        pair = ac[k] + ac[k + 1]
        if pair <= 0:
            break
        tau += 2.0 * pair
    return max(tau, 1.0)


def effective_n(r: np.ndarray) -> float:
    """Effective number of independent residuals (``n / correlation_time``), at least 1."""
    r = np.asarray(r, dtype=float)
    return max(r.size / correlation_time(r), 1.0)


def effective_n_time(t_s: np.ndarray, r: np.ndarray, w: np.ndarray, cell_s: float,
                     ss_within: float = 0.0) -> float:
    """Effective sample size of a weighted residual in time (issue 20 Deliver 3: time, not rows).

    ``r`` are residuals of rows or bins at times ``t_s`` (s), ``w`` the raw samples each stands
    for (a time-weighted count), ``ss_within`` the raw sum of squares about the bins' means. The
    residual sums ``S_j = sum w_i r_i`` over uniform cells of ``cell_s`` seconds (empty cells 0: a
    gap is time) give the long-run variance ``sum_j S_j^2 tau_S``, ``tau_S`` the cells'
    :func:`correlation_time`; over the raw sum of squares ``SSR = sum w_i r_i^2 + ss_within``
    it is the variance inflation ``tau`` of the sum of the raw residuals (1 for white noise,
    the raw samples per independent one otherwise), and ``n_eff = sum w / tau``. A record logged
    ten times faster after a step has ten times the rows there and ten times their correlation in
    rows: its ``n_eff`` is that of the uniformly sampled one. At most ``sum w``, at least 1."""
    t_s, r, w = (np.asarray(a, dtype=float) for a in (t_s, r, w))
    n = float(w.sum())
    ssr = float(np.sum(w * r * r)) + float(ss_within)
    if t_s.size < 3 or not n > 0 or not ssr > 0 or not cell_s > 0:
        return max(n, 1.0)
    cell = np.floor((t_s - t_s.min()) / cell_s).astype(np.int64)
    s = np.bincount(cell, weights=w * r)
    tau = float(np.dot(s, s)) / ssr * correlation_time(s)
    return float(min(max(n / max(tau, 1.0), 1.0), n))


#: the cells in time of :func:`effective_n_time` and :func:`score_inflation` (s); longer where the
#: rows are sparser (:func:`time_cell_s`)
CELL_S = 1.0


def time_cell_s(t_s: np.ndarray) -> float:
    """The cell of the effective sample size for rows at ``t_s``: CELL_S, or two rows' median
    interval where rows are sparser (every cell then holds a row)."""
    t_s = np.asarray(t_s, dtype=float)
    return max(CELL_S, 2.0 * float(np.median(np.diff(t_s)))) if t_s.size > 1 else CELL_S


def inflated_cov(jac: np.ndarray, r: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(cov_z, tau, s2)``: the least-squares covariance of the internal variables,
    ``(J^T J)^-1 s^2`` with ``s^2 = SSR / (n - p)``, each parameter's variance inflated by its
    :func:`score_inflation` ``tau`` (``n / n_eff`` of the residual where its information is), the
    correlations kept. The one rule for identify's whole-record fit and diagnose's models."""
    jac, r = np.asarray(jac, dtype=float), np.asarray(r, dtype=float)
    n, p = jac.shape
    s2 = float(np.dot(r, r)) / max(n - p, 1)
    white = np.linalg.pinv(jac.T @ jac) * s2
    tau = score_inflation(t_s, jac, r, time_cell_s(t_s))
    f = np.sqrt(tau)
    return white * np.outer(f, f), tau, s2


def score_inflation(t_s: np.ndarray, jac: np.ndarray, r: np.ndarray, cell_s: float) -> np.ndarray:
    """Per parameter, the variance inflation ``n / n_eff`` of the residual where that parameter's
    information is: each row's influence on the estimate, ``h_i = (J^T J)^-1 J_i r_i`` (the score
    ``J_i r_i`` with the other parameters partialled out), summed over uniform cells of ``cell_s``
    seconds, ``sum_j S_j^2 tau_S / sum_i h_i^2`` (``tau_S`` the cells' :func:`correlation_time`),
    at least 1. A slow misfit that a parameter does not see (a drift that the constant absorbs,
    under the transients that carry L) does not widen that parameter's error. Rows in time order,
    ``jac`` and ``r`` weighted alike: the diagonal of a Newey-West sandwich whose lag window the
    data choose."""
    t_s, r = np.asarray(t_s, dtype=float), np.asarray(r, dtype=float)
    jac = np.asarray(jac, dtype=float)
    out = np.ones(jac.shape[1])
    if t_s.size < 3 or not cell_s > 0:
        return out
    h = (jac * r[:, None]) @ np.linalg.pinv(jac.T @ jac)
    cell = np.floor((t_s - t_s.min()) / cell_s).astype(np.int64)
    for j in range(h.shape[1]):
        den = float(np.dot(h[:, j], h[:, j]))
        if not den > 0:
            continue
        s = np.bincount(cell, weights=h[:, j])
        out[j] = max(float(np.dot(s, s)) / den * correlation_time(s), 1.0)
    return out


def comparison_n_eff(t_s: np.ndarray, w: np.ndarray, r_worse: np.ndarray, r_better: np.ndarray,
                     cell_s: float) -> float:
    """The effective sample size on which two fits of one record are compared: ``sum w`` over the
    :func:`score_inflation` of the better fit's residual along the two fits' difference
    ``d = r_worse - r_better`` (the direction the extra parameters move the prediction). What
    decides between the models is the residual's correlation where they differ: a slow drift that
    both leave (another cause, not yet in either) does not hide a periodic term, and a record
    logged ten times faster after a step counts that part as long as it lasts."""
    t_s, w = np.asarray(t_s, dtype=float), np.asarray(w, dtype=float)
    sw = np.sqrt(w)
    d = np.asarray(r_worse, dtype=float) - np.asarray(r_better, dtype=float)
    tau = score_inflation(t_s, (sw * d)[:, None], sw * np.asarray(r_better, dtype=float), cell_s)[0]
    return float(max(w.sum() / tau, 1.0))


def information_criterion(ssr: float, n: int, n_eff: float, n_par: int) -> float:
    """Gaussian BIC on the effective sample size: ``n_eff ln(SSR/n) + p ln(n_eff)``."""
    ne = max(float(n_eff), 1.0)
    return ne * math.log(max(ssr, 1e-300) / max(n, 1)) + n_par * math.log(ne)


def correlation_of(cov: np.ndarray, names: list[str]) -> dict:
    """``{"names": [...], "matrix": [[...]]}`` from a covariance matrix (rounded to 4 digits)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = cov / np.outer(sd, sd)
    c = np.where(np.isfinite(c), c, 0.0)
    np.fill_diagonal(c, 1.0)
    return {"names": list(names), "matrix": [[round(float(v), 4) for v in row] for row in np.clip(c, -1, 1)]}


def jacobian_summary(pset: ParamSet, fit: FitOutcome, t_s: np.ndarray) -> dict:
    """sd, 68 % intervals and correlation from the fit's Jacobian (:func:`inflated_cov`: each
    parameter's variance inflated by ``n / n_eff`` of its score in time; rows at ``t_s``, in time
    order). Internal variables: ln for log parameters, so their intervals are asymmetric.
    ``sd_ratio`` (per parameter) is the inflation's square root, for rescaling a profile interval."""
    z = fit.extra["z"]
    r = np.asarray(fit.residuals, dtype=float)
    p = z.size
    try:
        cov_z, tau, _ = inflated_cov(fit.jac, r, t_s)
    except (np.linalg.LinAlgError, ValueError):
        cov_z, tau = np.full((p, p), np.nan), np.ones(p)
    sd_z = np.sqrt(np.maximum(np.diag(cov_z), 0.0))
    sd, iv = {}, {}
    for prm, zi, si in zip(pset.params, z, sd_z):
        val = prm.to_value(float(zi))
        if prm.log:
            # an undetermined parameter's interval stops at its fit bounds
            lo_z, hi_z = prm.internal_bounds
            sd[prm.name] = val * si if si < 700 else math.inf
            iv[prm.name] = [math.exp(max(zi - si, lo_z)), math.exp(min(zi + si, hi_z))]
        else:
            sd[prm.name] = si * prm.scale
            iv[prm.name] = [val - si * prm.scale, val + si * prm.scale]
    # covariance in the parameters' own units (first order) for the correlation
    d = np.array([prm.to_value(float(zi)) if prm.log else prm.scale for prm, zi in zip(pset.params, z)])
    cov = cov_z * np.outer(d, d)
    return {"method": "jacobian", "params_sd": sd, "intervals": iv, "correlation": correlation_of(cov, pset.names),
            "cov": cov, "sd_ratio": {nm: float(math.sqrt(x)) for nm, x in zip(pset.names, tau)},
            "errors": "n/n_eff of each parameter's score in time"}


def profile_interval(residual: Callable[[dict], np.ndarray], pset: ParamSet, fit: FitOutcome, name: str,
                     n_eff: float, sd_z: float, *, iterations: int = 3, max_nfev: int = 60) -> list[float] | None:
    """The 68 % profile-likelihood interval of one parameter: where the best fit with ``name`` held
    (the others refitted) has ``Delta = (SSR - SSR_min) / s^2 * n_eff / n`` equal to 1 (one sigma
    of a chi-square with 1 dof), ``s^2 = SSR_min / (n - p)``. Each side starts at the Jacobian's
    ``sd_z`` (internal units: ln for a log parameter) and is refined on ``sqrt(Delta)``, which is
    linear in the parameter where the likelihood is Gaussian (secant, ``iterations`` refits).
    Skewed likelihoods (L on a flat a-b-L valley) give an asymmetric interval, as xlook reports
    Dc. None when a refit fails."""
    j = pset.names.index(name)
    prm = pset.params[j]
    rest = ParamSet([q for q in pset.params if q.name != name])
    z0 = np.asarray(fit.extra["z"], dtype=float)
    r0 = np.asarray(fit.residuals, dtype=float)
    n, p = r0.size, z0.size
    ssr0 = float(np.dot(r0, r0))
    s2 = ssr0 / max(n - p, 1)
    scale = min(max(n_eff, 1.0) / n, 1.0) / s2
    lo_b, hi_b = prm.internal_bounds
    start = {k: v for k, v in fit.params.items() if k != name}

    def delta(zj: float) -> float:
        held = prm.to_value(zj)
        out = least_squares_fit(lambda q: residual({**q, name: held}), rest, [start], max_nfev=max_nfev,
                                diff_step=None, xtol=1e-6, ftol=1e-8, x_scale="jac")
        if out is None:
            raise ValueError("profile refit failed")
        return max(2.0 * out.cost - ssr0, 0.0) * scale

    if not (sd_z > 0 and math.isfinite(sd_z)):
        return None
    ends = []
    try:
        for sign in (-1.0, 1.0):
            a, fa = 0.0, 0.0                      # offset from z0 and sqrt(Delta) there
            b = sd_z
            for _ in range(iterations):
                zb = min(max(z0[j] + sign * b, lo_b + 1e-9), hi_b - 1e-9)
                fb = math.sqrt(delta(zb))
                if abs(fb - 1.0) < 0.02 or zb in (lo_b + 1e-9, hi_b - 1e-9):
                    break
                # secant on sqrt(Delta) = 1 (from the minimum, where it is 0)
                nb = a + (1.0 - fa) * (b - a) / (fb - fa) if fb > fa else 2.0 * b
                a, fa = (b, fb) if fb < 1.0 else (a, fa)
                b = min(max(nb, 0.2 * sd_z), 20.0 * sd_z)
            ends.append(prm.to_value(min(max(z0[j] + sign * b, lo_b), hi_b)))
    except ValueError:
        return None
    return [min(ends), max(ends)]


def _sample_summary(pset: ParamSet, samples: np.ndarray, method: str, **extra) -> dict:
    """sd, percentile intervals and correlation of parameter samples (rows; parameters' units)."""
    sd = {nm: float(np.std(samples[:, j], ddof=1)) for j, nm in enumerate(pset.names)}
    iv = {nm: [float(np.percentile(samples[:, j], Q_LO)), float(np.percentile(samples[:, j], Q_HI))]
          for j, nm in enumerate(pset.names)}
    cov = np.cov(samples, rowvar=False).reshape(len(pset.names), len(pset.names))
    return {"method": method, "params_sd": sd, "intervals": iv, "correlation": correlation_of(cov, pset.names),
            "cov": cov, "n_samples": int(samples.shape[0]), **extra}


def block_bootstrap(residual_for: Callable[[np.ndarray], Callable[[dict], np.ndarray]], pset: ParamSet,
                    fit: FitOutcome, n_boot: int, *, seed: int = 0, block: int | None = None, max_nfev: int = 60,
                    progress: Callable[[], None] | None = None) -> dict:
    """Moving-block bootstrap in time. ``residual_for(y_offset)`` returns the residual function of a
    pseudo record whose data are the fitted curve plus ``y_offset`` (the resampled residuals, in
    the residual vector's order, which is time order); each pseudo record is refitted from the
    best fit. Blocks hold about twice the residuals' correlation time (at least 5 samples)."""
    r = np.asarray(fit.residuals, dtype=float)
    n = r.size
    if block is None:
        block = int(max(5, math.ceil(2.0 * correlation_time(r))))
    block = min(block, max(n // 4, 1))
    rng = np.random.default_rng(seed)
    n_blocks = int(math.ceil(n / block))
    rows = []
    for _ in range(int(n_boot)):
        starts = rng.integers(0, n - block + 1, size=n_blocks)
        e = np.concatenate([r[s:s + block] for s in starts])[:n]
        e = e - e.mean() + r.mean()
        # residual = model - data; data* = model_hat - e*, so residual* = model - model_hat + e*
        out = least_squares_fit(residual_for(e), pset, [fit.params], max_nfev=max_nfev, diff_step=None,
                                xtol=1e-6, ftol=1e-6, x_scale="jac")
        if out is not None:
            rows.append([out.params[nm] for nm in pset.names])
        if progress is not None:
            progress()
    if len(rows) < 3:
        raise ValueError("bootstrap: fewer than 3 refits succeeded")
    return _sample_summary(pset, np.asarray(rows), "bootstrap", block_samples=int(block))


def mcmc(residual: Callable[[dict], np.ndarray], pset: ParamSet, fit: FitOutcome, n_steps: int, n_eff: float, *,
         seed: int = 0, cov_z: np.ndarray | None = None, progress: Callable[[], None] | None = None) -> dict:
    """emcee on the internal variables: ``ln p = -SSR / (2 s^2) * n_eff / n`` (flat priors inside
    the bounds), ``s^2`` the fit's residual variance; walkers 2 p + 2 started in a small ball
    around the best fit (the Jacobian's covariance / 10); the first third of the chain is burn-in."""
    try:
        import emcee
    except ImportError as exc:  # an optional extra
        raise ValueError("--uncertainty mcmc needs emcee: pip install 'rig[mcmc]' (or pip install emcee)") from exc
    z0 = np.asarray(fit.extra["z"], dtype=float)
    r0 = np.asarray(fit.residuals, dtype=float)
    n, p = r0.size, z0.size
    s2 = float(np.dot(r0, r0)) / max(n - p, 1)
    temper = min(max(n_eff, 1.0) / n, 1.0)
    lo, hi = pset.bounds()

    def log_prob(z):
        if np.any(z <= lo) or np.any(z >= hi):
            return -np.inf
        try:
            rr = np.asarray(residual(pset.unpack(z)), dtype=float)
        except (ValueError, ZeroDivisionError, OverflowError):
            return -np.inf
        if rr.size != n or not np.all(np.isfinite(rr)):
            return -np.inf
        return -0.5 * float(np.dot(rr, rr)) / s2 * temper

    nw = 2 * p + 2
    rng = np.random.default_rng(seed)
    if cov_z is None or not np.all(np.isfinite(cov_z)):
        cov_z = np.diag(np.full(p, 1e-4))
    scale = np.sqrt(np.maximum(np.diag(cov_z), 1e-12)) * 0.1
    p0 = z0 + rng.standard_normal((nw, p)) * scale
    p0 = np.clip(p0, lo + 1e-9, hi - 1e-9)
    sampler = emcee.EnsembleSampler(nw, p, log_prob)
    sampler.random_state = np.random.RandomState(seed).get_state()  # reproducible moves
    state = p0
    for _ in sampler.sample(state, iterations=int(n_steps)):
        if progress is not None:
            progress()
    chain = sampler.get_chain(discard=int(n_steps) // 3, flat=True)
    if chain.shape[0] < 3:
        raise ValueError("mcmc: too few steps (at least 6)")
    vals = np.array([[prm.to_value(float(zi)) for prm, zi in zip(pset.params, row)] for row in chain])
    acc = float(np.mean(sampler.acceptance_fraction))
    return _sample_summary(pset, vals, "mcmc", walkers=nw, steps=int(n_steps), acceptance=round(acc, 3))


def parse_uncertainty(text: str) -> tuple[str, int]:
    """``jacobian`` | ``bootstrap:N`` | ``mcmc:N`` -> (method, N); ValueError naming the option."""
    t = str(text).strip().lower()
    if t == "jacobian":
        return "jacobian", 0
    meth, _, num = t.partition(":")
    if meth in ("bootstrap", "mcmc"):
        try:
            n = int(num)
        except ValueError:
            n = -1
        least = 10 if meth == "bootstrap" else 30
        if n < least:
            raise ValueError(f"--uncertainty {text}: {meth} needs a count of at least {least}, e.g. {meth}:"
                             f"{200 if meth == 'bootstrap' else 2000}")
        return meth, n
    raise ValueError(f"--uncertainty {text}: expected jacobian, bootstrap:N or mcmc:N")


__all__ = ["Q_LO", "Q_HI", "autocorr", "block_bootstrap", "correlation_of", "correlation_time", "effective_n",
           "information_criterion", "jacobian_summary", "mcmc", "parse_uncertainty", "profile_interval"]
