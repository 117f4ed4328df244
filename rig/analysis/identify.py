"""Identification of rate-and-state friction from velocity steps (Dupont & Dunlap 1995).

Per step (section 4.2.1), with ``mu`` the friction coefficient of one interface
(friction over twice the normal force; the measured normals when logged):

* ``v1``, ``v2``: slopes of straight lines fitted to the LVDT position before and
  after the step; the *effective step* (time ``t*``, position ``x*``) is where
  the two lines cross; slip after the step is ``delta = x - x*``;
* ``mu1``: mean friction over the 200 samples before the step;
* ``mu2``: mean friction over a 200-point window starting 50, 100 or 250 µm
  after the step (three fits, the one with the largest coefficient of
  determination ``r2`` is kept, as in the paper);
* ``L``: least-squares fit of the exponential decay of eq. (12) in slip,
  ``mu(delta) = mu2 + (mu_max - mu2) exp(-delta / L)``, to the data from the
  end of the velocity rise (``rise_guard_s`` after ``t*``) to the end of the
  window, ``mu2`` fixed by the window; ``mu_max`` is the fitted curve at
  ``delta = 0`` (the friction an ideal step would have reached; the raw
  peak of a noisy record is biased up by the noise, and lowered by a finite
  rise time);
* eq. (10): ``A_mu = (mu_max - mu1) / ln(v2/v1)``;
  eq. (11): ``B_mu = A_mu - (mu2 - mu1) / ln(v2/v1)``;
  eq. (14): rise time ``t_r = L ln 9 / v2``.

Over steps (or over trials, when several files are given): mean and
standard error of the mean; eq. (13) ``k_cr = (B_mu - A_mu) N / L`` from the
means, ``N`` the nominal per-rider normal force (this reproduces Table 2), with
its standard error propagated to first order from those of A, B and L (which
also reproduces Table 2's k_cr errors).

Beyond the paper, :func:`fit_whole_record` fits the rate-and-state model to the
whole record at once (all steps; the forward model of :mod:`rig.model.forward`,
parameters as :data:`rig.model.spec.PARAMS` declares them, fitted by :mod:`rig.fitting`, the
same core diagnosis uses), optionally with a finite machine stiffness
between the position sensor and the interface (needed for rock-mechanics
records whose displacement is measured at the load point).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from rig.kinematics import Step, detect_steps, estimate_velocity, line_fit
from rig.data import TrialData, atomic_write_text, parse_number
from rig.log import load_trial
from rig.fitting import Param, ParamSet, least_squares_fit
from rig.fitting.stats import effective_n
from rig.analysis.report import rounded as _r, rounded_warnings
from rig.model.forward import predict_force
from rig.model.friction import V0_UM_S
from rig.model.paper import k_cr_eq13_N_per_um
from rig.model.spec import PARAMS, PLAUSIBLE, RSF_NAMES, FrictionModel, rsf_vocabulary

SCHEMA = "rig.identify/1"
WINDOW_STARTS_UM = (50.0, 100.0, 250.0)
WINDOW_POINTS = 200
LN9 = math.log(9.0)


# ---------------------------------------------------------------------------
# One step
# ---------------------------------------------------------------------------
@dataclass
class StepResult:
    step: Step
    mu1: float
    mu2: float
    mu_max: float
    mu_peak_raw: float
    A_mu: float
    B_mu: float
    L_um: float
    r2: float
    window_um: float
    fits: list = field(default_factory=list)   # every window's fit (for the plot/JSON)
    ok: bool = True
    reason: str = ""
    trial: int = 0

    @property
    def t_r_s(self) -> float:
        """Eq. (14): the rise time ``L ln 9 / v2`` (s); NaN without an L."""
        return self.L_um * LN9 / abs(self.step.v2_um_s) if math.isfinite(self.L_um) else math.nan

    def where(self, n_trials: int) -> str:
        """The ``where`` of this step's warnings (:func:`step_where`)."""
        return step_where(self.step.t_s, self.trial, n_trials)

    def report(self) -> dict:
        """The step's JSON (``steps[]`` of rig.identify/1), rounded here and only here."""
        s = self.step
        d = {"t_s": round(s.t_s, 4), "v1_um_s": _r(s.v1_um_s), "v2_um_s": _r(s.v2_um_s),
             "A_mu": _r(self.A_mu), "B_mu": _r(self.B_mu), "L_um": _r(self.L_um), "r2": _r(self.r2),
             "window_um": self.window_um,
             # additions (spec allows extra keys)
             "direction": s.direction, "trial": self.trial, "source": s.source,
             "mu1": _r(self.mu1), "mu2": _r(self.mu2), "mu_max": _r(self.mu_max),
             "mu_peak_raw": _r(self.mu_peak_raw),
             "t_r_s": _r(self.t_r_s),
             "windows": [{"window_um": f["window_um"], "mu2": _r(f["mu2"]), "L_um": _r(f["L_um"]),
                          "r2": _r(f["r2"])} for f in self.fits]}
        if not self.ok:
            d["rejected"] = self.reason
        return d


def _fit_exp(delta: np.ndarray, mu: np.ndarray, mu2: float, l_max: float):
    """Least squares ``mu = mu2 + a exp(-delta/L)`` with mu2 fixed: a linear for each L,
    L by a bounded 1-D search on ln L. Returns (a, L, r2)."""
    sst = float(np.sum((mu - mu.mean()) ** 2))
    within = 0.0
    wts = None
    if delta.size > 4000:
        # dense record: bin in slip (bins << L); SSE = sum n_b (ybar_b - model)^2 + within-bin SS
        nb = 2000
        lo_d, hi_d = float(delta.min()), float(delta.max())
        idx = np.minimum(((delta - lo_d) / max(hi_d - lo_d, 1e-12) * nb).astype(np.int64), nb - 1)
        cnt = np.bincount(idx, minlength=nb).astype(float)
        sd = np.bincount(idx, delta, minlength=nb)
        sm = np.bincount(idx, mu, minlength=nb)
        smm = np.bincount(idx, mu * mu, minlength=nb)
        ok = cnt > 0
        cnt, sd, sm, smm = cnt[ok], sd[ok], sm[ok], smm[ok]
        within = float(np.sum(smm - sm * sm / cnt))
        delta, mu, wts = sd / cnt, sm / cnt, cnt
    y = mu - mu2
    w_ = np.ones_like(y) if wts is None else wts

    def sse_for(lnl):
        e = np.exp(-delta / math.exp(lnl))
        we = w_ * e
        ee = float(np.dot(we, e))
        a = float(np.dot(we, y) / ee) if ee > 0 else 0.0
        r = y - a * e
        return float(np.dot(w_ * r, r)) + within, a

    lo, hi = math.log(0.3), math.log(max(l_max, 1.0))
    grid = np.linspace(lo, hi, 25)
    vals = [sse_for(g)[0] for g in grid]
    k = int(np.argmin(vals))
    a_, b_ = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if b_ > a_:
        res = minimize_scalar(lambda g: sse_for(g)[0], bounds=(a_, b_), method="bounded",
                              options={"xatol": 1e-4})
        lnl = float(res.x)
    else:
        lnl = float(grid[k])
    sse, a = sse_for(lnl)
    r2 = 1.0 - sse / sst if sst > 0 else 0.0
    return a, math.exp(lnl), r2


