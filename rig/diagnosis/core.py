"""The diagnosis loop: fit the baseline, find and name what it misses, extend, measure, repeat.

Method (docs/diagnosis.md):

1. :func:`rig.diagnosis.prep.prepare` turns the record into kinematics from
   the measured position and an adaptive fit grid split into alternate
   fit / hold-out blocks (20 blocks: 10 fit, 10 hold-out).
2. The baseline (rate_state or steady_state) is fitted by least squares on the
   fit blocks (several starting slip distances ``L``).
3. Screening on the residual (cheap statistics) proposes candidates:
   correlation with ``mu (N1 + N2 - 2 N_nom)`` (normal_force_variation), a
   trend in time or in slip (force_offset_drift, slip_wear_drift), a
   periodogram peak in position (position_periodic); the transient causes
   (frictional_memory, time_delay, second_state_variable, aging_law,
   sensor_lag, finite_stiffness) are always candidates while the residual
   holds structure locked to the velocity changes.
4. Each candidate is fitted *jointly* with the current model. A candidate is
   a finding only when, on the hold-out blocks, it lowers the RMS by at least
   ``MIN_GAIN_PCT`` with a paired chunk test ``z >= MIN_Z``, and its BIC on
   the fit blocks falls by more than ``MIN_DBIC``. Among those, the largest
   hold-out gain wins, which is where the discrimination happens: a lag of
   fixed duration (sensor_lag, time_delay) and one over a slip distance
   (second state, finite stiffness) predict different transients at
   different speeds, drift in time and drift in slip differ when the velocity
   varies; normal-force evidence takes precedence when the residual follows
   the measured normal force with the expected unit slope.
5. Repeat until no candidate passes; then the residual is searched for
   structure no extension explains (``unexplained``).

Issue 20 (docs/diagnosis.md, "The answer depends on the physics only"): the
record is seen from time 0 and position 0, samples are weighted by time; on a
load-point record the machine's coupling (``finite_stiffness``) is fitted from
the start or held at the file's ``machine_stiffness_kN_per_m``; the search is
repeated on re-splits of the record and a cause is named only when most splits
name it (``stability``, ``alternatives``); the reported parameters carry
``params_sd``, ``intervals`` (profile likelihood of L) and the A-B-L
``correlation``. What is particular to each cause is its object in
:mod:`rig.diagnosis.causes`.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass, field

import numpy as np

from rig.analysis.report import rounded as _r  # the one rounding of the reports (6 significant figures)
from rig.data import TrialData

from .fit import FitResult, at_bound, delta_bic, evaluate, fit, multistart, param, profile
from .intervals import undetermined_intervals, whole_domain
from rig.kinematics import velocity_changes
from rig.model.forward import as_model
from rig.model.spec import EXT_PARAMS, PLAUSIBLE, model_params
from .causes import CAUSES, PERIODIC_SEARCH_CYCLES, rate_starts, slip_of, stiffness_floor_kN_per_m
from .parallel import can_fork, fork_map, inner_workers, one_blas_thread
from .prep import Grid, canonical, prepare
from .transforms import crop

# a finding must matter in practice, not only pass a significance test (docs/diagnosis.md):
# a hold-out RMS gain of at least MIN_GAIN_PCT, and (per cause, _plausible) an effect above the
# noise floor with physically plausible parameters
MIN_GAIN_PCT = 1.0
MIN_Z = 2.5
MIN_ZW = 5.0
MIN_DBIC = -10.0
# a transient cause with a hold-out gain this large needs no chunk test: a single step gives too few
# chunks for one. A drift or a periodic term spreads over the whole record and always has the chunks:
# without them it is a gain the record's noise can make, named on some crops and samplings only
STRONG_GAIN_PCT = 5.0
UNEXPLAINED_MIN_GAIN_PCT = 1.0
# practical effect of an oscillation in time: its rms (amplitude / sqrt 2) at least this fraction of the
# hold-out residual rms; a smaller one is significant but negligible (a few mN on a 0.04 N residual)
UNEXPLAINED_MIN_EFFECT = 0.1
MAX_FINDINGS = 5
# a further cause must leave the causes already found as they were (within this fraction): one that
# takes over part of their job (a lag that makes a spring 60 % stiffer) is not separable from them
MAX_FINDING_SHIFT = 0.3
# |A|, |B| or |B2| above this is a pair of cancelling stand-ins, not rate-and-state coefficients (which
# are O(0.001-0.02): Table 2, rock friction): the upper end of rig.model.spec.PLAUSIBLE
COEF_MAX_MU = max(PLAUSIBLE["A_mu"].hi, PLAUSIBLE["B_mu"].hi)

# how the duration of each transient cause's correction scales with the new speed: over a slip
# distance (~1/v: memory, a second state, a spring taking up dF/k of slip) or a fixed time (lag, delay)
# step-aligned hold-out: a transient cause refitted on the held-out steps must gain at least this
# fraction of its gain on the fitted ones (true lags and springs of bench_diagnose: 0.23-0.8; a
# jump of friction inside one segment that a spring absorbed: 0.006)
SWAP_MIN_FRACTION = 0.1


@dataclass
class Candidate:
    cause: str
    result: FitResult
    gain_pct: float
    delta_bic: float
    z: float
    accepted: bool
    note: str = ""
    zw: float = 0.0
    info: dict = field(default_factory=dict)  # the screening figures of its round
    # a load-point coupling's parameters on a bound (:func:`_couple`): named, with "none" beside it
    undetermined: list[str] = field(default_factory=list)


@dataclass
class Finding:
    """A named cause (diagnosis.md, ``findings[]``), its numbers unrounded; :meth:`report` makes the
    JSON. ``params`` are the final model's values of the cause's parameters (the single-cause fit's,
    where they differ, are in ``evidence``); ``uncertainty``: ``params_sd``/``intervals``/``correlation``
    of those parameters in the final model."""
    cause: str
    params: dict[str, float]
    evidence: str
    holdout_rms_N_before: float
    holdout_rms_N_after: float
    gain_pct: float
    delta_bic: float
    stability: float | None = None  # the fraction of the record's splits that name it (None: one split)
    alternatives: list[dict] = field(default_factory=list)
    uncertainty: dict = field(default_factory=dict)

    def report(self) -> dict:
        out = {"cause": self.cause, "params": {k: _r(v) for k, v in self.params.items()}, "evidence": self.evidence,
               "holdout_rms_N_before": _r(self.holdout_rms_N_before),
               "holdout_rms_N_after": _r(self.holdout_rms_N_after),
               "gain_pct": _r(self.gain_pct, 4), "delta_bic": _r(self.delta_bic, 6)}
        if self.stability is not None:
            out["stability"] = _r(self.stability, 3)
        if self.alternatives:
            out["alternatives"] = self.alternatives
        out.update(self.uncertainty)
        return out


@dataclass
class Diagnosis:
    data: str
    baseline: FitResult
    findings: list[Finding]
    unexplained: list[dict]
    final: FitResult
    grid: Grid
    history: list[FitResult] = field(default_factory=list)
    tried: list[list[Candidate]] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    # the chosen baseline's and final model's parameters refitted on all sliding data (reported)
    baseline_all: dict | None = None
    final_all: dict | None = None
    # the same as FitResults (their Jacobians give params_sd, intervals, correlation)
    baseline_fit: FitResult | None = None
    final_fit: FitResult | None = None
    # causes the main split named that most re-splits did not (the record cannot tell them apart from
    # what is left): [{"cause", "stability", "gain_pct"}]
    unnamed: list[dict] = field(default_factory=list)

    @property
    def model(self):
        names = model_params(self.final.baseline, self.final.extensions)
        p = self.final_all or self.final.params
        return as_model(self.final.baseline, self.final.extensions, {k: v for k, v in p.items() if k in names})

    def report(self) -> dict:
        """The JSON report of diagnosis.md (schema rig.diagnosis/1)."""
        b = self.baseline
        base = {"model": b.baseline, "params": _public(self.baseline_all or b.params, b.baseline, b.extensions),
                "holdout_rms_N": _r(b.holdout_rms_N)}
        model = {"baseline": self.final.baseline, "extensions": list(self.final.extensions),
                 "params": _public(self.final_all or self.final.params, self.final.baseline, self.final.extensions)}
        for out, res in ((base, self.baseline_fit), (model, self.final_fit)):
            if res is not None:
                out.update(uncertainty(self.grid, res, list(out["params"])))
        return {
            "schema": "rig.diagnosis/1",
            "data": self.data,
            "baseline": base,
            "findings": [f.report() for f in self.findings],
            "unexplained": self.unexplained,
            "model": model,
            "holdout_rms_N": _r(self.final.holdout_rms_N),
        }




def _public(params: dict, baseline: str, extensions: list[str]) -> dict:
    names = model_params(baseline, extensions)
    return {k: _r(params[k]) for k in names if k in params}


# ---------------------------------------------------------------------------
# residual statistics
# ---------------------------------------------------------------------------
def _chunks(grid: Grid, mask: np.ndarray, n: int = 60) -> np.ndarray:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    c = np.zeros(grid.t.size, dtype=np.int64)
    tt = grid.t[idx]
    span = max(tt[-1] - tt[0], 1e-9)
    c[idx] = np.minimum(((tt - tt[0]) / span * n).astype(np.int64), n - 1)
    return c


def paired_z(grid: Grid, before: np.ndarray, after: np.ndarray) -> float:
    """z of the hold-out SSE reduction, chunked in time (robust to correlated residuals)."""
    hm = grid.holdout_mask()
    d = grid.w * ((grid.F_mean - before) ** 2 - (grid.F_mean - after) ** 2)
    ch = _chunks(grid, hm)
    nc = int(ch[hm].max()) + 1 if hm.any() else 0
    if nc < 3:
        return 0.0
    s = np.bincount(ch[hm], weights=d[hm], minlength=nc)
    sd = s.std(ddof=1)
    if sd <= 0:
        return 0.0 if s.mean() <= 0 else math.inf
    return float(s.mean() / (sd / math.sqrt(nc)))


def white_z(grid: Grid, before: np.ndarray, after: np.ndarray) -> float:
    """z of the hold-out SSE reduction against residual noise, corrected for its autocorrelation.

    Under "the extension is useless" the reduction sum w ((r_b)^2 - (r_a)^2) has standard
    deviation 2 sigma sqrt(sum w d^2) (d = after - before, sigma the residual's RMS) for white
    residuals; correlated residuals inflate it by sqrt((1 + rho) / (1 - rho)), rho the lag-1
    autocorrelation of the binned residual. Powerful when the evidence is concentrated in a few
    transients (too few for the chunk test).
    """
    hm = grid.holdout_mask()
    if hm.sum() < 10:
        return 0.0
    w = grid.count[hm]
    rb = (grid.F_mean - before)[hm]
    d = (after - before)[hm]
    red = float(np.sum(w * (rb ** 2 - (rb - d) ** 2)))
    sig = math.sqrt(float(np.sum(w * rb ** 2) + grid.ss_within[hm].sum()) / float(w.sum()))
    x = rb * np.sqrt(w)
    x = x - x.mean()
    rho = float(np.sum(x[1:] * x[:-1]) / max(float(np.sum(x * x)), 1e-300))
    rho = min(max(rho, 0.0), 0.98)
    sd = 2.0 * sig * math.sqrt(float(np.sum(w * d * d))) * math.sqrt((1 + rho) / (1 - rho))
    sd *= math.sqrt(grid.noise_corr)  # raw noise correlated within a bin (1 kHz behind the analog filter)
    return red / sd if sd > 0 else 0.0


def _wcorr_z(grid: Grid, r: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of r on q (weighted by count) and its z, chunk-robust."""
    w = grid.w
    qm = np.average(q, weights=w)
    rm = np.average(r, weights=w)
    qc = q - qm
    den = float(np.sum(w * qc * qc))
    if den <= 0:
        return 0.0, 0.0
    slope = float(np.sum(w * qc * (r - rm)) / den)
    # chunked standard error
    ch = _chunks(grid, np.ones(grid.t.size, bool), 60)
    e = r - rm - slope * qc
    sc = np.bincount(ch, weights=w * qc * e, minlength=60)
    se = math.sqrt(float(np.sum(sc ** 2))) / den
    return slope, (slope / se if se > 0 else 0.0)


def _fft_periodogram(q: np.ndarray, r: np.ndarray, w: np.ndarray, dq: float, per_min: float, per_max: float):
    """Periodogram of r against q (binned on a uniform q grid of step dq, weighted means, empty bins 0).

    Returns (periods, normalised power, best period, z) with z = P_max / mean(P) - ln(n): the
    normalised ordinates of white noise are exponential(1), so z > 8 happens by chance with
    probability ~3e-4 whatever the number of frequencies.
    """
    sel = w > 0
    if sel.sum() < 20:
        return None
    q0 = float(q[sel].min())
    nq = int((float(q[sel].max()) - q0) / dq) + 1
    if nq < 16:
        return None
    b = np.minimum(((q[sel] - q0) / dq).astype(np.int64), nq - 1)
    num = np.bincount(b, weights=(w * r)[sel], minlength=nq)
    den = np.bincount(b, weights=w[sel], minlength=nq)
    y = np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    y = np.where(den > 0, y - np.average(y[den > 0], weights=den[den > 0]), 0.0)
    nfft = 1 << int(math.ceil(math.log2(nq * 4)))
    Y = np.fft.rfft(y, nfft)
    f = np.fft.rfftfreq(nfft, dq)
    with np.errstate(divide="ignore"):
        per = np.where(f > 0, 1.0 / np.maximum(f, 1e-300), np.inf)
    band = (per >= per_min) & (per <= per_max)
    if band.sum() < 4:
        return None
    P = np.abs(Y[band]) ** 2
    per = per[band]
    Pn = P / max(float(P.mean()), 1e-300)
    k = int(np.argmax(Pn))
    n_indep = max(int(band.sum() / 4), 1)  # 4x zero padding
    return per, Pn, float(per[k]), float(Pn[k] - math.log(n_indep))


def position_periodogram(grid: Grid, r: np.ndarray, lam_min: float = 8.0):
    """Periodogram of the residual against position; returns (wavelengths, power, best, z)."""
    x = grid.x[grid.sliding]
    if x.size < 20:
        return None
    span = float(x.max() - x.min())
    if span < 10 * lam_min:
        return None
    return _fft_periodogram(grid.x, r, grid.w, lam_min / 4.0, lam_min, span / PERIODIC_SEARCH_CYCLES)


def time_periodogram(grid: Grid, r: np.ndarray):
    """Periodogram of the residual against time; returns (periods, power, best, z)."""
    t = grid.t
    T = float(t[-1] - t[0])
    dtm = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    pmin = max(4 * dtm, 0.2)
    if T <= 0 or T / 3 <= pmin:
        return None
    return _fft_periodogram(t, r, grid.w, pmin / 4.0, pmin, T / 3)


# ---------------------------------------------------------------------------
# starting points
# ---------------------------------------------------------------------------
def _steady_init(grid: Grid) -> dict:
    ok = grid.v > 0.02
    if ok.sum() < 5:
        ok = np.ones_like(grid.v, bool)
    lv = np.log(np.maximum(grid.v[ok], 1e-3))
    mu = grid.F_mean[ok] / (2 * grid.N_nom)
    w = grid.w[ok]
    A = np.vstack([np.ones_like(lv), lv]).T * np.sqrt(w)[:, None]
    sol, *_ = np.linalg.lstsq(A, mu * np.sqrt(w), rcond=None)
    return {"mu0": float(sol[0]), "c_mu": float(sol[1])}


def _candidate_starts(cause: str, cur: FitResult, grid: Grid, screen: dict) -> list[dict]:
    """Starting points of a candidate's joint fit (the cause's own, rig.diagnosis.causes)."""
    return CAUSES[cause].starts(dict(cur.params), grid, screen)


# ---------------------------------------------------------------------------
# screening
# ---------------------------------------------------------------------------
def screen(grid: Grid, cur: FitResult) -> tuple[list[str], dict]:
    """Cheap residual statistics -> candidate list and starting values."""
    r = grid.F_mean - cur.pred
    info: dict = {}
    cands: list[str] = []
    exts = cur.extensions
    has_state = cur.baseline == "rate_state" or "frictional_memory" in exts
    # transients
    if cur.baseline == "steady_state" and "frictional_memory" not in exts:
        if "time_delay" not in exts:
            cands += ["frictional_memory", "time_delay"]
    if has_state:
        if "second_state_variable" not in exts:
            cands.append("second_state_variable")
        if "aging_law" not in exts:
            cands.append("aging_law")
    for c in ("sensor_lag", "finite_stiffness"):
        if c not in exts:
            cands.append(c)
    # normal force
    if grid.has_normals and grid.normals_vary and "normal_force_variation" not in exts:
        q = cur.pred * (grid.N_tot / (2 * grid.N_nom) - 1.0)
        slope, z = _wcorr_z(grid, r, q)
        info["normal_slope"], info["normal_z"] = slope, z
        if z > MIN_Z and 0.5 < slope < 1.5:
            cands.append("normal_force_variation")
    # trends in time and in slip
    s = slip_of(grid)
    slope_t, z_t = _wcorr_z(grid, r, grid.t)
    slope_s, z_s = _wcorr_z(grid, r, s * 1e-3)
    info.update(time_slope_N_per_s=slope_t, time_z=z_t, slip_slope_N_per_mm=slope_s, slip_z=z_s)
    if max(abs(z_t), abs(z_s)) > MIN_Z:
        if "force_offset_drift" not in exts:
            cands.append("force_offset_drift")
            info["drift0"] = slope_t
        if "slip_wear_drift" not in exts:
            cands.append("slip_wear_drift")
            info["wear0"] = slope_s / (2 * grid.N_nom)
    # periodic in position
    if "position_periodic" not in exts:
        pg = position_periodogram(grid, r)
        if pg is not None:
            lam, pw, lam0, zp = pg
            info["period_lam_um"], info["period_z"] = lam0, zp
            if zp > 8.0:
                cands.append("position_periodic")
                info["lam0"] = lam0
                k = 2 * math.pi / lam0
                X = np.vstack([np.sin(k * grid.x), np.cos(k * grid.x)]).T
                co, *_ = np.linalg.lstsq(X * np.sqrt(grid.w)[:, None], r * np.sqrt(grid.w), rcond=None)
                info["amp0"] = float(np.hypot(*co) / (2 * grid.N_nom))
    return cands, info


# ---------------------------------------------------------------------------
# evidence sentences
# ---------------------------------------------------------------------------
def transient_scaling(grid: Grid, before: np.ndarray, after: np.ndarray):
    """How the duration of what an extension adds after each velocity change scales with speed.

    For every velocity change, the correction ``after - before`` (noise-free: a difference of two
    fitted predictions validated on hold-out data) is followed from its peak until it falls below
    1/e of it; the duration's log-log slope against the new speed is ~ -1 for a transient over a slip
    distance and ~ 0 for one of fixed duration. Returns (slope, n_steps, (v, duration) pairs) or None.
    """
    d = after - before
    t, v = grid.t, grid.v
    pairs = []
    tv = t

    # the ln-v detector's changes, unless they outnumber the steps identify finds several times: it
    # fires on the noise and bursty sampling of real records (753 "velocity changes" on a one-step one)
    te = velocity_changes(grid.kin["t"], grid.kin["v"])
    if grid.step_times_s is not None and te.size > 3 * (grid.step_times_s.size + 1):
        te = grid.step_times_s  # the detector fired on noise: identify's steps instead
    ev = sorted(set(int(i) for i in np.clip(np.searchsorted(t, te - 1.0), 0, t.size - 1)))
    for k, i in enumerate(ev):
        j_end = ev[k + 1] if k + 1 < len(ev) else t.size - 1
        seg = slice(i + 1, j_end)
        dd = np.abs(d[seg])
        if dd.size < 5:
            continue
        jm = int(np.argmax(dd))
        peak = dd[jm]
        if peak <= 0:
            continue
        below = np.flatnonzero(dd[jm:] < peak / math.e)
        if below.size == 0:
            continue
        dur = float(tv[seg][jm + below[0]] - tv[i])
        v2 = float(np.median(v[seg][jm + below[0]:][:50])) if below[0] + jm < dd.size else float(v[j_end])
        if dur > 0 and v2 > 0.05:
            pairs.append((v2, dur))
    if len(pairs) < 3:
        return None
    a = np.log(np.array(pairs))
    if np.ptp(a[:, 0]) < 0.5:
        return None
    slope = float(np.polyfit(a[:, 0], a[:, 1], 1)[0])
    return slope, len(pairs), pairs


def _evidence(cause: str, res: FitResult, grid: Grid, info: dict, others: dict[str, float],
              before: FitResult | None = None) -> str:
    p = res.params
    scal = ""
    if before is not None and CAUSES[cause].transient:
        ts = transient_scaling(grid, before.pred, res.pred)
        if ts is not None:
            slope, n, pairs = ts
            if slope < -0.6:
                kind = "a slip distance (duration ~ 1/v)"
            elif slope > -0.3:
                kind = "a fixed time"
            else:
                kind = "in between (transients cut short by the next velocity change, or both kinds)"
            scal = (f"; measured on {n} velocity changes, the added transient's duration scales as v^{slope:.2f}: "
                    f"{kind}")
            expect = CAUSES[cause].scaling
            if expect is not None and not ((expect == "slip" and slope < -0.6) or (expect == "time" and slope > -0.3)):
                scal += (f" -- not the {'~1/v of a slip distance' if expect == 'slip' else 'fixed time'} that "
                         f"{cause} predicts: the cause is named on the hold-out gain, not on this slope")
    alt = ", ".join(f"{k} {v:+.1f}%" for k, v in sorted(others.items(), key=lambda kv: -kv[1])[:3])
    alt = f" (other candidates' hold-out gains: {alt})" if alt else ""
    s = CAUSES[cause].evidence(p, grid, info)
    return s + scal + alt


# ---------------------------------------------------------------------------
# the loop
# ---------------------------------------------------------------------------
PRIOR_MAX_POINTS = 6000  # identify's time bins for the starting point


def identify_prior(trial: TrialData, steps: list | None = None, max_points: int = PRIOR_MAX_POINTS) -> dict:
    """identify's whole-record fit (rig.analysis.identify.fit_whole_record) as a starting point:
    ``{"A_mu", "B_mu", "L_um"[, "stiffness_kN_per_m"]}``, or {} when the record has no step it
    can use. With ``position_source: load_point`` the fit includes the stiffness. ``max_points``:
    identify's time bins; the start takes PRIOR_MAX_POINTS (3-row bins at 25 Hz), whose A is
    +5-8 % on the simulated rig's main job against identify's own 15000 points' -2 to +1 %
    (docs/validation.md, "Coverage"): a start, not a reference (:func:`floor_reference`)."""
    from rig.analysis.identify import fit_whole_record
    from rig.kinematics import detect_steps

    try:
        steps = detect_steps(trial) if steps is None else steps
        if not steps:
            return {}
        w = fit_whole_record(trial, steps, stiffness=trial.is_load_point, max_points=max_points, jackknife=False)
    except (ValueError, ZeroDivisionError, FloatingPointError, IndexError, np.linalg.LinAlgError):
        return {}
    if not w.params:
        return {}
    p = w.params  # the fit's own numbers, unrounded (WholeRecordFit.params; its report's are rounded)
    out = {k: float(p[k]) for k in ("A_mu", "B_mu", "L_um", "stiffness_kN_per_m") if p.get(k) is not None}
    if not (0.0 <= out.get("A_mu", -1) < COEF_MAX_MU and abs(out.get("B_mu", 1)) < COEF_MAX_MU
            and 0.1 < out.get("L_um", 0) < 1e4):
        return {}
    return out


def fit_baseline(grid: Grid, baseline: str, prior: dict | None = None) -> FitResult:
    p_ss = _steady_init(grid)
    if baseline == "steady_state":
        return fit(grid, "steady_state", [], p_ss)
    if baseline != "rate_state":
        raise ValueError(f"unknown baseline {baseline!r} (rate_state or steady_state)")
    starts = rate_starts(p_ss)
    # identify's whole-record fit (fitted whatever its cost at the start: a ranking by cost at the
    # starting point is what let the fit settle in a cancelling A ~ B ~ 0.05 minimum before)
    must = [{"mu0": p_ss["mu0"], "A_mu": prior["A_mu"], "B_mu": prior["B_mu"], "L_um": prior["L_um"]}] if prior else []
    if not grid.sliding[: max(3, grid.t.size // 200)].any():
        # the record starts at rest (a hold before sliding): the state it starts in is unknown,
        # a nuisance parameter (the velocity whose steady state it is), fitted with everything else
        v1 = _first_velocity(grid)
        starts = [dict(s, v_init_um_s=v1 * f) for s in starts for f in (1.0, 0.01)]
        must = [dict(s, v_init_um_s=v1 * f) for s in must for f in (1.0, 0.01)]
    # coefficients over COEF_MAX_MU (a cancelling A ~ B ~ 0.05 minimum) lose to any physical fit
    return multistart(grid, "rate_state", [], starts, keep=3, must=must, plausible=lambda p: not _coefs_too_large(p))


def _first_velocity(grid: Grid) -> float:
    """The velocity of the first sliding bin (um/s, at least 0.01): the steady state a start's state is searched from."""
    return float(max(grid.v[int(np.argmax(grid.sliding))], 0.01))


# the start's state is searched from the steady state of the first velocity times these
START_STATE_FACTORS = (0.1, 1.0, 10.0)


def _start_state(grid: Grid, res: FitResult, decided: bool | None = None) -> FitResult:
    """``res`` (started in the steady state of the first velocity), or the same model with the
    state it starts in fitted (``v_init_um_s``, the speed whose steady state it is, a nuisance
    parameter as for a start from rest) when that explains the fit blocks significantly better
    (BIC falls by more than -MIN_DBIC, the extra parameter counted): a record cut out of a longer
    run (a crop, a trim) starts mid-transient, e.g. a second after a velocity step whose direct
    effect is cut off, and a steady start would make every model bend its a, b and L to the
    first seconds. Every candidate then carries it (it is in the current model's parameters).
    ``decided``: the record's main split's answer, which a re-split takes (the state a record
    starts in is the record's, not a split's: decided on each split, a re-split of a trimmed
    drift record fitted it and its screen then missed the drift the main split names)."""
    free = _free_fit(grid, res, decided)
    return _start_decided(grid, res, free, decided)


def _start_to_fit(res: FitResult, decided: bool | None) -> bool:
    """The state ``res`` starts in is to be fitted (:func:`_start_state`)."""
    return "v_init_um_s" not in res.params and res.baseline == "rate_state" and decided is not False


def _free_fit(grid: Grid, res: FitResult, decided: bool | None) -> FitResult | None:
    """``res``'s model with the state it starts in fitted (None: not to be fitted)."""
    if not _start_to_fit(res, decided):
        return None
    v1 = _first_velocity(grid)
    starts = [dict(res.params, v_init_um_s=v1 * f) for f in START_STATE_FACTORS]
    return multistart(grid, res.baseline, list(res.extensions), starts, keep=1, max_nfev=120)


def _start_decided(grid: Grid, res: FitResult, free: FitResult | None, decided: bool | None) -> FitResult:
    """``free`` (:func:`_free_fit`) where the start is decided or the BIC asks for it, else ``res``."""
    if free is None:
        return res
    return free if decided or delta_bic(grid, res, free) < MIN_DBIC else res


def _free_start(s: "_Search", prior: dict, known: dict, warm: dict | None, progress=None,
                decided: bool | None = None, free: FitResult | None = None) -> None:
    """The start's state fitted where it is unknown (:func:`_start_state`), after the load point's
    coupling: on a load-point record the spring, not the start, explains the first transient, so
    the start is judged on the coupled model; where the coupling was refused on a steady start,
    it is tried again from the rigid model with its start fitted (a record that starts
    mid-transient: the spring then has the same start to work from)."""
    cur = s.history[-1]
    free = _start_state(s.grid, cur, decided) if free is None else _start_decided(s.grid, cur, free, decided)
    if free is cur or (s.coupled and _bounded(free)):
        return  # (a coupled fit that the free start runs to a bound keeps its steady start)
    if free.holdout_rms_N > cur.holdout_rms_N * (1.0 + MIN_GAIN_PCT / 100.0):
        # a nuisance the held-out data reject: a start that fits the fit blocks better but predicts
        # the held-out ones worse is another valley of the fit, not the record's start
        return
    s.start_fitted = True
    s.history[-1] = free
    if s.coupled:
        c, before = s.chosen[-1][0], s.chosen[-1][1]
        # the coupling's figures are the refitted model's, judged against the same rigid model
        c.result = free
        c.gain_pct, c.delta_bic, c.z, c.zw = _compare(s.grid, before, free)
        c.undetermined = _bounded(free, s.grid)
    elif len(s.history) == 1:
        s.base = free
    if s.coupling_refused is not None:
        s.coupling_refused = None
        _couple(s, prior, known, warm, progress)


def _compare(grid: Grid, cur: FitResult, res: FitResult) -> tuple[float, float, float, float]:
    """``res`` judged against ``cur``: (hold-out gain in %, BIC change, paired chunk z, white-noise z)."""
    gain = 100.0 * (cur.holdout_rms_N - res.holdout_rms_N) / cur.holdout_rms_N
    return gain, delta_bic(grid, cur, res), paired_z(grid, cur.pred, res.pred), white_z(grid, cur.pred, res.pred)


def try_candidate(grid: Grid, cur: FitResult, cause: str, info: dict, prior: dict | None = None,
                  warm: dict | None = None, fmap=None) -> Candidate:
    """Fit ``cause`` jointly with the current model and judge it on the hold-out blocks. ``warm``:
    the same candidate's fit on another split of the record (a re-split), its one starting point
    besides the current model's with the cause's first start; ``fmap``: how its starts' full fits
    run (:func:`rig.diagnosis.fit.multistart`)."""
    exts = list(cur.extensions) + [cause]
    res = _fit_candidate(grid, cur, cause, info, prior, warm, fmap)
    gain, dbic, z, zw = _compare(grid, cur, res)
    note = ""
    if gain < MIN_GAIN_PCT:
        note = f"hold-out gain under {MIN_GAIN_PCT:g}%"
    elif dbic > MIN_DBIC:
        note = (f"its BIC falls by only {-dbic:.1f}" if dbic < 0 else f"its BIC rises by {dbic:.1f}") + \
            f" (a fall of {-MIN_DBIC:g} needed)"
    elif not (z >= MIN_Z or zw >= MIN_ZW or (gain >= STRONG_GAIN_PCT and CAUSES[cause].transient)):
        note = f"not significant on the hold-out blocks (z = {z:.1f})"
    elif not _plausible(cause, res.params, grid):
        note = ("its fit is not physical (a bound, a parameter outside its plausible range, or an effect below "
                "the noise)")
    if not note:
        note = _veto(grid, cur, res, cause, exts, gain)
    c = Candidate(cause, res, gain, dbic, z, not note, note)
    c.zw = zw
    return c


def _fit_candidate(grid: Grid, cur: FitResult, cause: str, info: dict, prior: dict | None,
                   warm: dict | None, fmap=None) -> FitResult:
    """The joint fit of the current model and ``cause`` on the fit blocks, from the cause's starts
    (and a re-split's ``warm`` fit, or identify's whole-record fit for a spring or a second state)."""
    exts = list(cur.extensions) + [cause]
    starts = _candidate_starts(cause, cur, grid, info)
    # e.g. two states: many local minima (but the stiffness solver is costly)
    keep = CAUSES[cause].keep if "finite_stiffness" not in exts else 2
    must = []
    if warm is not None:
        # the warm fit's values for this model's parameters, the current model's for the rest (the
        # re-split may have named another cause in an earlier round than the main split did)
        names = set(model_params(cur.baseline, exts)) | {"v_init_um_s"}
        starts, keep = starts[:1], 1
        must = [{**cur.params, **{k: v for k, v in warm.items() if k in names and k in starts[0]}}]
    elif prior and cause in ("finite_stiffness", "second_state_variable") and cur.baseline == "rate_state":
        # also from identify's whole-record fit (the current model may sit in a minimum that only
        # the rigid model has)
        q = dict(cur.params, A_mu=prior["A_mu"], B_mu=prior["B_mu"], L_um=prior["L_um"])
        if cause == "finite_stiffness":
            k0 = prior.get("stiffness_kN_per_m", 600.0)
            must = [dict(q, stiffness_kN_per_m=k0), dict(cur.params, stiffness_kN_per_m=k0)]
        else:
            must = [dict(q, B2_mu=0.5 * abs(prior["B_mu"]) + 5e-4, L2_um=5.0 * prior["L_um"])]
    res = multistart(grid, cur.baseline, exts, starts, keep=min(keep, len(starts)), max_nfev=120, must=must,
                     fmap=fmap)
    if cause == "finite_stiffness" and res.sse_fit > cur.sse_fit:
        # the nested comparison at the better of the two fits: the extended model contains the current
        # one (k -> infinity), so a fit that ends worse on the fit blocks is stuck; from the current model
        # with a spring too stiff to matter it can only improve (docs/diagnosis.md, "Rules learned from
        # records")
        r2 = fit(grid, cur.baseline, exts, dict(cur.params, stiffness_kN_per_m=1e5), max_nfev=120)
        if r2.sse_fit < res.sse_fit:
            res = r2
    if "second_state_variable" in exts and "aging_law" not in exts:
        # the two slip-law states are interchangeable: by the spec's convention the second is the
        # slower one, L2_um > L_um (swapped before reporting)
        swap_slower_second(res.params)
    return res


def _veto(grid: Grid, cur: FitResult, res: FitResult, cause: str, exts: list[str], gain: float) -> str:
    """Why a candidate that passed the hold-out test is still not named ("" when nothing vetoes it):
    it moves a cause already found, a transient that is not in every step, a drift that is not linear."""
    if cur.extensions:
        moved = _confounded(cur, res)
        if moved:
            return (f"confounded with {moved[0]}: adding it moves {moved[1]} from {moved[2]:.4g} to {moved[3]:.4g} "
                    f"({100 * moved[4]:+.0f}%); the data do not tell the two apart")
    if CAUSES[cause].transient and grid.holdout_design.startswith("blocks aligned"):
        # with the hold-out segments aligned to the steps, a transient cause must also predict the
        # other half of the steps: refitted on the hold-out segments, judged on the fit segments.
        # A true memory, lag or spring shows in every step; a one-off event inside one segment (a
        # jump of friction) that the new parameters happen to absorb does not
        swap = _swapped(grid)
        base_sw = fit(swap, cur.baseline, list(cur.extensions), dict(cur.params), max_nfev=120)
        ext_sw = fit(swap, cur.baseline, exts, dict(res.params), max_nfev=120)
        before_sw = base_sw.holdout_rms_N
        gain_sw = (100.0 * (before_sw - ext_sw.holdout_rms_N) / before_sw
                   if math.isfinite(before_sw) and before_sw > 0 else math.inf)  # nothing to judge on: no veto
        if gain_sw < SWAP_MIN_FRACTION * gain:
            return (f"not in every step: refitted on the held-out steps and judged on the fitted ones it "
                    f"gains {gain_sw:+.2f}%, under {SWAP_MIN_FRACTION:g} of its {gain:.1f}% (an event in a few "
                    "segments, not a property of every transient)")
    if cause in ("force_offset_drift", "slip_wear_drift"):
        # a drift must be linear: if a free profile in the same quantity still explains much of what
        # is left, the drift only approximates something else (a jump, a non-linear run-in)
        ratio = _drift_leftover(grid, cur.pred, res.pred)
        if ratio > 0.5:
            return (f"not linear: block means of the residual after it keep {100 * ratio:.0f}% of the drift's own "
                    "size (a jump or a non-linear run-in, not a linear drift)")
    return ""


def _swapped(grid: Grid) -> Grid:
    """The same grid with fit and hold-out blocks exchanged."""
    return dataclasses.replace(grid, block=grid.block + 1)


def _confounded(cur: FitResult, res: FitResult):
    """(extension, parameter, before, after, relative change) when adding a cause moves a parameter of
    a cause already found by more than ``MAX_FINDING_SHIFT`` (or ``None``). Two causes that shape the
    same feature (a sensor lag and a machine spring both round a step) trade one against the other:
    if the second takes over part of the first's job, the data do not separate them, and the first
    (chosen head to head against every candidate on the same hold-out data) stands alone."""
    for ext in cur.extensions:
        for nm in EXT_PARAMS.get(ext, ()):
            a, b = cur.params.get(nm), res.params.get(nm)
            if a is None or b is None or nm in ("amplitude_mu", "phase_rad") or a == 0:
                continue
            rel = (b - a) / abs(a)
            if abs(rel) > MAX_FINDING_SHIFT:
                return ext, nm, a, b, rel
    return None


def swap_slower_second(p: dict) -> dict:
    """Put the slower slip-law state second (diagnosis.md: ``L2_um > L_um``), in place."""
    if "L2_um" in p and "L_um" in p and p["L2_um"] < p["L_um"]:
        p["L_um"], p["L2_um"] = p["L2_um"], p["L_um"]
        p["B_mu"], p["B2_mu"] = p["B2_mu"], p["B_mu"]
    return p


def _drift_leftover(grid: Grid, before: np.ndarray, after: np.ndarray) -> float:
    """RMS over the 20 blocks of the residual's block means after a drift extension, relative to the
    RMS of the drift's own block means: small for a linear drift, large when the drift only
    approximates a jump or a curved trend."""
    w = grid.w
    blk = grid.time_block if grid.time_block is not None else grid.block
    nb = int(blk.max()) + 1
    den = np.bincount(blk, weights=w, minlength=nb)
    ok = den > 0
    if ok.sum() < 4:
        return 0.0
    m_res = np.bincount(blk, weights=w * (grid.F_mean - after), minlength=nb)[ok] / den[ok]
    m_drift = np.bincount(blk, weights=w * (after - before), minlength=nb)[ok] / den[ok]
    a = float(np.std(m_res))
    b = float(np.std(m_drift))
    return a / b if b > 0 else math.inf


def _ext_params_plausible(extensions, p: dict) -> bool:
    """The extensions' own parameters inside their physical range (rig.model.spec.PLAUSIBLE, the
    ranges rig.model.checks warns with): a 72 s "sensor lag" on a 2.8 h gouge record is no sensor's."""
    for e in extensions:
        for name in EXT_PARAMS.get(e, ()):
            rng = PLAUSIBLE.get(name)
            if rng is not None and name in p and not (rng.lo <= p[name] <= rng.hi):
                return False
    return True


def _coefs_too_large(p: dict) -> bool:
    """|A|, |B| or |B2| above ``COEF_MAX_MU``."""
    return any(abs(p.get(k, 0.0)) > COEF_MAX_MU for k in ("A_mu", "B_mu", "B2_mu"))


def _plausible(cause: str, p: dict, grid: Grid) -> bool:
    """Reject fits that ran to a bound (the extension then stands in for something else)."""

    if at_bound(p, grid):
        return False
    if not _ext_params_plausible((cause,), p):
        return False
    # large cancelling coefficients (e.g. B = 0.13, B2 = -0.13) stand in for something else
    if _coefs_too_large(p):
        return False
    return CAUSES[cause].plausible(p, grid)


def known_params(trial: TrialData) -> dict:
    """Parameters the file states (measured-data.md): ``machine_stiffness_kN_per_m``, a calibrated
    stiffness between the measured position and the interface, held fixed in every fit (as xlook
    and RSFit hold a calibrated k)."""
    raw = trial.metadata.get("machine_stiffness_kN_per_m")
    if raw is None or str(raw).strip() == "":
        return {}
    from rig.data import parse_number

    k = parse_number(str(raw))
    if k is None or not math.isfinite(k) or k <= 0:
        raise ValueError(f"{trial.source or 'trial'}: metadata machine_stiffness_kN_per_m {raw!r} is not a positive "
                         "number of kN/m")
    return {"stiffness_kN_per_m": float(k)}


# re-splits of the record (Deliver 5 of issue 20): other hold-out blocks and crops of a few per cent;
# a cause is named only when it is named on most of them and the main split
RESPLITS = ({"n_blocks": 16, "align": False}, {"n_blocks": 24, "swap_aligned": True}, {"crop": (0.03, 0.0)},
            {"crop": (0.0, 0.03)})
MIN_STABILITY = 0.5  # named on more than this fraction of all splits (main + RESPLITS)
RESPLIT_PARALLEL_MIN_S = 3.0  # a main search shorter than this runs its re-splits in-process
CANDIDATES_PARALLEL_MIN_S = 1.0  # a baseline fit longer than this: a round's candidates on both cores
# on grids this large (a spring's fit takes seconds), a load-point coupling's starts are fitted on both cores,
# and the final model beside the residual's search for unexplained structure
PARALLEL_MIN_BINS = 5000
PROFILE_MAX_BINS_SPRING = 2000  # profile likelihood of a model with a spring only on grids this small
# the profiles over the domain of an undetermined final model (intervals.py) on grids up to this many bins
# (velstep2's 19,446: five profiles, 6-8 s of CPU on two cores); above, each parameter's whole searched domain
PROFILE_MAX_BINS_UNDETERMINED = 40000


@dataclass
class _Search:
    grid: Grid
    base: FitResult
    history: list[FitResult]
    tried: list[list[Candidate]]
    chosen: list[tuple[Candidate, FitResult, str]]  # (candidate, model before it, why it was chosen)
    # load point: the machine's coupling, fitted from the start (named first) or, when it worsens the
    # held-out data, left out (then it is here, not in ``chosen``)
    coupled: bool = False
    coupling_refused: Candidate | None = None
    start_fitted: bool = False  # the state the record starts in is fitted (:func:`_start_state`)


def _search(trial: TrialData, baseline: str, prior: dict, steps: list, known: dict, load_point: bool,
            n_blocks: int = 20, swap_aligned: bool = False, progress=None, max_rounds: int = MAX_FINDINGS,
            align: bool = True, warm: list[dict] | None = None, warm_coupling: dict | None = None,
            start: bool | None = None) -> _Search:
    """One split of the record: the baseline, the machine's coupling (load point), then the loop of
    candidates until none passes. ``warm``: per round of the loop, each candidate's fit on another
    split (``warm_coupling``: the coupling's); ``start``: whether the main split fitted the state
    the record starts in (None: decide, on the main split)."""
    grid = _prepared(trial, prior, steps, known, n_blocks, align)
    if swap_aligned and grid.holdout_design.startswith("blocks aligned"):
        grid = _swapped(grid)
    if int(grid.sliding.sum()) < 10:
        raise ValueError(f"{trial.source or 'trial'}: hardly any forward sliding (v > {0.1:g} um/s away from stops): "
                         "nothing to diagnose")
    t_base = _time.perf_counter()
    base = fit_baseline(grid, baseline, prior)
    t_base = _time.perf_counter() - t_base
    s = _Search(grid, base, [base], [], [])
    t_cur = _time.perf_counter()
    if load_point and baseline == "rate_state":
        _couple(s, prior, known, warm_coupling, progress)
    # the candidates' cost is the current model's: a coupled one (a spring solved per bin) costs
    # several times the rigid baseline's fit
    t_pre = max(t_base, _time.perf_counter() - t_cur if s.coupled else 0.0)
    first = None
    # (a re-split that takes the main split's fitted start fits it first: it is certain to change the model)
    if t_pre > CANDIDATES_PARALLEL_MIN_S and start is None and _start_to_fit(s.history[-1], start) \
            and inner_workers() > 1 and can_fork():
        first = _free_start_beside_round(s, prior, known, warm, warm_coupling, progress, start)
        t_base = t_pre
    else:
        _free_start(s, prior, known, warm_coupling, progress, start)
        t_base = max(t_base, _time.perf_counter() - t_cur if s.coupled else 0.0)
    cur, tried, chosen, history = s.history[-1], s.tried, s.chosen, s.history
    for round_no in range(max_rounds):
        if round_no == 0 and first is not None:
            cands, info, results = first
        else:
            cands, info = screen(grid, cur)
            w = warm[round_no] if warm and round_no < len(warm) else {}
            results = _round(grid, cur, cands, info, prior, w, t_base > CANDIDATES_PARALLEL_MIN_S, progress)
        tried.append(results)
        acc = [c for c in results if c.accepted]
        if not acc:
            break
        best, why = _best(grid, acc)
        nfv = [c for c in acc if c.cause == "normal_force_variation"]
        if nfv and nfv[0] is not best and nfv[0].gain_pct > 0.5 * best.gain_pct:
            why = (f"named over {best.cause} ({best.gain_pct:+.1f}%) because the residual follows the measured normal "
                   f"force with the unit slope friction proportional to it predicts")
            best = nfv[0]
        best.info = info
        chosen.append((best, cur, why))
        cur = best.result
        history.append(cur)
    return s


def _prepared(trial: TrialData, prior: dict, steps: list, known: dict, n_blocks: int, align: bool,
              rest: bool = False) -> Grid:
    """The record's grid (:func:`rig.diagnosis.prep.prepare`) with the file's stated parameters and the
    stiffness floor: the restart guard 3 L of identify's fit, its steps; ``rest``: the reported rigid
    models' velocity, zero where the position rests (:func:`reported_grid`)."""
    grid = prepare(trial, n_blocks=n_blocks, restart_guard_um=3.0 * prior["L_um"] if prior else 0.0,
                   step_times_s=np.array([s.t_s for s in steps]) if steps else np.zeros(0), align_to_steps=align,
                   rest=rest)
    grid.known = dict(known)
    if "stiffness_kN_per_m" not in known:
        grid.stiffness_floor_kN_per_m = stiffness_floor_kN_per_m(grid)
    return grid


def _round_jobs(grid: Grid, cur: FitResult, cands: list[str], info: dict, prior: dict, w: dict) -> list:
    """A round's candidate fits as :func:`_run_job` jobs, the costliest first (the most starts fitted
    in full), so that no core is idle at the end; with the index of each in ``cands``."""
    order = sorted(range(len(cands)), key=lambda i: -CAUSES[cands[i]].keep)
    return [(i, (try_candidate, (grid, cur, cands[i], info, prior, w.get(cands[i])))) for i in order]


def _round(grid: Grid, cur: FitResult, cands: list[str], info: dict, prior: dict, w: dict, parallel: bool,
           progress=None) -> list[Candidate]:
    """The candidates of a round, fitted and judged (independent: on the cores :mod:`.parallel`
    allows where the fits are slow); in the screen's order, whatever the cores."""
    jobs = _round_jobs(grid, cur, cands, info, prior, w)
    done = fork_map(_run_job, [j for _, j in jobs], parallel, progress, lambda j: f"trying {j[1][2]}")
    return [r for _, r in sorted(zip([i for i, _ in jobs], done))]


def _forked_fits(args_list: list) -> list[FitResult]:
    """:func:`rig.diagnosis.fit.fit` ``(*args)`` for each of ``args_list``, on the cores :mod:`.parallel` allows."""
    return fork_map(_run_job, [(fit, a) for a in args_list], True)


def _run_job(job):
    """``fn(*args)`` of a job ``(fn, args)`` (a worker of :func:`fork_map`)."""
    import warnings

    fn, args = job
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a forked worker writes nothing (a stream's lock may be held at the fork)
        return fn(*args)


def _free_start_beside_round(s: _Search, prior: dict, known: dict, warm: list[dict] | None,
                             warm_coupling: dict | None, progress, start: bool | None):
    """:func:`_free_start` with the first round's candidates fitted beside it, from the model as it is
    (the start's fit is one job among them, listed first): the start is rarely fitted (none of the
    real records' originals fit it), and then the round's fits are dropped (the jobs not yet begun
    are cancelled) and made again from the new model. Returns (candidates, screen info, results) of
    the first round, or None when the start changed the model."""
    cur = s.history[-1]
    cands, info = screen(s.grid, cur)
    w = warm[0] if warm else {}
    jobs = _round_jobs(s.grid, cur, cands, info, prior, w)

    def changed(i: int, free) -> bool:
        if i:
            return False
        _free_start(s, prior, known, warm_coupling, progress, start, free=free)
        return s.history[-1] is not cur

    done = fork_map(_run_job, [(_free_fit, (s.grid, cur, start))] + [j for _, j in jobs], True, progress,
                    lambda j: "the start's state" if j[0] is _free_fit else f"trying {j[1][2]}", stop=changed)
    if s.history[-1] is not cur:
        return None
    return cands, info, [r for _, r in sorted(zip([i for i, _ in jobs], done[1:]))]


def _best(grid: Grid, acc: list[Candidate]) -> tuple[Candidate, str]:
    """The accepted candidate to name, and why where it is not simply the largest hold-out gain.
    Candidates whose hold-out prediction the largest gain does not beat significantly (paired chunk
    z < MIN_Z) are a tie the held-out data cannot break: among them the fit blocks' BIC decides (the
    same number of parameters: the better fit of the larger half). The hold-out gains of a drift in
    time and one in slip on a generated record differed by 0.25 % (z 2.2) on the original and by
    -0.03 % (z 0.2) decimated, so the gain named the force drift on one and the slip drift on the
    other; the BIC preferred the force drift on both (-3193 vs -3043, -1824 vs -1805)."""
    top = max(acc, key=lambda c: c.gain_pct)
    tied = [c for c in acc if c is not top and paired_z(grid, c.result.pred, top.result.pred) < MIN_Z]
    best = min([top] + tied, key=lambda c: c.delta_bic)
    if best is top:
        return top, ""
    return best, (f"named over {top.cause} ({top.gain_pct:+.1f}%, not significantly more on the held-out data) "
                  f"by the fit blocks' BIC ({best.delta_bic:.0f} against {top.delta_bic:.0f})")


# a coupled fit with one of these on its fit bound (rig.model.spec.PARAMS, the record's stiffness floor,
# a spring's floor of A) is not determined by the record: the coupling is named with "none" beside it
# (sepiolite velstep2: B = -0.2, L 840 um; velstep1: A at its floor, decimated B at 0.2)
CORE_BOUNDED = ("A_mu", "B_mu", "L_um", "stiffness_kN_per_m")


def _bounded(res: FitResult, grid: Grid | None = None) -> list[str]:
    """The parameters of CORE_BOUNDED that ``res`` has on a bound (with a ``grid``, also the record's
    floor of the stiffness, and a spring fit's floor of A)."""
    return [k for k in CORE_BOUNDED if k in res.params and _on_bound(k, res.params[k], grid,
                                                                      "finite_stiffness" in res.extensions)]


def _on_bound(name: str, value: float, grid: Grid | None = None, spring: bool = False) -> bool:
    """``value`` on (or within 1e-4 of the range from) a bound of the model's domain for ``name``
    (``fit.param``, rig.model.spec.PARAMS; a ln-fitted one within 1 %). Not the record's own bound
    on L (``Grid.max_state_um``): a trimmed 36 um record's L of 18 um is no runaway. With a ``grid``:
    the stiffness floor its force-displacement slope sets, and (``spring``) A's floor of a spring fit."""
    p = param(name, grid, spring) if name != "L_um" else param(name)
    if p.log:
        return p.at_bound(value)
    return min(value - p.lo, p.hi - value) <= 1e-4 * (p.hi - p.lo)


def _significant(c: Candidate) -> bool:
    """A hold-out gain of at least MIN_GAIN_PCT that the paired chunk z or the white-noise z supports."""
    return c.gain_pct >= MIN_GAIN_PCT and (c.z >= MIN_Z or c.zw >= MIN_ZW)


def _untested_coupling(c: Candidate) -> str:
    """Why the held-out data do not decide a load-point coupling ("" when they do): its fit on a
    bound (:func:`_couple`), or a gain that is not significant by a clear margin -- each z at least
    one (its own standard error) above its threshold. A z within one of the threshold passes on
    one copy of a record and fails on another (Leeman: white z 6.0 on the original, 2.9 decimated),
    so the answer there is the same on every copy: the coupling, with "none" beside it."""
    bound = c.undetermined
    if bound:
        return (f"its fit runs to the bound of {', '.join(f'{k} = {c.result.params[k]:.4g}' for k in bound)}: "
                "the one-state model with a spring does not determine these on this record")
    if c.gain_pct >= MIN_GAIN_PCT and (c.z >= MIN_Z + 1.0 or c.zw >= MIN_ZW + 1.0):
        return ""
    return (f"the held-out data do not test the spring clearly ({c.gain_pct:+.1f}%, chunk z {c.z:.1f}, white z "
            f"{c.zw:.1f}): its stiffness and the a, b it trades with are not determined by this record")


def _worsens(c: Candidate) -> bool:
    """The held-out data predicted worse with the candidate than without it, consistently in time: a
    loss of at least MIN_GAIN_PCT that the paired chunk test finds significant (z <= -MIN_Z). A loss
    inside the noise (a spring on a one-step record whose hold-out blocks hold no transient: -0.1 %)
    is no evidence either way, nor is one that a single event makes: the white-noise z and the
    size of the loss alone counted a 0.2 s jump of the basalt record's load-point position (0.9 um,
    which a stiff spring turns into a force spike the friction does not show) as hundreds of
    independent samples, and refused the coupling on the trimmed copy where that second fell in a
    hold-out block (-8 %, chunk z -1.4). A coupling kept this way, whose gain is not significant,
    is reported with "none" as its alternative (:func:`_findings`)."""
    if not math.isfinite(c.gain_pct):
        return True
    return c.gain_pct <= -MIN_GAIN_PCT and c.z <= -MIN_Z


def _couple(s: _Search, prior: dict, known: dict, warm: dict | None, progress=None) -> None:
    """The machine's coupling of a load-point record (measured-data.md: ``position_source:
    load_point`` or a stated ``machine_stiffness_kN_per_m``): the elastic coupling between the
    measured position and the interface is always there, so it is fitted from the start (or held at
    the stated value) and named first, before any stand-in cause (aging, a lag, a drift) is tried,
    whatever its significance, but never when it worsens the held-out data (:func:`_worsens`: a
    hold-out RMS that rises significantly is evidence against it; the search then goes on from the
    rigid model)."""
    if progress:
        progress("the machine's coupling")
    cur = s.history[-1]
    # its starts' fits on the cores where a spring's fit is slow (a long record)
    fmap = _forked_fits if s.grid.t.size >= PARALLEL_MIN_BINS else None
    c = try_candidate(s.grid, cur, "finite_stiffness", {}, prior, warm=warm, fmap=fmap)
    sl = s.grid.sliding
    # the spring's integration reverses the friction where the record slides forward: the interface
    # overshoots the load point by F/k (Leeman trimmed, A at its floor: a hold-out RMS 33 times the rigid one's)
    reversed_ = int(np.sum(c.result.pred[sl] * s.grid.F_mean[sl] < 0.0))
    if _worsens(c) or reversed_:
        c.note = (f"its prediction reverses the friction in {reversed_} forward-sliding bins: the one-state "
                  "model with a spring does not describe this record" if reversed_ else
                  f"the held-out data get worse with it (hold-out RMS {cur.holdout_rms_N:.4g} -> "
                  f"{c.result.holdout_rms_N:.4g} N, {c.gain_pct:+.1f}%)")
        s.coupling_refused = c
        return
    # a fit on a bound of the model's domain, of the record's stiffness floor or of a spring's A is
    # not decisive either way: the coupling is still physics (named), but the record does not determine
    # it, and "none" is listed beside it (_findings). Refusing it there named nothing on sepiolite
    # velstep1's decimated copy (B at 0.2) and the coupling on the original (A at its floor)
    c.undetermined = _bounded(c.result, s.grid)
    why = ("the file states the machine stiffness (machine_stiffness_kN_per_m), held fixed" if known else
           "position_source: load_point: the machine's compliance lies between the measured position and the "
           "interface, so the coupling is fitted from the start, whatever the significance of its hold-out gain")
    s.chosen.append((c, cur, why))
    s.tried.append([c])
    s.history.append(c.result)
    s.coupled = True


def _resplit_causes(args) -> list[str]:
    """The causes one re-split names, in order (a worker of :func:`diagnose`)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a forked worker writes nothing (a stream's lock may be held at the fork)
        return _resplit_search(*args)


def _resplit_search(trial, baseline, prior, steps, known, load_point, spec, rounds, warm, warm_coupling,
                    start) -> list[str]:
    a, b = spec.get("crop", (0.0, 0.0))
    if a or b:
        # not re-zeroed: the steps are on this clock (prepare measures everything from the first sample)
        trial = crop(trial, a, b)
    try:
        s = _search(trial, baseline, prior, steps, known, load_point, n_blocks=spec.get("n_blocks", 20),
                    swap_aligned=spec.get("swap_aligned", False), max_rounds=rounds, align=spec.get("align", True),
                    warm=warm, warm_coupling=warm_coupling, start=start)
    except (ValueError, ZeroDivisionError, FloatingPointError, IndexError, KeyError):
        return ["(failed)"]  # counted as a split that does not name the cause
    return [c.cause for c, _, _ in s.chosen]


def _run_resplits(jobs: list, parallel: bool, progress=None) -> list[list[str]]:
    return fork_map(_resplit_causes, jobs, parallel, progress, lambda j: "re-splits")


def diagnose(trial: TrialData, baseline: str = "rate_state", progress=None, n_blocks: int = 20,
             resplits: bool = True) -> Diagnosis:
    """Run the whole diagnosis on a trial; see the module docstring. BLAS on one thread throughout
    (:mod:`rig.diagnosis.parallel`: the same numbers, less CPU)."""
    with one_blas_thread():
        return _diagnose(trial, baseline, progress, n_blocks, resplits)


def _diagnose(trial: TrialData, baseline: str, progress, n_blocks: int, resplits: bool) -> Diagnosis:
    from rig.analysis.identify import check_analysable

    t0 = _time.perf_counter()
    check_analysable(trial, "diagnose")
    # the file's clock and the position's zero are no physics: every step below sees them from 0
    trial = canonical(trial)
    known, steps, prior, load_point = _inputs(trial)
    t_prep = _time.perf_counter() - t0
    main = _search(trial, baseline, prior, steps, known, load_point, n_blocks=n_blocks, progress=progress)
    grid = main.grid
    t_loop = _time.perf_counter() - t0 - t_prep
    # re-splits: a cause is named only when most splits name it (the coupling of a load-point record is
    # physics, named on every split)
    split_causes: list[list[str]] = []
    coupling = int(main.coupled)
    if resplits and len(main.chosen) > coupling:
        # as many rounds as the main split took (what a re-split names after that is not asked)
        # warm-started from the main split's fit of every candidate of the same round
        warm = [{c.cause: dict(c.result.params) for c in round_} for round_ in main.tried[coupling:]]
        wc = main.chosen[0][0] if main.coupled else main.coupling_refused
        jobs = [(trial, baseline, prior, steps, known, load_point, spec, len(main.chosen) - coupling, warm,
                 None if wc is None else dict(wc.result.params), main.start_fitted) for spec in RESPLITS]
        split_causes = _run_resplits(jobs, t_loop > RESPLIT_PARALLEL_MIN_S, progress)
    kept, stab = _stability(main, split_causes)
    cur = main.history[kept]
    findings = _findings(main, kept, stab, split_causes)
    d = Diagnosis(data=str(trial.source), baseline=main.base, findings=findings, unexplained=[], final=cur,
                  grid=grid, history=main.history[: kept + 1], tried=main.tried)
    d.unnamed = _unnamed(main, kept, stab)
    if progress:
        progress("the final model and what it leaves")
    # the reported refits' grid; the residual's search keeps the decisions'
    d.grid = reported_grid(grid, cur, lambda: _prepared(trial, prior, steps, known, n_blocks, True, rest=True))
    undetermined = main.coupled and kept >= 1 and bool(main.chosen[0][0].undetermined)  # (_undetermined_floor)
    copies = "finite_stiffness" in cur.extensions and not undetermined  # (copies_sd: a coupled final model's)
    # independent: side by side where the record is long (the final model's profile, the residual's profiles)
    d.unexplained, (d.baseline_fit, d.final_fit) = fork_map(
        _run_job, [(find_unexplained, (grid, cur)),
                   (_final_fits, (d, (trial, prior, steps, known) if copies else None))],
        grid.t.size >= PARALLEL_MIN_BINS)
    d.baseline_all, d.final_all = d.baseline_fit.params, d.final_fit.params
    _kinematics_floor(d, lambda: floor_reference(trial, steps, prior))
    _undetermined_floor(d, main, kept, bool(steps))
    for i, f in enumerate(findings):
        _as_final(f, d)
        if i < coupling and (d.final_fit.extra.get("undetermined") or not f.uncertainty.get("params_sd")):
            # the coupling whose final model the record does not determine (its fit on a bound, or its
            # refit on all the data ran to one or failed) is named as physics, with "none" beside it, as
            # on a bound (_untested_coupling): velstep1's trimmed copy, the only one of six without it
            _none_beside(f, "the final model is not determined by this record (its fit or its refit on all the "
                            "data runs to a bound or fails; its errors are profile intervals over each "
                            "parameter's domain): this record does not determine the spring")
    d.timings = {"prepare_s": t_prep, "fit_s": t_loop, "total_s": _time.perf_counter() - t0,
                 "n_samples": int(len(trial)), "n_bins": int(grid.t.size), "n_splits": 1 + len(split_causes)}
    return d


def _inputs(trial: TrialData) -> tuple[dict, list, dict, bool]:
    """What every split shares: the file's stated parameters, identify's steps and whole-record fit
    (the starting point), and whether the record is a load-point one."""
    from rig.analysis.identify import decimated
    from rig.kinematics import detect_steps

    known = known_params(trial)
    try:
        small = decimated(trial)
        steps = detect_steps(small)
    except (ValueError, IndexError, ZeroDivisionError):
        small, steps = trial, []
    prior = identify_prior(small, steps)
    load_point = trial.is_load_point or bool(known)
    if known and prior and "stiffness_kN_per_m" in prior:
        prior["stiffness_kN_per_m"] = known["stiffness_kN_per_m"]
    return known, steps, prior, load_point


def _stability(main: _Search, split_causes: list[list[str]]) -> tuple[int, list[float]]:
    """(how many of the main split's causes are named, the fraction of all splits naming each): the
    causes in order until the first that most splits do not name (the coupling is always kept)."""
    n_splits = 1 + len(split_causes)
    stab = [(1 + sum(c.cause in sc for sc in split_causes)) / n_splits for c, _, _ in main.chosen]
    kept = 0
    for i, st in enumerate(stab):
        if st <= MIN_STABILITY and i >= int(main.coupled):
            break
        kept = i + 1
    return kept, stab


def _unnamed(main: _Search, kept: int, stab: list[float]) -> list[dict]:
    """Causes the main split found but most re-splits did not (the record cannot tell them from none),
    and a load-point coupling left out because it worsens the held-out data."""
    out = [{"cause": main.chosen[i][0].cause, "stability": _r(stab[i], 3),
            "gain_pct": _r(main.chosen[i][0].gain_pct, 4)} for i in range(kept, len(main.chosen))]
    if main.coupling_refused is not None:
        c = main.coupling_refused
        out.insert(0, {"cause": c.cause, "stability": None, "gain_pct": _r(c.gain_pct, 4),
                       "why": f"the machine's coupling of a load-point record, but {c.note}"})
    return out


def _findings(main: _Search, kept: int, stab: list[float], split_causes: list[list[str]]) -> list[Finding]:
    """The named causes, each with its evidence, hold-out figures, stability and alternatives, as
    found (single-cause fit on the fit blocks; :func:`_as_final` gives them the final model's values)."""
    grid = main.grid
    out = []
    for i, (c, before, why) in enumerate(main.chosen[:kept]):
        res = c.result
        round_ = main.tried[i]
        others = {o.cause: o for o in round_ if o is not c}
        ev = _evidence(c.cause, res, grid, getattr(c, "info", {}), {k: o.gain_pct for k, o in others.items()},
                       before=before)
        stronger = [o for o in others.values() if o.gain_pct > c.gain_pct + 0.5 and o.note]
        if why:
            ev += f"; {why}"
        if stronger:
            ev += "; not named: " + "; ".join(f"{o.cause} ({o.gain_pct:+.1f}%): {o.note}" for o in stronger)
        alts = _alternatives(grid, c, round_, [sc[i] if i < len(sc) else "none" for sc in split_causes
                                               if c.cause not in sc])
        out.append(Finding(c.cause, {k: res.params[k] for k in CAUSES[c.cause].params}, ev, before.holdout_rms_N,
                           res.holdout_rms_N, c.gain_pct, c.delta_bic,
                           stability=stab[i] if (split_causes or i < int(main.coupled)) else None,
                           alternatives=alts))
        if i < int(main.coupled) and (untested := _untested_coupling(c)):
            _none_beside(out[-1], untested)  # the coupling is named as physics, but the held-out data do not test it
    return out


def _none_alternative() -> dict:
    """The alternative "none": the record explains the held-out data about as well without the cause."""
    return {"cause": "none", "params": {}, "gain_pct": 0.0, "delta_bic": 0.0}


def _none_beside(f: Finding, why: str) -> None:
    """"none" listed beside ``f`` and ``why`` added to its evidence; nothing when "none" is there already."""
    if any(a["cause"] == "none" for a in f.alternatives):
        return
    f.evidence += "; " + why
    f.alternatives.append(_none_alternative())


def _final_models(d: Diagnosis, progress=None) -> None:
    """The reported models: the chosen baseline and final model refitted on every sliding bin (fit
    and hold-out blocks), at the global optimum of the a-b-L valley (profile likelihood over ln L),
    with split-half errors where each half holds steps of its own. The split decides WHICH model
    (hold-out gains); with half of a few steps in the fit blocks, the direct effect A of a three-step
    record moves by +-50 % with the split alone. On ``d.grid``, the reported models' grid
    (:func:`reported_grid`, set by :func:`_diagnose` before this runs, perhaps in a forked helper)."""
    grid, base, cur = d.grid, d.baseline, d.final
    d.baseline_fit = refit_all(grid, base)
    d.final_fit = d.baseline_fit if cur is base else refit_all(grid, cur)
    # the profile of a model with a spring only on small grids: each profile point is a spring fit
    for attr in ("baseline_fit", "final_fit"):
        res = getattr(d, attr)
        if attr == "final_fit" and res is d.baseline_fit:
            continue
        if "L_um" not in res.params or ("finite_stiffness" in res.extensions and grid.t.size > PROFILE_MAX_BINS_SPRING):
            continue
        if progress:
            progress("profile likelihood of L")
        better, iv = profile(grid, res)
        if better is not None and not at_bound(better.params, grid) and _ext_params_plausible(better.extensions,
                                                                                                better.params):
            if "second_state_variable" in better.extensions and "aging_law" not in better.extensions:
                better.params = swap_slower_second(better.params)
            res = better
            _, iv = profile(grid, res)
        if iv is not None:
            res.extra["interval_L_um"] = iv
        setattr(d, attr, res)
        if attr == "baseline_fit" and cur is base:
            d.final_fit = res
    d.baseline_all, d.final_all = d.baseline_fit.params, d.final_fit.params
    if grid.holdout_design.startswith("blocks aligned"):
        # only where each half holds steps of its own: with one to three steps the hold-out blocks are
        # phased so that the step is fitted, and refitted alone they hold no transient to fit
        if progress:
            progress("split-half errors")
        split_sd(grid, base, d.baseline_fit)
        if d.final_fit is not d.baseline_fit:
            split_sd(grid, cur, d.final_fit)


def _final_fits(d: Diagnosis, inputs: tuple | None = None) -> tuple[FitResult, FitResult]:
    """:func:`_final_models` of ``d``: (baseline, final model), refitted on all sliding data; with
    ``inputs`` (the record and what :func:`_grid` takes), the final model's :func:`copies_sd`."""
    _final_models(d)
    if inputs is not None:
        copies_sd(d, *inputs)
    return d.baseline_fit, d.final_fit


# the crops of the copies' floor (copies_sd): the re-splits' (RESPLITS), a few per cent at either end
CROPS = tuple(r["crop"] for r in RESPLITS if "crop" in r)
COPIES_MAX_ROWS = 100_000  # a longer record's copies are made from every n-th row


def _copies(trial: TrialData, steps: list) -> list[TrialData]:
    """The copies of the record whose refits set :func:`copies_sd`: each crop of :data:`CROPS`, and
    the positions moved by half a sampling interval either way in time (a step's timing is known to
    within the interval of the rows about it, :func:`step_timing_s`; from 1 kHz rows 0.5 ms, from
    20 Hz rows 25 ms, at 300 um/s 7.5 um of slip)."""
    t = np.asarray(trial.time_s, dtype=float)
    half = 0.5 * step_timing_s(t, steps)
    if t.size > COPIES_MAX_ROWS:  # every n-th row (a decimation is harmless too): 4 s less per copy of 1 h at 1 kHz
        trial = trial.select(np.arange(t.size) % -(-t.size // COPIES_MAX_ROWS) == 0)
        t = np.asarray(trial.time_s, dtype=float)
    out = [crop(trial, a, b) for a, b in CROPS]
    x = np.asarray(trial.position_um, dtype=float)
    for lag in ((half, -half) if half > 0 else ()):
        c = trial.select(np.ones(t.size, bool))
        c.position_um = np.interp(t - lag, t, x)
        out.append(c)
    return out


def step_timing_s(t: np.ndarray, steps: list) -> float:
    """The longest interval between the rows about a velocity step of ``steps`` (s; 0 without one)."""
    if not steps or t.size < 2:
        return 0.0
    i = np.clip(np.searchsorted(t, [float(st.t_s) for st in steps]), 1, t.size - 1)
    return float(np.max(t[i] - t[i - 1]))


def copies_sd(d: Diagnosis, trial: TrialData, prior: dict, steps: list, known: dict) -> dict:
    """Errors never below what a copy of the record with no other physics does to the final model
    (diagnosis.md, "The answer depends on the physics only"): a crop of a few per cent at either
    end, and the positions moved in time by half the sampling interval about the steps
    (:func:`_copies`). Each copy is prepared afresh (its velocity estimate, steps and hold-out
    blocks its own, as such a file's would be) and the final model refitted on its sliding data from
    the final values; each parameter's floor is its largest move (``res.extra["copies_sd"]``). The
    noise of the 3 % a crop leaves out moves a value by about a fifth of its error; more is the
    kinematics or the start's state, which the Jacobian does not see. Leeman's step (4.35 s before
    it, rows every 10-630 ms): a 3 % crop at the start moves A from 0.0077 +- 0.0005 to 0.0024 (k
    534 -> 192 kN/m), as `rig diagnose` gives on a file cropped so. Basalt velstep7 logged at 50 Hz
    about its step (1 kHz in the file): k 1,190 +- 400 kN/m against 2,410 +- 520 from every row: the
    rise lasts a few ms, and where in the 20 ms between two rows the step fell sets k.

    Run for a final model with the load point's spring (:func:`_diagnose`), whose Jacobian describes
    one corner of a valley the kinematics shape. A rigid final model's kinematics floor is identify's
    disagreement (:func:`_kinematics_floor`); the copies' floor there too widened the simulated rig's
    intervals past honest (paper protocol: A covered in 98 % of 40 trials, against 52 % without; the
    crops move A by 1.6-3.4 of its errors: docs/validation.md, "Coverage")."""
    res = d.final_fit
    if res is None or "jac" not in res.extra:
        return {}
    moves: dict[str, float] = {}
    for c in _copies(trial, steps):
        try:
            # prepared as the reported grid is (a rigid final model's: at rest where the position rests,
            # the measured normals)
            g = reported_grid(_prepared(c, prior, steps, known, 20, True), res,
                              lambda: _prepared(c, prior, steps, known, 20, True, rest=True))
            r = fit(g, res.baseline, res.extensions, res.params, max_nfev=200, mask=g.sliding)
        except (ValueError, ZeroDivisionError, FloatingPointError, IndexError):
            continue
        if not all(np.isfinite(v) for v in r.params.values()) or at_bound(r.params, g):
            continue  # a copy on which the model runs away says nothing about the spread
        for k, v in res.params.items():
            if k in r.params and k not in g.known:
                moves[k] = max(moves.get(k, 0.0), abs(float(r.params[k]) - float(v)))
    res.extra["copies_sd"] = moves
    return moves


def reported_grid(grid: Grid, final: FitResult, at_rest=None) -> Grid:
    """The grid of the reported models. Where the final model is the rigid baseline:

    - the velocity is zero where the measured position rests (``at_rest()``: the record's grid with
      :func:`rig.diagnosis.prep._at_rest`, called only then). The line fit smears each hold and the stick
      before a break-away into sliding (the simulated rig's main job: -4 to +3 um/s through a 2 s
      hold), and the state integrated through them is not the interface's; the misfit after each
      restart then widened the final model's errors three times over (A, B and L covered the truth in
      40 of 40 trials: docs/validation.md, "Coverage"). Only here: on the decisions' grid it led to
      false second-state findings on the paper protocol;
    - where the record's measured normal forces vary, friction is mu times them
      (``Grid.normals_in_model``), as identify divides friction by them (``TrialData.mu``) and as on
      every rig and generated record: on the simulated rig the normal force falls 0.07-0.22 N along each
      slide, which the nominal load read as a slower decay (L +7.5 % on the main job's recipe, +2.2 % on
      the paper protocol; with the normals +3.4 % and +0.1 %).

    The decisions keep diagnosis.md's nominal load (``normal_force_variation`` is named when the held-out
    data gain from it) and the line fit's velocity, and so does a final model with a named cause, whose
    values were found on them (a sensor lag's tau moved by +9 % with the normals, past 25 % on one of
    bench_diagnose's records)."""
    if final.extensions:
        return grid
    if at_rest is not None:
        g = at_rest()
        if int(g.sliding.sum()) >= 10:
            grid = g
    if not (grid.has_normals and grid.normals_vary) or grid.normals_in_model:
        return grid
    return dataclasses.replace(grid, normals_in_model=True)


# the parameters whose errors the kinematics floor bounds (:func:`_kinematics_floor`)
KINEMATICS_FLOOR_PARAMS = ("A_mu", "B_mu")


def _kinematics_floor(d: Diagnosis, reference) -> None:
    """When the final model is the rigid baseline, identify's whole-record fit of the same record
    (``reference()``, called only then: :func:`floor_reference`) is another estimate of the same
    parameters, differing only in the kinematics (the segments' constant velocities and each run's
    fitted starting state, against diagnose's own velocity estimate and the history integrated
    through): the errors of A and B (KINEMATICS_FLOOR_PARAMS) are never below their disagreement
    (``extra["kinematics_sd"]``). The velocity estimate rounds and shifts each step's rise, which
    moves A and B together without showing in the residual (the simulated rig's main job: A +6 % with
    the estimate, -0.8 % with the interface's true velocity at the steps; docs/validation.md,
    "Coverage"). Not L: its two biases (the holds smeared into sliding, the nominal normal load) are
    modelled in the reported grid (:func:`reported_grid`), what is left (+1.0 %) is within its own
    error (1.1 %), and identify's L, five times as precise (+-0.2 %), made the floor the distance to
    the truth itself: L covered it in 39 of 40 main-job trials, 24 of 40 without the floor."""
    res = d.final_fit
    if res is None or res.extensions or res.baseline != "rate_state":
        return
    ref = reference()
    if not ref:
        return
    res.extra["kinematics_sd"] = {k: abs(float(res.params[k]) - float(ref[k])) for k in KINEMATICS_FLOOR_PARAMS
                                  if k in ref and k in res.params and k not in d.grid.known}


def floor_reference(trial: TrialData, steps: list, prior: dict) -> dict:
    """The kinematics floor's reference: identify's whole-record fit at its own resolution
    (WHOLE_RECORD_MAX_POINTS time bins), not the start's coarser PRIOR_MAX_POINTS, whose A is +5-8 %
    off on the simulated rig's main job (identify's own: -2 to +1 %; docs/validation.md,
    "Coverage"); ``prior`` where that fit fails, {} without one."""
    from rig.analysis.identify import WHOLE_RECORD_MAX_POINTS, decimated

    if not prior:
        return {}
    try:
        return identify_prior(decimated(trial), steps, max_points=WHOLE_RECORD_MAX_POINTS) or prior
    except (ValueError, IndexError, ZeroDivisionError):
        return prior


def _undetermined_floor(d: Diagnosis, main: _Search, kept: int, has_steps: bool = True) -> None:
    """When the load point's coupling was found on a bound (:func:`_couple`: the record does not
    determine it), the final model's refit on all sliding data is a second valley of the same
    likelihood, and its Jacobian's errors describe that valley only. Sepiolite velstep2: the
    fit-block fit has A on its floor and k 1163 kN/m, the refit A 0.0118 and k 483 +- 90;
    decimated, k 1221 and 210 +- 80; trimmed, B on its bound: the Jacobian's errors called these
    three answers, where the record gives none. A final model whose refit on all the data ran to a
    bound or failed (:func:`refit_all` keeps the split fit: velstep1 trimmed) has no Jacobian at all.

    Either way the final model is marked undetermined (``extra["undetermined"]``), and each of its
    parameters carries the interval a profile over its domain gives, started from the refit and
    from the coupling's own fit (:mod:`rig.diagnosis.intervals`), the half-width as its error: honest
    about how little the record says (Leeman trimmed past its step: A on its floor, but anything up
    to 0.0019 explains the copy as well). On grids over ``PROFILE_MAX_BINS_UNDETERMINED`` bins, or
    where no profile ends, a parameter's interval is its whole searched domain, and so are A, B, L
    and k's where the record has no velocity step (``has_steps`` False)
    (``extra["domain_whole"]``; the summary says so)."""
    from .fit import covariance

    res = d.final_fit
    if res is None:
        return
    bound = main.coupled and kept >= 1 and bool(main.chosen[0][0].undetermined)
    if not bound and covariance(d.grid, res) is not None:
        return
    names = [k for k in model_params(res.baseline, res.extensions) if k in res.params and k not in d.grid.known]
    res.extra["undetermined"] = list(main.chosen[0][0].undetermined) if bound else names
    # another valley of the same likelihood: the coupling's own fit (on the fit blocks, on a bound);
    # identify's whole-record fit as a third held point moved no interval of velstep2 (4 s more)
    others = [p for p in ([main.chosen[0][0].result.params] if bound else []) if p != res.params]
    # without a velocity change (identify finds no step: a copy trimmed past its only one) the decay
    # the record holds is its start's, whose state the model holds to one number (steady at
    # v_init_um_s) where a start in mid-transient has two: A, B, L and k are not told by a step
    flat = [] if has_steps else [n for n in names if n in CORE_BOUNDED]
    ivs, whole = undetermined_intervals(d.grid, res, [n for n in names if n not in flat], COEF_MAX_MU, others,
                                        PROFILE_MAX_BINS_UNDETERMINED, d.grid.t.size >= PARALLEL_MIN_BINS)
    ivs.update({n: whole_domain(d.grid, n, COEF_MAX_MU) for n in flat})
    res.extra["domain_intervals"] = ivs
    # why each whole domain (the summary's sentence)
    big = d.grid.t.size > PROFILE_MAX_BINS_UNDETERMINED
    res.extra["domain_whole"] = {**{n: "the record is too long for its profile" if big else "no profile fit ended"
                                    for n in whole}, **{n: "the record has no velocity step" for n in flat}}


def _as_final(f: Finding, d: Diagnosis) -> None:
    """A finding's parameters are the final model's; the single-cause fit's values (as found, on the
    fit blocks) beside them in the evidence where they differ by more than 0.5 %."""
    single = {k: _r(v) for k, v in f.params.items()}
    final = {k: _r(d.final_all[k]) for k in single if k in d.final_all}
    moved = {k: v for k, v in single.items() if v is not None and final.get(k) is not None
             and abs(final[k] - v) > 0.005 * abs(v)}
    if moved:
        f.evidence += ("; the parameters are the final model's, refitted on all sliding data (when it was "
                       "found, on the fit blocks: " + ", ".join(f"{k} = {v:.4g}" for k, v in moved.items()) + ")")
    f.params = {k: d.final_all[k] if k in d.final_all else v for k, v in f.params.items()}
    f.uncertainty = uncertainty(d.grid, d.final_fit, list(single))


def _alternatives(grid: Grid, chosen: Candidate, round_: list[Candidate], instead: list[str]) -> list[dict]:
    """Other causes (or "none") that explain the held-out data about as well as the one named: a
    candidate of the same round with at least half its gain that the named one does not beat
    significantly (paired z < MIN_Z), and whatever the re-splits that did not name it named instead."""
    out = []
    for o in round_:
        if o is chosen or o.cause == chosen.cause or o.gain_pct < max(0.5 * chosen.gain_pct, MIN_GAIN_PCT):
            continue
        if paired_z(grid, o.result.pred, chosen.result.pred) < MIN_Z:
            out.append({"cause": o.cause, "params": {k: _r(o.result.params[k]) for k in CAUSES[o.cause].params},
                        "gain_pct": _r(o.gain_pct, 4), "delta_bic": _r(o.delta_bic, 6)})
    seen = {a["cause"] for a in out}
    for cz in instead:
        if cz in seen or cz == "(failed)":
            continue
        seen.add(cz)
        o = next((x for x in round_ if x.cause == cz), None)
        if o is not None:
            out.append({"cause": cz, "params": {k: _r(o.result.params[k]) for k in CAUSES[cz].params},
                        "gain_pct": _r(o.gain_pct, 4), "delta_bic": _r(o.delta_bic, 6)})
        else:
            out.append(_none_alternative() if cz == "none" else {"cause": cz, "params": {}, "gain_pct": None,
                                                                  "delta_bic": None})
    return out


# correlations reported between these parameters (Deliver 2 of issue 20: the a-b-L valley)
CORRELATED = ("A_mu", "B_mu", "L_um")


def split_sd(grid: Grid, split_fit: FitResult, res: FitResult) -> dict:
    """Standard errors from the split: ``split_fit`` (the model on the fit blocks) refitted on the
    hold-out blocks; two independent half-record estimates p1, p2 of a parameter whose whole-record
    estimate has variance ~ (p1 - p2)^2 / 4. Stored in ``res.extra["split_sd"]`` and returned."""
    try:
        other = fit(_swapped(grid), split_fit.baseline, split_fit.extensions, dict(split_fit.params), max_nfev=60)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return {}
    if "second_state_variable" in other.extensions and "aging_law" not in other.extensions:
        swap_slower_second(other.params)
    out = {k: abs(float(other.params[k]) - float(v)) / 2.0 for k, v in split_fit.params.items()
           if k in other.params and np.isfinite(other.params[k]) and k not in grid.known}
    res.extra["split_sd"] = out
    return out


def uncertainty(grid: Grid, res: FitResult, names: list[str] | None = None) -> dict:
    """``params_sd`` (one standard error per parameter, from the Jacobian with the residual's
    autocorrelation), ``intervals`` for the slip distances (the +-1 sd interval in ln L, skewed as
    the likelihood in L is) and ``correlation`` of A, B and L, for ``names`` (all by default)."""
    from .fit import covariance

    if res.extra.get("undetermined"):  # :func:`_undetermined_floor`: the profiles over the domain, or nothing
        div = {n: v for n, v in res.extra.get("domain_intervals", {}).items() if names is None or n in names}
        return {"params_sd": {n: _r((hi - lo) / 2.0) for n, (lo, hi) in div.items()},
                "intervals": {n: [_r(lo), _r(hi)] for n, (lo, hi) in div.items()}} if div else {}
    cv = covariance(grid, res)
    if cv is None:
        return {}
    nm, vals, cov = cv
    sd_j = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # never below the split-half spread (:func:`split_sd`): errors in the kinematics (a step's rise
    # as the line fit sees it) move A and B without showing in the residual
    spl, kin = res.extra.get("split_sd", {}), res.extra.get("kinematics_sd", {})
    crop = res.extra.get("copies_sd", {})  # nor below the move of a copy with no other physics (:func:`copies_sd`)
    sd = np.array([max(sd_j[i], spl.get(n, 0.0), kin.get(n, 0.0), crop.get(n, 0.0)) for i, n in enumerate(nm)])
    # the errors the kinematics floor sets (the summary says so: they are a disagreement, not a fit's)
    res.extra["kinematics_set"] = [n for i, n in enumerate(nm) if kin.get(n, 0.0) > max(sd_j[i], spl.get(n, 0.0))]
    res.extra["copies_set"] = [n for i, n in enumerate(nm) if crop.get(n, 0.0) > max(sd_j[i], spl.get(n, 0.0),
                                                                                   kin.get(n, 0.0))]
    want = nm if names is None else [n for n in names if n in nm]
    out: dict = {"params_sd": {n: _r(sd[nm.index(n)]) for n in want}}
    iv = {}
    prof = res.extra.get("interval_L_um")
    if prof is not None and "L_um" in want:
        # from the profile likelihood (fit.profile), widened in ln L as the split-half spread widens sd
        v, i = vals[nm.index("L_um")], nm.index("L_um")
        f = sd[i] / sd_j[i] if sd_j[i] > 0 else 1.0
        iv["L_um"] = [_r(v * (prof[0] / v) ** f), _r(v * (prof[1] / v) ** f)]
    for n in want:
        if n in ("L_um", "L2_um") and n not in iv and vals[nm.index(n)] > 0:
            v, s = vals[nm.index(n)], sd[nm.index(n)]
            e = min(s / v, 30.0)  # (a distance the record does not determine: no overflow)
            iv[n] = [_r(v * math.exp(-e)), _r(v * math.exp(e))]
    if iv:
        out["intervals"] = iv
    cn = [n for n in CORRELATED if n in nm and n in want]
    if len(cn) >= 2:
        corr = {}
        for a_i, a in enumerate(cn):
            for b in cn[a_i + 1:]:
                i, j = nm.index(a), nm.index(b)
                den = sd_j[i] * sd_j[j]
                corr[f"{a},{b}"] = _r(cov[i, j] / den, 4) if den > 0 else None
        out["correlation"] = corr
    return out


def refit_all(grid: Grid, res: FitResult) -> FitResult:
    """``res``'s model fitted on all sliding bins, from ``res``'s own parameters (the fit can only
    improve on its start; a fit that fails or runs away keeps them, evaluated on all bins: a second
    state longer than the record can tell from a drift, ``Grid.max_state_um``, is one)."""
    keep = evaluate(grid, res.baseline, res.extensions, res.params)
    try:
        r = fit(grid, res.baseline, res.extensions, res.params, max_nfev=200, mask=grid.sliding)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return keep
    p = dict(r.params)
    if (not np.all(np.isfinite(list(p.values()))) or at_bound(p, grid)
            or _coefs_too_large(p) or p.get("L2_um", 0.0) > grid.max_state_um
            or not _ext_params_plausible(res.extensions, p)):
        return keep  # ran away on the joined data: keep the validated split fit
    if "second_state_variable" in res.extensions and "aging_law" not in res.extensions:
        L1 = r.params.get("L_um")
        swap_slower_second(r.params)
        if r.params.get("L_um") != L1:
            r.extra.pop("jac", None)  # its columns are in the other order: no standard errors
    return r


# ---------------------------------------------------------------------------
# structure no extension explains
# ---------------------------------------------------------------------------
def _binned_gain(grid: Grid, r: np.ndarray, q: np.ndarray, nb: int = 30):
    """Hold-out gain (%) of a step function of q (quantile bins) fitted to r on the fit blocks."""
    fm, hm = grid.fit_mask(), grid.holdout_mask()
    qs = np.quantile(q, np.linspace(0, 1, nb + 1))
    qs = np.unique(qs)
    if qs.size < 4:
        return 0.0, None, 0.0
    b = np.clip(np.searchsorted(qs, q, side="right") - 1, 0, qs.size - 2)
    nbin = qs.size - 1
    w = grid.w
    num = np.bincount(b[fm], weights=(w * r)[fm], minlength=nbin)
    den = np.bincount(b[fm], weights=w[fm], minlength=nbin)
    prof = np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    fit_h = prof[b]
    before = float(np.sum((w * r * r)[hm]) + grid.ss_within[hm].sum())
    after = float(np.sum((w * (r - fit_h) ** 2)[hm]) + grid.ss_within[hm].sum())
    n = max(float(w[hm].sum()), 1.0)
    rb, ra = math.sqrt(before / n), math.sqrt(after / n)
    z = paired_z(grid, grid.F_mean - r, grid.F_mean - r + fit_h)
    return 100.0 * (rb - ra) / rb, prof, z


def _joint_profile_gain(grid: Grid, cur: FitResult, q: np.ndarray, nb: int = 20, rounds: int = 2,
                        max_nfev: int = 40):
    """Hold-out gain (%) and z of the current model plus a free step-function profile in q, the
    two fitted together on the fit blocks (alternately: profile of the residual, model refit to the
    data minus the profile), so that the model's own parameters cannot hide the structure."""
    fm = grid.fit_mask()
    qs = np.unique(np.quantile(q[grid.sliding], np.linspace(0, 1, nb + 1)))
    if qs.size < 4:
        return 0.0, 0.0
    b = np.clip(np.searchsorted(qs, q, side="right") - 1, 0, qs.size - 2)
    nbin = qs.size - 1
    w = grid.w
    params, pred = cur.params, cur.pred
    prof = np.zeros(nbin)
    for _ in range(rounds):
        r = grid.F_mean - pred
        num = np.bincount(b[fm], weights=(w * r)[fm], minlength=nbin)
        den = np.bincount(b[fm], weights=w[fm], minlength=nbin)
        prof = np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
        g2 = dataclasses.replace(grid, F_mean=grid.F_mean - prof[b])
        res = fit(g2, cur.baseline, cur.extensions, params, max_nfev=max_nfev)
        params, pred = res.params, res.pred
    final = pred + prof[b]
    after = evaluate(grid, cur.baseline, cur.extensions, params, pred=final)
    gain = 100.0 * (cur.holdout_rms_N - after.holdout_rms_N) / cur.holdout_rms_N
    return gain, paired_z(grid, cur.pred, final)


def find_unexplained(grid: Grid, cur: FitResult) -> list[dict]:
    holdout_rms_N = cur.holdout_rms_N
    if grid.time_block is not None and grid.holdout_design.startswith("blocks aligned"):
        # a free profile in time or slip cannot reach a held-out segment that is a whole step (no
        # fitted bin falls in it), so the profiles are judged on the 20 equal time blocks, as the
        # linear-drift check is
        grid = dataclasses.replace(grid, block=grid.time_block)
        cur = evaluate(grid, cur.baseline, cur.extensions, cur.params, pred=cur.pred)
    r = grid.F_mean - cur.pred
    out = []
    qs = {"time": grid.t, "slip": slip_of(grid), "position": grid.x, "velocity": grid.v}
    if grid.has_normals and grid.normals_vary:
        qs["normal_force"] = grid.N_tot
    scores = {}
    # the stiffness solver is costly: one alternation with few evaluations is enough to rank quantities
    rounds, nfev = (1, 15) if "finite_stiffness" in cur.extensions else (2, 40)
    for name, q in qs.items():
        # a velocity profile is a non-log-linear steady-state curve: a few bins in ln v (with as many
        # bins as segments, a staircase visiting each speed once could mimic anything in time)
        if name == "velocity":
            scores[name] = _joint_profile_gain(grid, cur, np.log(np.maximum(q, 1e-3)), nb=6, rounds=rounds,
                                               max_nfev=nfev)
        else:
            scores[name] = _joint_profile_gain(grid, cur, q, rounds=rounds, max_nfev=nfev)
    # periodic in time (frequency)
    tp = time_periodogram(grid, r)
    if tp is not None:
        P, pw, P0, zp = tp
        k = 2 * math.pi / P0
        X = np.vstack([np.sin(k * grid.t), np.cos(k * grid.t)]).T
        fm = grid.fit_mask()
        sw = np.sqrt(grid.w)
        co, *_ = np.linalg.lstsq((X * sw[:, None])[fm], (r * sw)[fm], rcond=None)
        fitv = X @ co
        hm = grid.holdout_mask()
        w = grid.w
        before = float(np.sum((w * r * r)[hm]) + grid.ss_within[hm].sum())
        after = float(np.sum((w * (r - fitv) ** 2)[hm]) + grid.ss_within[hm].sum())
        g = 100.0 * (math.sqrt(before) - math.sqrt(after)) / math.sqrt(before)
        z = paired_z(grid, grid.F_mean - r, grid.F_mean - r + fitv)
        scores["frequency"] = (g, z)
        freq_info = {"period_s": _r(P0), "amplitude_N": _r(float(np.hypot(*co)))}
    else:
        freq_info = {}
    ok = {k: v for k, v in scores.items() if v[0] >= UNEXPLAINED_MIN_GAIN_PCT and v[1] >= MIN_Z}
    if "frequency" in ok and freq_info["amplitude_N"] / math.sqrt(2.0) < UNEXPLAINED_MIN_EFFECT * cur.holdout_rms_N:
        del ok["frequency"]
    if not ok:
        return []
    best = max(ok, key=lambda k: ok[k][0])
    g, z = ok[best]
    ties = [k for k in scores if k != best and k != "frequency" and abs(scores[k][0] - g) <= 0.05 * abs(g)]
    tie_note = (f" ({', '.join(ties)} {'rank' if len(ties) > 1 else 'ranks'} the same: in this record they "
                "follow each other and cannot be told apart)") if ties else ""
    ent = {"follows": best,
           "evidence": (f"the final model's residual follows {best.replace('_', ' ')}: a profile in {best} fitted on "
                        f"the fit blocks lowers the hold-out RMS by {g:.1f}% (z = {z:.1f}){tie_note}; no catalogue "
                        "extension explains it"),
           "holdout_rms_N": _r(holdout_rms_N),
           "gain_pct_if_modelled": _r(g, 4),
           "z": _r(z, 4),
           "gain_pct_by_quantity": {k: _r(v[0], 4) for k, v in scores.items()}}
    if best == "frequency":
        ent.update(freq_info)
        ent["evidence"] = (f"the residual oscillates in time with period {freq_info['period_s']:.3g} s, amplitude "
                           f"{freq_info['amplitude_N']:.2g} N (hold-out gain {g:.1f}% if modelled); not periodic in "
                           "position, so not the surface; no catalogue extension explains it")
    out.append(ent)
    return out