def fit_step(t: np.ndarray, x: np.ndarray, mu: np.ndarray, step: Step, *, window_points: int = WINDOW_POINTS,
             window_starts_um=WINDOW_STARTS_UM, pre_points: int = WINDOW_POINTS,
             rise_guard_s: float = 0.5) -> StepResult:
    """Eqs. (10)-(12) for one step (see the module docstring)."""
    i0 = step.i
    # the pre_points samples before the step, not using the rise itself
    hi_pre = min(int(np.searchsorted(t, step.t_s - 0.5 * rise_guard_s)), i0)
    lo_pre = max(step.pre[0], hi_pre - pre_points)
    hi_pre = max(hi_pre, lo_pre + 1)
    mu1 = float(np.mean(mu[lo_pre:hi_pre]))
    post_lo, post_hi = step.post
    tt = t[post_lo:post_hi]
    delta = x[post_lo:post_hi] - step.x_um
    mseg = mu[post_lo:post_hi]
    lnr = math.log(step.v2_um_s / step.v1_um_s)
    fit_lo = int(np.searchsorted(tt, step.t_s + rise_guard_s))
    # raw peak (smoothed over 5 samples) in the first part of the transient
    sgn = 1.0 if lnr > 0 else -1.0
    nb = min(tt.size, max(fit_lo + 5, int(np.searchsorted(delta, 20.0))))
    sm = np.convolve(mseg[:nb], np.ones(5) / 5, mode="valid") if nb >= 5 else mseg[:nb]
    mu_peak = float(sgn * np.max(sgn * sm)) if sm.size else math.nan
    fits = []
    # monotone slip for window search (noise makes delta non-monotone by ~0.1 µm)
    dmono = np.maximum.accumulate(delta)
    wins = []
    for w in window_starts_um:
        j0 = int(np.searchsorted(dmono, w))
        j1 = j0 + window_points
        if j1 <= tt.size:
            wins.append((w, j0, j1))
    # the same data (from the end of the rise to the end of the furthest window) for all
    # three fits, so that their coefficients of determination compare the mu2 values
    j_end = max((j1 for _, _, j1 in wins), default=0)
    for w, j0, j1 in wins:
        mu2 = float(np.mean(mseg[j0:j1]))
        dd = delta[fit_lo:j_end]
        mm = mseg[fit_lo:j_end]
        if dd.size < 10:
            continue
        a, L, r2 = _fit_exp(dd, mm, mu2, l_max=4.0 * max(dd.max(), 1.0))
        fits.append({"window_um": int(w) if float(w).is_integer() else w, "mu2": mu2, "a": a, "L_um": L, "r2": r2,
                     "j0": j0 + post_lo, "j1": j1 + post_lo, "fit_lo": fit_lo + post_lo})
    if not fits:
        # the segment is too short for the paper's windows: use its last 200 points
        j1 = tt.size
        j0 = max(fit_lo + 10, j1 - window_points)
        if j1 - fit_lo < 20:
            return StepResult(step, mu1, math.nan, math.nan, mu_peak, math.nan, math.nan, math.nan, math.nan,
                              math.nan, [], ok=False, reason="segment after the step too short")
        mu2 = float(np.mean(mseg[j0:j1]))
        dd = delta[fit_lo:j1]
        mm = mseg[fit_lo:j1]
        a, L, r2 = _fit_exp(dd, mm, mu2, l_max=4.0 * max(dd.max(), 1.0))
        fits.append({"window_um": round(float(delta[j0]), 1), "mu2": mu2, "a": a, "L_um": L, "r2": r2,
                     "j0": j0 + post_lo, "j1": j1 + post_lo, "fit_lo": fit_lo + post_lo})
    best = max(fits, key=lambda f: f["r2"])
    mu2 = best["mu2"]
    mu_max = mu2 + best["a"]
    A = (mu_max - mu1) / lnr
    B = A - (mu2 - mu1) / lnr
    res = StepResult(step, mu1, mu2, mu_max, mu_peak, A, B, best["L_um"], best["r2"], best["window_um"], fits)
    fit_span = float(np.max(delta[best["fit_lo"] - post_lo:best["j1"] - post_lo])) if best["j1"] > best["fit_lo"] else 0.0
    res.ok, res.reason = physical_check(A, B, best["L_um"], best["r2"], best["a"] * sgn, fit_span)
    return res


# physical bounds of a per-step result (docs/identification.md): rate-and-state coefficients of
# lubricated metals and rocks are O(1e-4 - 2e-2) (Table 2; rock friction), so |A|, |B| >= 0.05 is
# an extrapolation, not a measurement; L must lie inside the slip the decay was fitted over (an
# L beyond it is a drift, one below 0.3 µm is the rise itself); an r2 below R2_MIN means the
# exponential explains too little of the transient to trust A (which extrapolates it to delta 0)
AB_MAX = PLAUSIBLE["A_mu"].hi  # 0.05, the physical range declared with the parameters (rig.model.spec)
R2_MIN = 0.2
L_MIN_UM = 0.3


def physical_check(A: float, B: float, L: float, r2: float, signed_amp: float, fit_span_um: float) -> tuple[bool, str]:
    """(ok, reason) of one step's A, B, L against the physical bounds above."""
    if not all(math.isfinite(v) for v in (A, B, L, r2)):
        return False, "fit did not converge (non-finite A, B, L or r2)"
    if not signed_amp > 0:
        return False, "no decay of the expected sign after the step"
    if abs(A) >= AB_MAX or abs(B) >= AB_MAX:
        return False, f"|A| or |B| >= {AB_MAX} (A = {A:.3g}, B = {B:.3g}): an extrapolated peak, not a measurement"
    if not (L_MIN_UM * 1.01 < L < fit_span_um):
        return False, (f"L = {L:.3g} um outside the fitted window ({L_MIN_UM:g} to {fit_span_um:.3g} um of slip): "
                       "the decay is not resolved")
    if r2 < R2_MIN:
        return False, f"r2 = {r2:.2f} < {R2_MIN}: the exponential explains too little of the transient"
    return True, ""


# ---------------------------------------------------------------------------
# Statistics and eq. (13)
# ---------------------------------------------------------------------------
def mean_sem(values) -> tuple[float, float]:
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if a.size == 0:
        return math.nan, math.nan
    if a.size == 1:
        return float(a[0]), math.nan
    return float(a.mean()), float(a.std(ddof=1) / math.sqrt(a.size))


def k_cr_table2(A, sA, B, sB, L, sL, N_N) -> tuple[float, float]:
    """Eq. (13) in kN/m from mean A, B, L, with the first-order propagated standard error
    (A, B, L independent). Reproduces Table 2 (e.g. boundary: 15.1 +- 2.4 vs 14.8 +- 2.3)."""
    k = k_cr_eq13_N_per_um(A, B, L, N_N) * 1e3
    if not all(math.isfinite(v) for v in (sA, sB, sL)):
        return k, math.nan
    dBA = B - A
    rel2 = ((sA ** 2 + sB ** 2) / dBA ** 2 if dBA != 0 else math.inf) + (sL / L) ** 2
    return k, abs(k) * math.sqrt(rel2)


def reject_outliers(steps: list[StepResult], k: float = 4.0, rel: float = 0.5) -> None:
    """Robust mean over steps: with 4 or more accepted steps, one whose A, B or L lies more than
    ``k`` robust sigmas (1.4826 MAD) AND more than ``rel`` (50 %) from the median of the steps is
    rejected, with its reason (steps that agree to a few % have a tiny MAD: 8 % is no outlier)."""
    good = [s for s in steps if s.ok]
    if len(good) < 4:
        return
    for nm in ("A_mu", "B_mu", "L_um"):
        vals = np.array([getattr(s, nm) for s in good])
        med = float(np.median(vals))
        mad = 1.4826 * float(np.median(np.abs(vals - med)))
        if mad <= 0:
            continue
        for s, v in zip(good, vals):
            if s.ok and abs(v - med) > k * mad and abs(v - med) > rel * abs(med):
                s.ok = False
                s.reason = f"outlier: {nm} = {v:.3g} is {abs(v - med) / mad:.1f} robust sigma from the median {med:.3g}"


@dataclass
class TrialMeans:
    """One trial's means over its accepted steps (``per_trial[]`` of rig.identify/1 with several files)."""
    A_mu: float
    B_mu: float
    L_um: float
    n_steps: int

    def report(self) -> dict:
        return {"A_mu": _r(self.A_mu), "B_mu": _r(self.B_mu), "L_um": _r(self.L_um), "n_steps": self.n_steps}


def summarize(groups: list[list[StepResult]], N_N: float) -> tuple[dict, dict, str, list[TrialMeans]]:
    """Mean and SEM over steps (one group) or over trials (each group's mean first), after the
    physical bounds (:func:`physical_check`) and the outlier rule (:func:`reject_outliers`).
    Unrounded (the report rounds: :meth:`Identification.report`)."""
    names = ("A_mu", "B_mu", "L_um")
    for g in groups:
        reject_outliers(g)
    good = [[s for s in g if s.ok] for g in groups]
    per_trial = [TrialMeans(*(mean_sem([getattr(s, n) for s in g])[0] for n in names), n_steps=len(g))
                 for g in good]
    if len(groups) > 1:
        over = "trials"
        cols = {n: [getattr(r, n) for r in per_trial if r.n_steps > 0] for n in names}
    else:
        over = "steps"
        cols = {n: [getattr(s, n) for s in good[0]] for n in names}
    mean, sem = {}, {}
    for n in names:
        mean[n], sem[n] = mean_sem(cols[n])
    k, sk = k_cr_table2(mean["A_mu"], sem["A_mu"], mean["B_mu"], sem["B_mu"], mean["L_um"], sem["L_um"], N_N)
    mean["k_cr_kN_per_m"], sem["k_cr_kN_per_m"] = k, sk
    # eq. (14) rise time, mean over steps
    mean["t_r_s"], sem["t_r_s"] = mean_sem([s.t_r_s for g in good for s in g])
    return mean, sem, over, per_trial


# ---------------------------------------------------------------------------
# Whole-record fit (beyond the paper)
# ---------------------------------------------------------------------------
def _segment_velocity(t: np.ndarray, x: np.ndarray, steps: list[Step], fallback: np.ndarray | None = None,
                      skip_um: float = 0.0):
    """Velocity that is the line-fit slope on each step's constant-velocity stretches
    (before: ``v1``, after: ``v2``) and ``fallback`` (an estimator) elsewhere; and the mask
    of those stretches (where the whole-record fit compares model and data)."""
    v = np.array(fallback, dtype=float) if fallback is not None else np.full(t.size, np.nan)
    mask = np.zeros(t.size, bool)
    if not steps:
        if fallback is None:
            v[:] = line_fit(t, x)[1]
        mask[:] = True
        return v, mask
    for s in steps:
        v[s.pre[0]:s.i] = s.v1_um_s
        v[s.i:s.post[1]] = s.v2_um_s
        # the first skip_um of a stretch may still carry the transient of what came before
        # (a start from rest, a return): compare from there on, at most half the stretch
        x0 = x[s.pre[0]]
        skip = min(skip_um, 0.5 * (x[max(s.i - 1, s.pre[0])] - x0))
        lo = s.pre[0] + int(np.searchsorted(x[s.pre[0]:s.i] - x0, skip)) if skip > 0 else s.pre[0]
        mask[lo:s.post[1]] = True
    if fallback is None:
        # fill the gaps by the neighbouring stretch's velocity
        idx = np.where(np.isfinite(v), np.arange(t.size), 0)
        np.maximum.accumulate(idx, out=idx)
        v = v[idx]
        first = np.flatnonzero(np.isfinite(v))
        v[: first[0]] = v[first[0]]
    return v, mask


def _time_weights(t: np.ndarray) -> tuple[np.ndarray, float]:
    """Each sample's share of the record's time: half the span to its neighbours, at most three
    typical spacings (a gap adds no weight), over the typical spacing (the spacing that covers
    half the duration: 0.1 s for a record at 10 Hz for half its time, whatever its rows at
    100 Hz). A part logged ten times faster then counts as long as it lasts, not ten times more;
    evenly sampled records have every weight 1. Returns (weights, typical spacing in s)."""
    dt = np.diff(t)
    if dt.size == 0:
        return np.ones(t.size), 1.0
    order = np.argsort(dt)
    cum = np.cumsum(dt[order])
    typical = float(dt[order][min(int(np.searchsorted(cum, 0.5 * cum[-1])), dt.size - 1)])
    d = np.minimum(dt, 3.0 * typical)
    span = 0.5 * (np.concatenate([[d[0]], d]) + np.concatenate([d, [d[-1]]]))
    return span / max(typical, 1e-12), typical


def _time_bins(t: np.ndarray, max_points: int) -> tuple[np.ndarray, float]:
    """Uniform bins in time for a record of more than ``max_points`` samples (each sample's bin,
    empty bins dropped) and their width (s): duration / ``max_points``, a whole number of typical
    spacings; shorter records keep every sample (bin i = sample i)."""
    if t.size <= max_points:
        return np.arange(t.size), float(np.median(np.diff(t))) if t.size > 1 else 1.0
    _, typical = _time_weights(t)
    dur = float(t[-1] - t[0])
    width = typical * max(1.0, math.ceil(dur / max(max_points, 1) / max(typical, 1e-12) - 1e-9)) * 0.999
    raw = np.floor((t - t[0]) / width + 1e-9).astype(np.int64)
    used = np.zeros(int(raw[-1]) + 1, bool)
    used[raw] = True
    comp = np.cumsum(used) - 1
    return comp[raw], width


def _bin_mean(a: np.ndarray, idx: np.ndarray, cnt: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Means per bin (weighted by ``w`` when given; ``cnt`` the bins' total weight)."""
    a = np.asarray(a, dtype=float)
    return np.bincount(idx, a if w is None else a * w, minlength=cnt.size) / cnt


def _binned_steps(steps: list[Step], idx: np.ndarray, nb: int) -> list[Step]:
    """The steps' sample indices moved to the time bins."""
    def at(i):
        return int(idx[min(max(i, 0), idx.size - 1)]) if i < idx.size else nb

    def end(i):
        return int(idx[i - 1]) + 1 if i > 0 else 0

    return [Step(s.t_s, s.t_nominal_s, min(at(s.i), nb - 1), s.v1_um_s, s.v2_um_s, s.x_um,
                 (at(s.pre[0]), at(s.i)), (at(s.i), min(end(s.post[1]), nb)), s.source) for s in steps]


def _runs(steps: list[Step], n: int) -> list[tuple[int, int]]:
    """Sample ranges [lo, hi) of the record's sliding runs: steps whose stretches join (a step's
    stretch after it is the next one's before it) form one run; each run starts after a rest, a
    return or the record's start, where the state is unknown (fitted per run). No steps: one run."""
    if not steps:
        return [(0, n)]
    out: list[list[int]] = []
    for s in sorted(steps, key=lambda s: s.pre[0]):
        lo, hi = s.pre[0], max(s.post[1], s.i + 1)
        if out and lo <= out[-1][1] + 2:
            out[-1][1] = max(out[-1][1], hi)
        else:
            out.append([lo, hi])
    return [(a, b) for a, b in out if b - a >= 5]


DETRENDS = ("none", "linear", "auto")
LAWS = ("slip", "aging")
#: the trend's slip is in mm (the field's unit: friction per mm of slip)
TREND = Param("rate_mu_per_mm", "1/mm", -1.0, 1.0, scale=1e-4)


def steady_windows(t: np.ndarray, x: np.ndarray, mu: np.ndarray, v: np.ndarray, steps: list[Step],
                   runs: list[tuple[int, int]], L_um: float, min_slip_um: float = 20.0) -> list[tuple[int, int]]:
    """Steady-state windows in the manner of Giacomel et al. (2024): the parts of each
    constant-velocity stretch more than 5 L of slip after its start (the transient has decayed to
    e^-5 = 0.7 %: at 3 L its 5 % still tilted the windows by half the trend on generated records),
    holding at least ``min_slip_um`` of slip."""
    bounds = sorted({lo for lo, _ in runs} | {hi for _, hi in runs} | {s.i for s in steps})
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 10 or not any(lo <= a < hi for lo, hi in runs):
            continue
        x0 = x[a]
        j = a + int(np.searchsorted(np.maximum.accumulate(x[a:b] - x0), 5.0 * L_um))
        if j < b - 5 and x[b - 1] - x[j] >= min_slip_um:
            out.append((j, b))
    return out


def trend_from_windows(s_mm: np.ndarray, mu: np.ndarray, windows: list[tuple[int, int]]) -> tuple[float, float]:
    """Common slope of mu against slip (per mm) within the steady-state windows, each window with
    its own level (the velocity's steady state): pooled within-window regression, (slope, s.e.)."""
    sxx = sxy = 0.0
    res = []
    for a, b in windows:
        s, m = s_mm[a:b] - s_mm[a:b].mean(), mu[a:b] - mu[a:b].mean()
        sxx += float(np.dot(s, s))
        sxy += float(np.dot(s, m))
        res.append((s, m))
    if not sxx > 0:
        return math.nan, math.nan
    slope = sxy / sxx
    r = np.concatenate([m - slope * s for s, m in res])
    n_eff = effective_n(r)
    dof = max(n_eff - len(windows) - 1, 1.0)
    se = math.sqrt(float(np.dot(r, r)) / r.size * n_eff / dof / sxx * r.size / n_eff)
    return slope, se


@dataclass
class _Record:
    """The whole-record fit's record: time-binned rows, velocity, runs and the compared bins."""
    t: np.ndarray
    x: np.ndarray
    mu: np.ndarray
    v: np.ndarray
    wsum: np.ndarray           # each bin's share of the time (sum of the rows' time weights)
    width: float               # the bins' width (s)
    decimation: int
    steps: list
    runs: list
    sliding: np.ndarray        # the bins compared
    velocity_method: str


def _binned_record(trial: TrialData, steps: list[Step], stiffness: bool, velocity_method: str,
                   max_points: int, rise_guard_s: float) -> _Record:
    """The record reduced to time bins, its velocity (segments or an estimator), its runs and the
    bins compared (the runs' sliding stretches, without the steps' velocity rise)."""
    t = np.asarray(trial.time_s, dtype=float)
    w_raw, _ = _time_weights(t)
    idx, width = _time_bins(t, max_points)
    wsum = np.bincount(idx, w_raw).astype(float)
    nb = wsum.size
    t, x, mu = (_bin_mean(a, idx, wsum, w_raw) for a in (t, trial.position_um, trial.mu))
    steps = _binned_steps(steps, idx, nb)
    v_est = estimate_velocity(t, x, "local_poly" if velocity_method == "segments" else velocity_method)
    if stiffness or (velocity_method == "segments" and steps):
        v, in_steps = _segment_velocity(t, x, steps, v_est)
        velocity_method = "segments"
    else:
        v = v_est
        _, in_steps = _segment_velocity(t, x, steps, v_est)
    runs = _runs(steps, t.size)
    if not stiffness or not trial.is_load_point:
        # the velocity rise of a step (the rig's controller, 0.2-0.5 s) is not the segments' ideal
        # step: it is not compared, as the per-step method leaves it out (rise_guard_s after t*,
        # half of it before); on generated records it biased A by -1.6 of its sd. A load point's
        # (position_source: load_point) rounding is the spring's, which the model has: compared whole.
        for s_ in steps:
            in_steps[(t > s_.t_s - 0.5 * rise_guard_s) & (t < s_.t_s + rise_guard_s)] = False
    vmed = max(float(np.median(np.abs(v))), 1e-6)
    # compare model and data on the runs' sliding stretches (not on rests or returns)
    sliding = np.zeros(t.size, bool)
    for lo, hi in runs:
        sliding[lo:hi] = in_steps[lo:hi] & (v[lo:hi] > 0.05 * vmed)
    _exclude_break_away(t, x, runs, sliding, 2.0 * rise_guard_s)
    if sliding.sum() < 20:
        runs = [(0, t.size)]
        sliding = v > 0.05 * vmed
    return _Record(t, x, mu, v, wsum, width, int(max(1, round(idx.size / nb))), steps, runs, sliding,
                   velocity_method)


def _exclude_break_away(t: np.ndarray, x: np.ndarray, runs: list[tuple[int, int]], sliding: np.ndarray,
                        settle_s: float) -> None:
    """Leave out of ``sliding`` (in place) each run's start from rest: a run after a rest or a
    return (not from the record's first samples) begins where its constant-velocity stretch is
    detected, while the slider still sticks, then breaks away and catches up with the loop's
    reference (on the simulated rig: at rest for 1 s, then 2 µm/s for 0.5 s at v1 = 1 µm/s). No
    constant velocity drives that (static friction, the controller's catch-up), and comparing it
    biased L by -4 % (6 of its sd) on the README's main job. The run's state is still fitted
    (``v_init_um_s``); the comparison starts ``settle_s`` after the position first moves by three
    times its noise (the noise from the binned position's second differences)."""
    if x.size < 8:
        return
    d2 = np.diff(x, 2)
    # the rms of a white noise's second difference is sqrt(6) times the noise (median of squares: robust)
    noise_um = math.sqrt(float(np.median(d2 * d2)) / 0.4549 / 6.0)
    for lo, hi in runs:
        if lo < 3:
            continue
        moved = np.abs(x[lo:hi] - x[lo]) > 3.0 * noise_um
        if not moved.any():
            continue
        i = lo + int(np.argmax(moved))
        sliding[lo:i + int(np.searchsorted(t[i:hi], t[i] + settle_s))] = False


def _detrending(rec: _Record, detrend: str, L0: float) -> tuple[np.ndarray, float, dict]:
    """(slip since the first compared bin in mm, the trend held (auto) or 0, the report's detrend)."""
    t, x = rec.t, rec.x
    # slip since the first compared sample (mm), for the trend: |dx| summed (returns count as slip)
    s_mm = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)))]) * 1e-3
    s_mm = s_mm - s_mm[int(np.argmax(rec.sliding))]
    trend_fixed = 0.0
    info: dict = {"method": detrend}
    if detrend == "auto":
        wins = steady_windows(t, x, rec.mu, rec.v, rec.steps, rec.runs, L0)
        slope, se = trend_from_windows(s_mm, rec.mu, wins)
        if math.isfinite(slope):
            trend_fixed = slope
            info.update(rate_mu_per_mm=_r(slope), rate_sd_mu_per_mm=_r(se),
                        windows_s=[[_r(t[a], 5), _r(t[b - 1], 5)] for a, b in wins])
        else:
            info.update(rate_mu_per_mm=0.0, note="no steady-state window of 20 µm beyond 5 L: not detrended")
    return s_mm, trend_fixed, info


@dataclass
class _Problem:
    """The whole-record least-squares problem: free parameters, held ones, the model (mu per bin)."""
    pset: ParamSet
    names: list
    fixed: dict
    run_names: list
    v_first: dict
    model: object              # q -> mu per bin
    sw: np.ndarray             # sqrt of each compared bin's share of the time (mean 1)
    F_per_mu: float

    def resid(self, rec: _Record, compared: np.ndarray | None = None, fixed: dict | None = None):
        """The weighted residual on the compared bins (``compared``: another mask, its own time
        weights; ``fixed``: more held values)."""
        sl = rec.sliding if compared is None else compared
        sw = self.sw if compared is None else np.sqrt(rec.wsum[sl] / np.mean(rec.wsum[sl]))
        held = {**self.fixed, **(fixed or {})}
        mu_s = rec.mu[sl]

        def r(free: dict) -> np.ndarray:
            d = (self.model({**held, **free})[sl] - mu_s) * sw
            return np.where(np.isfinite(d), d, 1.0)
        return r


def _problem(rec: _Record, trial: TrialData, stiffness: bool, k_fixed, law: str, detrend: str,
             s_mm: np.ndarray, trend_fixed: float) -> _Problem:
    """Parameters, held values and the forward model of the whole-record fit: each run starts in
    the steady state of a fitted speed (a run from the record's first samples: of its first speed)."""
    t, v = rec.t, rec.v
    F_per_mu = 2.0 * trial.normal_force_N  # the fixture's total friction force per unit mu (two interfaces)
    t_rel = t - t[0]
    ext = (["finite_stiffness"] if stiffness else []) + (["aging_law"] if law == "aging" else [])
    # a run that starts after a rest, a return or a stretch the fit does not compare has an unknown
    # state: fitted; a run from the record's first samples starts in the steady state of its first
    # speed (xlook's and RSFit's convention before a step)
    run_names = [f"v_init_um_s.{j}" for j in range(len(rec.runs))]
    v_first = {nm: max(abs(float(np.median(v[lo:min(hi, lo + 5)]))), 0.01) for nm, (lo, hi) in zip(run_names, rec.runs)}
    held_init = {nm: v_first[nm] for nm, (lo, _) in zip(run_names, rec.runs) if lo < 3}
    names = ["mu0", "A_mu", "B_mu", "L_um"] + (["stiffness_kN_per_m"] if stiffness and k_fixed is None else []) + \
        (["rate_mu_per_mm"] if detrend == "linear" else []) + [nm for nm in run_names if nm not in held_init]
    V_INIT = Param.of("v_init_um_s", PARAMS["v_init_um_s"])
    pset = ParamSet([TREND if nm == "rate_mu_per_mm" else
                     (Param(nm, V_INIT.unit, V_INIT.lo, V_INIT.hi, True) if nm.startswith("v_init") else
                      Param.of(nm, PARAMS[nm])) for nm in names])
    fixed = {"stiffness_kN_per_m": float(k_fixed) * F_per_mu * 1e3} if stiffness and k_fixed is not None else {}
    fixed.update(held_init)
    # the load point (stiffness) moves with the segment velocity, piecewise constant per interval
    x_lp = np.concatenate([[rec.x[0]], rec.x[0] + np.cumsum(v[:-1] * np.diff(t))]) if stiffness else rec.x
    N_N = trial.normal_force_N

    def model(q: dict) -> np.ndarray:
        fm = FrictionModel(extensions=ext, params={k_: q[k_] for k_ in ("mu0", "A_mu", "B_mu", "L_um",
                                                                        "stiffness_kN_per_m") if k_ in q})
        out = np.full(t.size, np.nan)
        for j, (lo, hi) in enumerate(rec.runs):
            out[lo:hi] = predict_force(fm, t_rel[lo:hi], x_lp[lo:hi], v[lo:hi], None, N_N,
                                       q[run_names[j]]) / F_per_mu
        return out + q.get("rate_mu_per_mm", trend_fixed) * s_mm

    # statistics weigh time, not rows: each compared bin by its share of the time (mean 1)
    sw = np.sqrt(rec.wsum[rec.sliding] / np.mean(rec.wsum[rec.sliding]))
    return _Problem(pset, names, fixed, run_names, v_first, model, sw, F_per_mu)


FIT_OPTS = dict(max_nfev=200, diff_step=None, xtol=1e-8, ftol=1e-8, x_scale="jac")


def _least_squares(rec: _Record, prob: _Problem, init: dict, stiffness: bool):
    """The fit from a semi-log regression's steady state (and per-step results if given), several L."""
    resid = prob.resid(rec)
    mu, v, sl = rec.mu, rec.v, rec.sliding
    lv = np.log(np.maximum(v[sl], 1e-6) / V0_UM_S)
    c = np.polyfit(lv, mu[sl], 1) if np.ptp(lv) > 0.1 else (0.0, float(np.mean(mu[sl])))
    A0 = float(init.get("A_mu", 0.005 if stiffness else 0.002))
    A0 = A0 if math.isfinite(A0) and A0 > 0 else 0.002
    B0 = float(init.get("B_mu", A0 - c[0]))
    B0 = B0 if math.isfinite(B0) else A0
    k0 = float(init.get("k_mu_per_um", 0.005)) * prob.F_per_mu * 1e3

    def start(L_: float) -> dict:
        return {"mu0": float(c[1]), "A_mu": A0, "B_mu": B0, "L_um": max(L_, 0.5), "stiffness_kN_per_m": k0,
                "rate_mu_per_mm": 0.0, **prob.v_first}

    Ls = [float(init["L_um"])] if "L_um" in init and math.isfinite(init["L_um"]) else []
    opts = FIT_OPTS
    fit = least_squares_fit(resid, prob.pset, [start(L_) for L_ in (Ls or [5.0, 20.0, 80.0])], **opts)
    if Ls and (fit is None or not fit.success):
        more = least_squares_fit(resid, prob.pset, [start(Ls[0] / 3.0), start(Ls[0] * 3.0)], **opts)
        if more is not None and (fit is None or more.cost < fit.cost):
            fit = more
    return fit


def _whole_record_uncertainty(rec: _Record, prob: _Problem, fit, method: str, n_draws: int, seed: int,
                              profile: bool, progress, jackknife: bool = True,
                              rigid: tuple | None = None) -> tuple[dict, float]:
    """(params_sd, intervals, correlation and cov of :mod:`rig.fitting.stats`; the residual's n_eff).
    Jacobian errors: each parameter's variance inflated by n / n_eff of its score in time (as
    diagnose's); with ``profile``, L's interval from its profile likelihood, inflated alike."""
    from rig.fitting.stats import block_bootstrap, effective_n_time, jacobian_summary, mcmc, profile_interval, \
        time_cell_s

    resid = prob.resid(rec)
    r = fit.residuals
    n = r.size
    t_sl = rec.t[rec.sliding]
    n_eff = effective_n_time(t_sl, r / prob.sw, prob.sw ** 2, time_cell_s(t_sl))
    unc = jacobian_summary(prob.pset, fit, t_sl)
    if method == "jacobian" and profile:
        # L's interval from its profile likelihood (the a-b-L valley is flat and skewed in L): its
        # shape from the white-noise likelihood, its width inflated as L's sd is
        zl = fit.extra["z"][prob.names.index("L_um")]
        ratio = unc["sd_ratio"].get("L_um", 1.0)
        ratio = ratio if math.isfinite(ratio) and ratio > 0 else 1.0
        sd_zl = unc["params_sd"]["L_um"] / max(math.exp(zl), 1e-12) / ratio
        piv = profile_interval(resid, prob.pset, fit, "L_um", float(n), sd_zl)
        if piv is not None:
            lo_z, hi_z = math.log(piv[0]), math.log(piv[1])
            unc["intervals"]["L_um"] = [math.exp(zl - (zl - lo_z) * ratio), math.exp(zl + (hi_z - zl) * ratio)]
            unc["profile"] = ["L_um"]
    if method == "jacobian" and jackknife:
        _jackknife_floor(unc, _run_jackknife(rec, prob, fit), {**prob.fixed, **fit.params})
        if rigid is not None:  # (trial, k_fixed, law, detrend, s_mm, trend_fixed) of a rigid record's problem
            _rise_floor(rec, prob, fit, lambda r_: _problem(r_, rigid[0], False, *rigid[1:]), unc)
    if method == "bootstrap":
        m_hat = prob.model({**prob.fixed, **fit.params})[rec.sliding]

        def residual_for(e):
            return lambda free: np.where(np.isfinite(rr := ((prob.model({**prob.fixed, **free})[rec.sliding] - m_hat)
                                                            * prob.sw + e)), rr, 1.0)

        unc = block_bootstrap(residual_for, prob.pset, fit, n_draws, seed=seed, progress=progress)
    elif method == "mcmc":
        z_cov = np.linalg.pinv(fit.jac.T @ fit.jac) * float(np.dot(r, r)) / max(n - len(prob.names), 1)
        unc = mcmc(resid, prob.pset, fit, n_draws, n_eff, seed=seed, cov_z=z_cov, progress=progress)
    return unc, n_eff


JACKKNIFE_GROUPS = 10  # at most this many refits


def _run_jackknife(rec: _Record, prob: _Problem, fit) -> dict:
    """Leave-one-run-out jackknife (each run: a step from steady sliding, in the paper's protocol):
    the fit refitted without each run's compared bins (its starting state held at the full fit's),
    ``{"runs", "groups": n, "sd": {name: sqrt((n-1)/n sum (p_i - mean)^2)}}`` (more than
    JACKKNIFE_GROUPS runs are left out in n contiguous groups); ``{}`` with fewer than 3 runs.
    It sees what the residual does not: an error of the model's input that differs from run to run
    (the closed loop's velocity rise against the segments' ideal step, the fixture's slip)."""

    if len(rec.runs) < 3:
        return {}
    est = []
    # more runs than JACKKNIFE_GROUPS: left out in contiguous groups (the delete-a-group jackknife)
    for grp in np.array_split(np.arange(len(rec.runs)), min(len(rec.runs), JACKKNIFE_GROUPS)):
        keep = rec.sliding.copy()
        for j in grp:
            keep[rec.runs[j][0]:rec.runs[j][1]] = False
        if keep.sum() < 20 or keep.sum() == rec.sliding.sum():
            return {}
        held = {prob.run_names[j]: fit.params[prob.run_names[j]] for j in grp if prob.run_names[j] in fit.params}
        pset = ParamSet([p for p in prob.pset.params if p.name not in held])
        f = least_squares_fit(prob.resid(rec, keep, held), pset,
                              [{k_: v_ for k_, v_ in fit.params.items() if k_ not in held}], **FIT_OPTS)
        if f is None:
            return {}
        est.append(f.params)
    n = len(est)
    names = [k_ for k_ in fit.params if not k_.startswith("v_init") and all(k_ in e for e in est)]
    return {"runs": len(rec.runs), "groups": n, "sd": {k_: float(math.sqrt((n - 1) / n * np.sum(np.square(
        np.array([e[k_] for e in est]) - np.mean([e[k_] for e in est]))))) for k_ in names}}


def _raise_to(unc: dict, floor: dict, values: dict) -> list[str]:
    """Each parameter's error raised to ``floor[name]`` where that is larger: ``params_sd``, the
    interval (about the value, in ln for a positive slip distance) and the covariance's row and
    column widen by the same ratio. Returns the names raised."""
    raised = []
    names = unc["correlation"]["names"]
    for k_, s_fl in floor.items():
        s = unc["params_sd"].get(k_)
        if s is None or not math.isfinite(s) or not s_fl > s:
            continue
        f = s_fl / s if s > 0 else 1.0
        v = values[k_]
        lo, hi = unc["intervals"][k_]
        if k_.endswith("_um") and v > 0 and lo > 0:
            unc["intervals"][k_] = [v * (lo / v) ** f, v * (hi / v) ** f]
        else:
            unc["intervals"][k_] = [v - (v - lo) * f, v + (hi - v) * f]
        unc["params_sd"][k_] = s_fl
        if k_ in names:
            i = names.index(k_)
            unc["cov"][i, :] *= f
            unc["cov"][:, i] *= f
        raised.append(k_)
    return raised


def _jackknife_floor(unc: dict, jk: dict, values: dict) -> None:
    """Each parameter's error never below the jackknife's over runs (:func:`_run_jackknife`), as
    diagnose's never below its split-half spread (:func:`_raise_to`). On the simulated rig the
    Jacobian's alone covered L in 30-55 % of 20 trials (docs/validation.md)."""
    if not jk:
        return
    raised = _raise_to(unc, jk["sd"], values)
    unc["jackknife"] = {"runs": jk["runs"], "groups": jk["groups"], "sd": {k_: _r(v_) for k_, v_ in jk["sd"].items()}, "raised": raised}
    unc["errors"] = unc.get("errors", "") + "; never below the leave-one-run-out jackknife's"


# the stretch after each step (s) driven by the estimated velocity in the rise floor's second fit
RISE_FLOOR_S = 1.0


def _rise_floor(rec: _Record, prob: _Problem, fit, remake, unc: dict) -> None:
    """Each error never below the fit's change when the model is driven, from a quarter second
    before each step to RISE_FLOOR_S after it, by the velocity the record gives (the local
    polynomial of :func:`rig.kinematics.estimate_velocity`) instead of the segments' ideal step:
    an error in the model's input shared by every step (the closed loop's rise and overshoot,
    40 um/s2 with the feed-forwards on the README's main job), which neither the residual nor the
    jackknife over steps sees. The interface's true velocity there gave A -0.2 % where the
    segments gave +2.8 % (docs/validation.md, "Coverage"); the two inputs bracket it, and the
    disagreement of the two fits is the error floor, as diagnose's kinematics floor is.
    ``remake(rec)``: the problem on another record (its velocity)."""
    from dataclasses import replace

    if rec.velocity_method != "segments" or not rec.steps:
        return
    v_est = estimate_velocity(rec.t, rec.x, "local_poly")
    near = np.zeros(rec.t.size, bool)
    for s_ in rec.steps:
        near |= (rec.t >= s_.t_s - 0.25) & (rec.t < s_.t_s + RISE_FLOOR_S)
    rec2 = replace(rec, v=np.where(near, v_est, rec.v))
    prob2 = remake(rec2)
    f2 = least_squares_fit(prob2.resid(rec2), prob2.pset, [dict(fit.params)], **FIT_OPTS)
    if f2 is None or not f2.success:
        return
    floor = {k_: abs(float(f2.params[k_]) - float(fit.params[k_])) for k_ in ("A_mu", "B_mu", "L_um")
             if k_ in f2.params and k_ in fit.params and math.isfinite(f2.params[k_])}
    raised = _raise_to(unc, floor, {**prob.fixed, **fit.params})
    unc["velocity_rise"] = {"window_s": RISE_FLOOR_S, "sd": {k_: _r(v_) for k_, v_ in floor.items()}, "raised": raised}
    unc["errors"] = unc.get("errors", "") + "; never below the change when the steps are driven by the estimated velocity"


def _reported(prob: _Problem, fit, unc: dict, stiffness: bool, detrend: str) -> dict:
    """params, params_sd, intervals, correlation, err, err_corr in the report's units (k in mu per
    µm and kN/m) and the friction lab's vocabulary (rsf_vocabulary); ``_sd`` and ``_q`` for the rest."""
    F_per_mu, fixed = prob.F_per_mu, prob.fixed
    q = {**fixed, **fit.params}
    sd = dict(unc["params_sd"])
    iv = {k_: list(v_) for k_, v_ in unc["intervals"].items()}
    if "stiffness_kN_per_m" in fixed:
        sd["stiffness_kN_per_m"] = 0.0
        iv["stiffness_kN_per_m"] = [fixed["stiffness_kN_per_m"]] * 2
    order = ["mu0", "A_mu", "B_mu", "L_um"] + (["k_mu_per_um", "stiffness_kN_per_m"] if stiffness else []) + \
        (["rate_mu_per_mm"] if detrend == "linear" else [])
    val = dict(q)
    jac_sd = {nm: fit.stderr.get(nm, 0.0) for nm in q}
    if stiffness:
        val["k_mu_per_um"] = q["stiffness_kN_per_m"] * 1e-3 / F_per_mu
        for d in (sd, jac_sd):
            d["k_mu_per_um"] = d.get("stiffness_kN_per_m", 0.0) * 1e-3 / F_per_mu
        iv["k_mu_per_um"] = [b_ * 1e-3 / F_per_mu for b_ in iv["stiffness_kN_per_m"]]
    params = {nm: _r(val[nm]) for nm in order}
    params_sd = {nm: _r(sd.get(nm, 0.0)) for nm in order}
    corr = unc["correlation"]
    keep = [i for i, nm in enumerate(corr["names"]) if not nm.startswith("v_init")]
    correlation = {"names": [corr["names"][i] for i in keep],
                   "matrix": [[corr["matrix"][i][j] for j in keep] for i in keep]}
    # the field's vocabulary (a, b, Dc_um, a_minus_b, k_per_um): rig.model.spec.rsf_vocabulary
    rsf = rsf_vocabulary(val, F_per_mu)
    cov, names_c = unc["cov"], corr["names"]
    ia, ib = names_c.index("A_mu"), names_c.index("B_mu")
    amb_sd = math.sqrt(max(cov[ia, ia] + cov[ib, ib] - 2 * cov[ia, ib], 0.0))
    rsf_sd = {**rsf_vocabulary(sd, F_per_mu), "a_minus_b": amb_sd}
    rsf_iv = {RSF_NAMES[k_]: iv[k_] for k_ in RSF_NAMES if k_ in iv}
    if "k_mu_per_um" in iv:
        rsf_iv["k_per_um"] = iv["k_mu_per_um"]
    params.update({k_: _r(v_) for k_, v_ in rsf.items()})
    params_sd.update({k_: _r(v_) for k_, v_ in rsf_sd.items() if k_ in rsf})
    intervals = {nm: [_r(iv[nm][0]), _r(iv[nm][1])] for nm in order if nm in iv}
    intervals.update({k_: [_r(v_[0]), _r(v_[1])] for k_, v_ in rsf_iv.items()})
    return {"params": params, "params_sd": params_sd, "intervals": intervals, "correlation": correlation,
            "err": {nm: _r(jac_sd.get(nm, 0.0)) for nm in order}, "err_corr": {nm: params_sd[nm] for nm in order},
            "_sd": sd, "_q": q}


def _checked_options(law: str, trend: bool, detrend: str) -> str:
    """The detrend method (``trend`` asks for ``linear``); ValueError for an unknown law or detrend."""
    if law not in LAWS:
        raise ValueError(f"unknown state law {law!r} (slip, aging)")
    if trend and detrend == "none":
        detrend = "linear"
    if detrend not in DETRENDS:
        raise ValueError(f"unknown detrend {detrend!r} (none, linear, auto)")
    return detrend


def _held_stiffness(trial: TrialData, stiffness: bool, k_fixed: float | None) -> tuple[float | None, str | None]:
    """(k held in mu per µm or None, its source: fitted, metadata or given): a known machine
    stiffness (measured-data.md: machine_stiffness_kN_per_m) is held."""
    if not stiffness:
        return k_fixed, None
    k_meta = parse_number(str(trial.metadata.get("machine_stiffness_kN_per_m", "")))
    if k_fixed is None and k_meta is not None and k_meta > 0:
        k_fixed = k_meta * 1e-3 / (2.0 * trial.normal_force_N)
    return k_fixed, ("fitted" if k_fixed is None else ("metadata" if k_meta is not None and k_meta > 0 else "given"))


# the whole-record fit's most time bins (:func:`_time_bins`; the main job's 650 s at 25 Hz: 2-row bins)
WHOLE_RECORD_MAX_POINTS = 15000


def fit_whole_record(trial: TrialData, steps: list[Step] | None = None, *, stiffness: bool = False,
                     velocity_method: str = "segments", max_points: int = WHOLE_RECORD_MAX_POINTS, trend: bool = False,
                     init: dict | None = None, k_fixed: float | None = None, law: str = "slip",
                     detrend: str = "none", uncertainty: str = "jacobian", seed: int = 0,
                     progress=None, rise_guard_s: float = 0.5, profile: bool = False,
                     jackknife: bool = True) -> WholeRecordFit:
    """Fit mu0, A, B, L (and the machine stiffness ``k``, and a linear trend in slip) to the
    whole record by least squares (:mod:`rig.fitting`, trust region), with honest errors.

    * **Time, not rows.** The record is first reduced to means over uniform bins in time
      (:func:`_time_bins`), so a part logged ten times faster counts as long as it lasts.
    * **Runs.** The steps' constant-velocity stretches that join form runs (:func:`_runs`); each
      run starts after a rest, a return or the record's start, where the state is not known: the
      model starts each run in the steady state of a fitted speed ``v_init_um_s`` (a nuisance per
      run), rather than guessing the history (the simulated rig's trials start after holds and
      returns at 100 µm/s: guessing it biased A by -19 % and L by +13 %).
    * **Law.** ``slip`` (Ruina, eq. 6) or ``aging`` (Dieterich): :mod:`rig.model.friction`.
    * **Velocity.** ``segments`` (default: piecewise constant, the line-fit slopes between the
      effective steps: free of the noise an estimator passes into ``A ln v``, which biases A low
      as an errors-in-variables problem), ``local_poly`` or ``paper`` (the estimators). With
      stiffness, the position is the load point, its velocity the segments', and the interface's
      follows from the spring (:func:`rig.model.loading.stiff_series`); ``k_fixed`` (friction
      units per µm) holds it at a known value.
    * **Detrend.** ``none``; ``linear``: ``mu += rate_mu_per_mm * s`` with ``s`` the slip since
      the first compared sample, fitted; ``auto``: the rate from the steady-state windows
      (:func:`steady_windows`, :func:`trend_from_windows`), then held.
    * **Uncertainty** (:mod:`rig.fitting.stats`): ``jacobian`` (default; with ``profile``, L's
      interval from its profile likelihood), ``bootstrap:N`` (block bootstrap of the residuals in
      time), ``mcmc:N`` (emcee). ``params_sd``, ``intervals``
      (68 %) and ``correlation``; ``err_corr`` is ``params_sd`` (kept for older readers) and
      ``err`` the plain Jacobian's. Jacobian errors are never below the leave-one-run-out
      jackknife's; ``jackknife=False`` skips its refits where only the values are wanted (a
      starting point: diagnose's prior).
    """
    from rig.fitting.stats import information_criterion, parse_uncertainty

    detrend = _checked_options(law, trend, detrend)
    method, n_draws = parse_uncertainty(uncertainty)
    max_points = min(max_points, 8000) if stiffness else max_points
    rec = _binned_record(trial, detect_steps(trial) if steps is None else steps, stiffness, velocity_method,
                         max_points, rise_guard_s)
    F_per_mu = 2.0 * trial.normal_force_N
    k_fixed, k_source = _held_stiffness(trial, stiffness, k_fixed)
    L0 = float((init or {}).get("L_um", 20.0))
    s_mm, trend_fixed, detrend_info = _detrending(rec, detrend, L0 if math.isfinite(L0) and L0 > 0 else 20.0)
    prob = _problem(rec, trial, stiffness, k_fixed, law, detrend, s_mm, trend_fixed)
    t0 = time.perf_counter()
    fit = _least_squares(rec, prob, dict(init or {}), stiffness)
    if fit is None:
        return WholeRecordFit({"ok": False, "reason": "least squares failed"})
    unc, n_eff = _whole_record_uncertainty(rec, prob, fit, method, n_draws, seed, profile, progress, jackknife,
                                           None if stiffness else (trial, k_fixed, law, detrend, s_mm, trend_fixed))
    rep = _reported(prob, fit, unc, stiffness, detrend)
    sd, q = rep.pop("_sd"), rep.pop("_q")
    r = fit.residuals
    n = r.size
    ssr = float(np.dot(r, r))
    n_par = len(prob.names)
    out = {"ok": fit.success, "model": "rate_state" + ("+finite_stiffness" if stiffness else "")
           + ("+aging_law" if law == "aging" else ""), "law": law, **rep,
           "uncertainty": {k_: v_ for k_, v_ in unc.items() if k_ not in ("params_sd", "intervals", "correlation", "cov",
                                                                          "sd_ratio")},
           "rho1": _r(float(np.corrcoef(r[:-1], r[1:])[0, 1]) if n > 3 else 0.0), "n_eff": _r(n_eff, 4), "bin_s": _r(rec.width, 4),
           "information_criterion": _r(information_criterion(ssr, n, n_eff, n_par)),
           "n_params": n_par, "runs": len(rec.runs),
           "v_init_um_s": [_r(q[nm], 4) for nm in prob.run_names],
           "rms_mu": _r(math.sqrt(ssr / n)), "rms_N": _r(math.sqrt(ssr / n) * F_per_mu),
           "n_points": int(n), "decimation": rec.decimation, "nfev": int(fit.nfev),
           "fit_time_s": _r(time.perf_counter() - t0, 3),
           "velocity": "segments (load point)" if stiffness else rec.velocity_method, "detrend": detrend_info}
    if stiffness:
        out["stiffness_source"] = k_source
    if detrend == "linear":
        detrend_info.update(rate_mu_per_mm=rep["params"]["rate_mu_per_mm"],
                            rate_sd_mu_per_mm=rep["params_sd"]["rate_mu_per_mm"])
    kcr, skcr = k_cr_table2(q["A_mu"], sd["A_mu"], q["B_mu"], sd["B_mu"], q["L_um"], sd["L_um"], trial.normal_force_N)
    out.update(k_cr_kN_per_m=_r(kcr), k_cr_err_kN_per_m=_r(skcr))
    return WholeRecordFit(out, params=dict(q), ssr=ssr, n_eff=n_eff,
                          curve=(rec.t, prob.model(q), rec.mu, rec.sliding,
                                 q.get("rate_mu_per_mm", trend_fixed) * s_mm))


@dataclass
class LawComparison:
    """Both state laws' whole-record fits compared (:func:`compare_laws`), unrounded; :meth:`report`
    is ``laws.comparison`` of rig.identify/1."""
    preferred_law: str
    n_eff: float = math.nan
    bic: dict = field(default_factory=dict)
    delta_bic: float = math.nan
    reason: str = ""

    def report(self) -> dict:
        if self.reason:
            return {"preferred_law": self.preferred_law, "reason": self.reason}
        return {"criterion": "BIC on the effective sample size", "n_eff": _r(self.n_eff, 4),
                "bic": {k: _r(v) for k, v in self.bic.items()}, "delta_bic": _r(self.delta_bic),
                "preferred_law": self.preferred_law}


def compare_laws(fits: dict[str, WholeRecordFit], margin: float = 6.0) -> LawComparison:
    """Both laws side by side (xlook's qi.r and qi.d): the information criterion of each on one
    effective sample size (the better fit's: its residual is the closest to noise), and the law
    the record prefers: the one lower by more than ``margin`` (Kass & Raftery 1995: 6 is strong
    evidence), else ``undecided``. From the fits' unrounded sums of squares and n_eff."""
    ok = {k: w for k, w in fits.items() if w.params}
    if len(ok) < 2:
        return LawComparison("undecided", reason="a fit failed")
    from rig.fitting.stats import information_criterion

    best = min(ok, key=lambda k: ok[k].ssr / max(ok[k].n_points, 1))
    n_eff = ok[best].n_eff
    ic = {k: information_criterion(w.ssr, w.n_points, n_eff, w.n_params) for k, w in ok.items()}
    lo = min(ic, key=ic.get)
    other = [k for k in ic if k != lo][0]
    d = ic[other] - ic[lo]
    return LawComparison(lo if d > margin else "undecided", n_eff, ic, d)


# ---------------------------------------------------------------------------
# The whole identification
# ---------------------------------------------------------------------------
#: the fewest samples of a record that any friction analysis takes (identify, stribeck, heal, diagnose;
#: the CLI refuses a shorter file at once, exit 2)
MIN_RECORD_SAMPLES = 20
MAX_ABS_FORCE_N = 1e6


def check_analysable(trial: TrialData, what: str = "analyse") -> None:
    """One clear ValueError (naming the file) for a record no friction analysis can use: too few
    samples, a force beyond any load cell, time that is not in seconds, a position that never
    moves. Shared by identify and diagnose."""
    src = trial.source or "trial"
    n = len(trial)
    if n < MIN_RECORD_SAMPLES:
        raise ValueError(f"{src}: too few samples ({n}) to {what} (at least {MIN_RECORD_SAMPLES})")
    F = np.asarray(trial.friction_N, dtype=float)
    big = np.flatnonzero(~(np.abs(F) < MAX_ABS_FORCE_N))
    if big.size:
        raise ValueError(f"{src}: friction_N = {F[big[0]]:.3g} N in data row {big[0] + 1}: beyond any load cell "
                         f"(|F| < {MAX_ABS_FORCE_N:g} N); not a friction force")
    t = np.asarray(trial.time_s, dtype=float)
    dt = float(np.median(np.diff(t)))
    if dt > 60.0:
        unit = "nanoseconds" if dt > 1e6 else ("milliseconds" if dt > 1e1 else "another unit")
        raise ValueError(f"{src}: time_s has a median spacing of {dt:.3g} s (a {1 / dt:.3g} Hz record?): "
                         f"time looks like {unit}; time_s must be in seconds (measured-data.md)")
    x = np.asarray(trial.position_um, dtype=float)
    if not float(np.ptp(x)) > 0.5:
        raise ValueError(f"{src}: position_um does not move (range {float(np.ptp(x)):.3g} um): no sliding to {what}")


MAX_STEP_SAMPLES = 1_000_000
STEP_TARGET_SAMPLES = 100_000


def decimated(trial: TrialData, max_samples: int = MAX_STEP_SAMPLES, target: int = STEP_TARGET_SAMPLES) -> TrialData:
    """A record of more than ``max_samples`` as block means of k samples (about ``target`` left;
    1 h at 1 kHz: k = 37, 27 Hz); shorter records unchanged. Step detection and the per-step
    fits cost per sample: a one-hour 1 kHz sawtooth (720 steps) took over 5 minutes; block means
    keep the friction information (noise averaged) at a rate still far above the transients'
    (L / v >= 0.1 s)."""
    n = len(trial)
    if n <= max_samples:
        return trial
    k = int(math.ceil(n / target))
    m = (n // k) * k

    def bm(a):
        return None if a is None else np.asarray(a, dtype=float)[:m].reshape(-1, k).mean(axis=1)

    return TrialData(time_s=bm(trial.time_s), position_um=bm(trial.position_um), friction_N=bm(trial.friction_N),
                     normal_1_N=bm(trial.normal_1_N), normal_2_N=bm(trial.normal_2_N),
                     position_ref_um=bm(trial.position_ref_um), valve_cmd=None, extra={},
                     metadata=dict(trial.metadata), events=list(trial.events), source=trial.source,
                     warnings=list(trial.warnings) + [f"{n} samples: identified on block means of {k}"])


@dataclass
class WholeRecordFit:
    """One whole-record fit (:func:`fit_whole_record`): its JSON (``whole_record`` of rig.identify/1, as
    the fit and its uncertainty (rig.fitting) report it: :meth:`report`) and the unrounded numbers the
    analyses start from (diagnose's prior, the law comparison, the figure)."""
    reported: dict
    params: dict = field(default_factory=dict)   # fitted and held values, unrounded (internal units); {} if failed
    ssr: float = math.nan                        # sum of squared (time-weighted) residuals, in mu^2
    n_eff: float = math.nan                      # the residual's effective sample size
    curve: tuple | None = None                   # (t, model mu, measured mu, sliding mask, trend) of the bins

    @property
    def ok(self) -> bool:
        return bool(self.reported.get("ok", True))

    @property
    def model(self) -> str:
        return self.reported.get("model", "")

    @property
    def n_points(self) -> int:
        return int(self.reported.get("n_points", 0))

    @property
    def n_params(self) -> int:
        return int(self.reported.get("n_params", 0))

    def report(self) -> dict:
        return dict(self.reported)


@dataclass
class Identification:
    """What ``rig identify`` found, typed and unrounded: the steps (per trial), their mean and s.e.
    over steps (one trial) or trials (several; ``per_trial``: each trial's means), the whole-record fit
    of each trial (and with ``law="both"`` both laws' and their comparison), and the warnings judged on
    these values. :meth:`report` is the JSON (rig.identify/1), rounded once, when it is made."""
    results: list[list[StepResult]]
    trials: list[TrialData]
    fits: list[WholeRecordFit]
    laws: list[dict[str, WholeRecordFit]] = field(default_factory=list)   # per trial {law: fit} with --law both
    comparisons: list[LawComparison] = field(default_factory=list)
    mean: dict = field(default_factory=dict)
    sem: dict = field(default_factory=dict)
    sem_over: str = "steps"
    per_trial: list[TrialMeans] = field(default_factory=list)
    names: list[str] | None = None        # the files' names as given
    velocity_method: str = "local_poly"
    law: str | None = None                # the whole-record fits' law (slip, aging, both); None: no fit
    stiffness_by_rule: bool = False       # the stiffness was chosen by the load-point rule
    warnings: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def steps(self) -> list[StepResult]:
        return [r for g in self.results for r in g]

    @property
    def n_steps(self) -> int:
        """The accepted steps."""
        return sum(1 for r in self.steps if r.ok)

    @property
    def rejected(self) -> list[StepResult]:
        return [r for r in self.steps if not r.ok]

    @property
    def data(self):
        """The report's ``data``: the files' names (one name for one file), else the trial's source."""
        names = self.names
        return names if names and len(names) > 1 else (names[0] if names else self.trials[0].source)

    @property
    def preferred_law(self) -> str:
        """With ``law="both"``: the law every trial prefers, else ``undecided``."""
        prefs = {c.preferred_law for c in self.comparisons}
        return prefs.pop() if len(prefs) == 1 else "undecided"

    def report(self) -> dict:
        """The rig.identify/1 JSON: the numbers rounded here (6 significant figures,
        :func:`rig.analysis.report.rounded`)."""
        report = _report(self)
        if self.law is not None:  # the whole-record fits
            wr = [w.report() for w in self.fits]
            report["whole_record"] = wr[0] if len(wr) == 1 else wr
            report["law"] = self.law
            if self.law == "both":
                both = [{**{lw: f.report() for lw, f in fits.items()}, "comparison": c.report()}
                        for fits, c in zip(self.laws, self.comparisons)]
                report["laws"] = both[0] if len(both) == 1 else both
                report["preferred_law"] = self.preferred_law
        report["warnings"] = rounded_warnings(self.warnings)
        return report


def identify_trials(trials: list[TrialData], *, use_events: bool = True, velocity_method: str = "local_poly",
                    whole_velocity: str = "segments",
                    whole_record: bool = True, stiffness: bool | None = None, min_ratio: float = 1.25,
                    directions: str = "both", rise_guard_s: float = 0.5, window_points: int = WINDOW_POINTS,
                    names: list[str] | None = None, law: str = "slip", detrend: str = "none",
                    uncertainty: str = "jacobian", seed: int = 0, progress=None) -> Identification:
    """Identify every trial; mean and SEM over steps (one trial) or trials (several).

    The whole-record fit (:func:`fit_whole_record`) with the state ``law`` (``slip``, ``aging``
    or ``both``: both fits side by side, :func:`compare_laws`), ``detrend`` and ``uncertainty``."""
    if law not in LAWS + ("both",):
        raise ValueError(f"--law {law}: expected slip, aging or both")
    if detrend not in DETRENDS:
        raise ValueError(f"--detrend {detrend}: expected none, linear or auto")
    from rig.fitting.stats import parse_uncertainty

    parse_uncertainty(uncertainty)
    laws = LAWS if law == "both" else (law,)
    comparisons: list[LawComparison] = []
    per_law: list[dict[str, WholeRecordFit]] = []
    groups: list[list[StepResult]] = []
    wholes: list[WholeRecordFit] = []
    trials = [decimated(tr) for tr in trials]
    for ti, tr in enumerate(trials):
        check_analysable(tr, "identify")
        steps = detect_steps(tr, use_events=use_events, min_ratio=min_ratio)
        res = _fit_steps(tr, ti, steps, directions, rise_guard_s, window_points)
        groups.append(res)
        if whole_record:
            good = [r for r in res if r.ok]
            init = {nm: float(np.median([getattr(r, nm) for r in good])) for nm in ("A_mu", "B_mu", "L_um")} \
                if good else {}
            stiff = (tr.is_load_point or _known_stiffness(tr)) if stiffness is None else stiffness
            fits = {lw: fit_whole_record(tr, steps, stiffness=stiff, velocity_method=whole_velocity, init=init,
                                         law=lw, detrend=detrend, uncertainty=uncertainty, seed=seed,
                                         progress=progress, profile=True) for lw in laws}
            if law == "both":
                comparisons.append(compare_laws(fits))
                per_law.append(fits)
                wholes.append(fits["slip"])
            else:
                wholes.append(fits[law])
    mean, sem, over, per_trial = summarize(groups, trials[0].normal_force_N)
    idn = Identification(groups, trials, wholes, per_law, comparisons, mean, sem, over, per_trial, names=names,
                         velocity_method=velocity_method, law=law if whole_record else None,
                         stiffness_by_rule=whole_record and stiffness is None)
    idn.notes = _notes(trials, idn.stiffness_by_rule)
    idn.warnings = result_warnings(idn)
    return idn


def _fit_steps(tr: TrialData, ti: int, steps: list[Step], directions: str, rise_guard_s: float,
               window_points: int) -> list[StepResult]:
    """Eqs. (10)-(12) on each step of trial number ``ti`` in the wanted direction(s)."""
    t = np.asarray(tr.time_s, dtype=float)
    x = np.asarray(tr.position_um, dtype=float)
    mu = np.asarray(tr.mu, dtype=float)
    res = []
    for s in steps:
        if directions != "both" and s.direction != directions:
            continue
        r = fit_step(t, x, mu, s, rise_guard_s=rise_guard_s, window_points=window_points)
        r.trial = ti
        res.append(r)
    return res


def _report(idn: Identification) -> dict:
    """The per-step part of the ``rig.identify/1`` report, rounded: the steps, mean and s.e. over steps
    (one trial) or trials (several), the rejected steps and, with several trials, each trial's means."""
    trials = idn.trials
    mean = {k_: _r(v) for k_, v in idn.mean.items()}
    sem = {k_: _r(v) for k_, v in idn.sem.items()}
    # the field's vocabulary beside the spec's names (rig.model.spec.rsf_vocabulary), of the rounded means
    mean.update({k_: _r(v_) for k_, v_ in rsf_vocabulary(mean).items()})
    sem.update({k_: v_ for k_, v_ in ((RSF_NAMES[k], sem.get(k)) for k in RSF_NAMES)})
    report = {
        "schema": SCHEMA,
        "data": idn.data,
        "steps": [r.report() for r in idn.steps],
        "mean": mean,
        "sem": sem,
        "sem_over": idn.sem_over,
        "n_steps": idn.n_steps,
        "n_trials": len(trials),
        "normal_force_N": trials[0].normal_force_N,
        "velocity_method": idn.velocity_method,
        "step_source": sorted({r.step.source for r in idn.steps}),
        "k_cr_note": "eq. (13), k_cr = (B_mu - A_mu) N / L with N the nominal per-rider normal force (Table 2 "
                     "convention); the moving test piece sees twice this (total friction 2 N mu): see rig stability",
    }
    report["rejected_steps"] = [{"trial": r.trial, "t_s": _r(r.step.t_s), "reason": r.reason} for r in idn.rejected]
    report["notes"] = list(idn.notes)
    if len(trials) > 1:
        report["per_trial"] = [row.report() for row in idn.per_trial]
    return report


def _notes(trials: list[TrialData], stiffness_by_rule: bool) -> list[str]:
    """The notes on load-point records: the per-step method's rigid-machine bias, the stiffness fitted."""
    lp = [tr.is_load_point for tr in trials]
    notes = []
    if any(lp):
        notes.append(RIGID_NOTE)
    if stiffness_by_rule and any(lp):
        notes.append("position_source: load_point, so the whole-record fit includes the machine stiffness "
                     "(--no-stiffness to fit without)")
    return notes


def step_where(t_s: float, trial: int, n_trials: int) -> str:
    """The ``where`` of a step's warnings (its time as the report gives it, 4 decimals)."""
    return f"step at t = {round(t_s, 4):g} s" + (f" (trial {trial})" if n_trials > 1 else "")


def result_warnings(idn: Identification) -> list[dict]:
    """Parameters that hit a fit bound or are not physical (:mod:`rig.model.checks`): the accepted
    steps', the mean's and each whole-record fit's (the last judged on its report)."""
    from rig.model.checks import check_params

    n_trials = len(idn.trials)
    out = []
    for r in idn.steps:
        if r.ok:
            out += check_params({"A_mu": r.A_mu, "B_mu": r.B_mu, "L_um": r.L_um}, where=r.where(n_trials))
    out += check_params({k: idn.mean.get(k) for k in ("A_mu", "B_mu", "L_um", "k_cr_kN_per_m")},
                        idn.sem, where=f"mean over {idn.sem_over}")
    if idn.law is None:
        return out
    for i, w in enumerate(idn.fits):
        rep = w.report()
        if "params" in rep:
            where = "whole-record fit" + (f" (trial {i})" if len(idn.fits) > 1 else "")
            out += check_params({**rep["params"], "k_cr_kN_per_m": rep.get("k_cr_kN_per_m")}, rep.get("err_corr"),
                                where)
    return out


def _known_stiffness(trial: TrialData) -> bool:
    """The file gives ``machine_stiffness_kN_per_m`` (measured-data.md): a known stiffness between
    the measured position and the interface, held in the whole-record fit."""
    v = parse_number(str(trial.metadata.get("machine_stiffness_kN_per_m", "")))
    return v is not None and v > 0


RIGID_NOTE = ("the per-step method (eqs. 10-12) assumes a rigid machine: with the position measured at the load "
              "point the machine's compliance rounds the peak and spreads the decay, so its A and L are biased "
              "(A by about +50 % on load-point records); the whole-record fit with stiffness is the estimate to use")


def write_json(report: dict, path: str | Path) -> None:
    import json

    atomic_write_text(path, json.dumps(report, indent=2, allow_nan=False) + "\n")


def identify_files(paths: list[str | Path], **kw) -> Identification:
    trials = [load_trial(p) for p in paths]
    return identify_trials(trials, names=[str(p) for p in paths], **kw)
