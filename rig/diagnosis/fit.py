"""Least-squares fits of a model (baseline + extensions) against the measured friction force.

The fit minimises the raw-sample sum of squares of the friction residual on
the *fit* blocks of the record (even-numbered blocks of :mod:`.prep`); the
*hold-out* blocks (odd) are only predicted. Parameters that must be positive
(``L_um``, ``L2_um``, ``tau_s``, ``delay_s``, ``stiffness_kN_per_m``,
``wavelength_um``) are fitted in ``ln`` (rig.model.spec.PARAMS declares them, rig.fitting fits); the periodic term is fitted as a
sine and cosine amplitude (linear) and reported as ``amplitude_mu`` and
``phase_rad``. All other parameters are fitted as they are, scaled to O(1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from rig.model.forward import as_model, force_sensitivities, has_sensitivities, predict_force
from rig.fitting import Param, ParamSet, least_squares_fit
from rig.fitting.stats import comparison_n_eff, inflated_cov, information_criterion, time_cell_s
from rig.model.spec import PARAMS, PLAUSIBLE, model_params
from .prep import Grid

# the periodic term is fitted as a cosine and a sine amplitude (linear), reported as
# amplitude_mu and phase_rad; every other parameter as rig.model.spec.PARAMS declares it
_REPARAM = {"_pc": Param("_pc", "1", -0.5, 0.5, scale=1e-3), "_ps": Param("_ps", "1", -0.5, 0.5, scale=1e-3)}
_NOT_CHECKED = ("mu0", "amplitude_mu", "phase_rad", "v_init_um_s")  # v_init: a nuisance (the start)
# multistart: with more ranked starts than this, each gets a first pass of FIRST_PASS_NFEV evaluations
# and only the best POLISH_KEEP distinct ones are fitted in full
POLISH_KEEP = 2
FIRST_PASS_NFEV = 20
# the periodic term's linear amplitudes under rig.model.forward.force_sensitivities' names:
# _pc = amplitude sin(phase) multiplies cos(2 pi x / wavelength), _ps = amplitude cos(phase) sin(...)
_SENS_NAME = {"_pc": "periodic_cos_mu", "_ps": "periodic_sin_mu"}


def param(name: str, grid: Grid | None = None, spring: bool = False) -> Param:
    """The fitted parameter ``name`` (unit, bounds, scaling) of rig.model.spec.PARAMS; with a
    ``grid``, the first state's ``L_um`` is bounded by the record (``Grid.max_state_um``), and the
    stiffness from below (``Grid.stiffness_floor_kN_per_m``). With a
    ``spring`` (finite_stiffness), ``A_mu`` is at least its plausible floor (PLAUSIBLE): the
    spring-slider's interface velocity is set by the direct effect, ``v = V0 exp((F/N - ...)/A)``
    (eq. 5), and as A -> 0 it is not determined (the integration then reverses the interface)."""
    if name in _REPARAM:
        return _REPARAM[name]
    p = Param.of(name, PARAMS[name])
    if spring and name == "A_mu":
        p = replace(p, lo=max(p.lo, PLAUSIBLE["A_mu"].lo))
    if name == "stiffness_kN_per_m" and grid is not None and grid.stiffness_floor_kN_per_m > p.lo:
        p = replace(p, lo=grid.stiffness_floor_kN_per_m)  # what the record's slope allows (causes.py)
    if name == "L_um" and grid is not None:
        hi = grid.max_state_um
        if math.isfinite(hi) and 10.0 * p.lo < hi < p.hi:
            p = replace(p, hi=hi)
    return p


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
    noise_corr: float = 1.0          # Grid.noise_corr: raw samples per independent one

    @property
    def holdout_rms_N(self) -> float:
        return math.sqrt(self.sse_hold / max(self.n_hold, 1))

    @property
    def fit_rms_N(self) -> float:
        return math.sqrt(self.sse_fit / max(self.n_fit, 1))


def delta_bic(grid: Grid, cur: FitResult, res: FitResult) -> float:
    """``res``'s Gaussian BIC minus ``cur``'s on the fit blocks, ``n_eff ln(SSE/n) + k ln n_eff``
    (rig.fitting.stats.information_criterion), on one effective sample size: the better fit's residual in
    time along the two predictions' difference (rig.fitting.stats.comparison_n_eff), so that the
    difference weighs the record's time, not its rows (issue 20 Deliver 3), and another effect
    that both models leave in the residual does not hide this one."""
    fm = grid.fit_mask()
    better, worse = (res, cur) if res.sse_fit < cur.sse_fit else (cur, res)
    ne = math.nan
    if fm.any() and np.all(np.isfinite(better.pred[fm])) and np.all(np.isfinite(worse.pred[fm])):
        t = grid.t[fm]
        ne = comparison_n_eff(t, grid.count[fm], (grid.F_mean - worse.pred)[fm], (grid.F_mean - better.pred)[fm],
                              time_cell_s(t))
    if not math.isfinite(ne):
        ne = max(better.n_fit / max(better.noise_corr, 1.0), 1.0)
    return (information_criterion(res.sse_fit, res.n_fit, ne, res.n_par)
            - information_criterion(cur.sse_fit, cur.n_fit, ne, cur.n_par))


def _free_names(baseline: str, extensions: list[str], init: dict | None = None,
                known: dict | None = None) -> list[str]:
    names = [nm for nm in model_params(baseline, extensions) if nm not in (known or {})]
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


def _fold(p: dict) -> dict:
    p = dict(p)
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


def _model(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float]):
    """The model as the forward model runs it on ``grid``: with the measured normal forces where
    the grid says every model has them (``Grid.normals_in_model``)."""
    if grid.normals_in_model and "normal_force_variation" not in extensions:
        extensions = list(extensions) + ["normal_force_variation"]
    return as_model(baseline, extensions, params)


def predict(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float]) -> np.ndarray:
    """The forward model (rig.model.forward) on the grid; ``v_init_um_s`` in params is the
    speed whose steady state the record starts in."""
    v_init = params.get("v_init_um_s")
    return predict_force(_model(grid, baseline, extensions, params), grid.t, grid.x, grid.v, grid.N_tot, grid.N_nom,
                         None if v_init is None else float(v_init))


def evaluate(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float],
             pred: np.ndarray | None = None, nfev: int = 0) -> FitResult:
    kn = {k: v for k, v in grid.known.items() if k in model_params(baseline, extensions)}
    if any(params.get(k) != v for k, v in kn.items()):  # a parameter the file states is never another
        params, pred = {**params, **kn}, None
    if pred is None:
        pred = predict(grid, baseline, extensions, params)
    r2 = grid.count * (grid.F_mean - pred) ** 2 + grid.ss_within
    fm = grid.fit_mask()
    hm = grid.holdout_mask()
    bad = not np.all(np.isfinite(pred))
    sse_f = float(r2[fm].sum()) if not bad else math.inf
    sse_h = float(r2[hm].sum()) if not bad else math.inf
    # the start's state (``v_init_um_s``), where it is fitted, is a parameter too
    npar = len([nm for nm in model_params(baseline, extensions) if nm not in grid.known]) + ("v_init_um_s" in params)
    return FitResult(baseline, list(extensions), dict(params), pred, sse_f, sse_h, int(grid.count[fm].sum()),
                     int(grid.count[hm].sum()), npar, nfev, noise_corr=grid.noise_corr)


def fit(grid: Grid, baseline: str, extensions: list[str], init: dict[str, float],
        max_nfev: int = 400, mask: np.ndarray | None = None) -> FitResult:
    """Least-squares fit of all the model's parameters from ``init`` on the fit blocks (or ``mask``)."""
    names = _free_names(baseline, extensions, init, grid.known)
    internal = _from_params(init)
    internal.update({k: v for k, v in grid.known.items() if k in model_params(baseline, extensions)})
    pset = ParamSet([param(nm, grid, "finite_stiffness" in extensions) for nm in names])
    fixed = {k: v for k, v in internal.items() if k not in names and not k.startswith("_")
             and k not in ("amplitude_mu", "phase_rad")}
    if "position_periodic" not in extensions:
        fixed.pop("phase_rad", None)
    m = grid.fit_mask() if mask is None else mask
    w = np.sqrt(grid.count[m])
    Fm = grid.F_mean[m]

    jac, sens = None, None
    if has_sensitivities(baseline, extensions):
        # exact Jacobian along the same integration (rig.model.forward.force_sensitivities): one
        # kernel pass instead of one model evaluation per parameter; the rest by differences
        sens_names = [_SENS_NAME.get(nm, nm) for nm in names]

        def sens(free: dict) -> tuple[np.ndarray, np.ndarray]:
            p = _fold({**fixed, **free})
            v_init = p.get("v_init_um_s")
            F, cols = force_sensitivities(_model(grid, baseline, extensions, p), grid.t, grid.x, grid.v, grid.N_tot,
                                          grid.N_nom, sens_names, None if v_init is None else float(v_init))
            J = np.full((Fm.size, len(names)), np.nan)
            for j, nm in enumerate(sens_names):
                if nm in cols:
                    J[:, j] = -w * cols[nm][m]
            return F, J

        def jac(free: dict) -> np.ndarray:
            hit = cached.pop(_key(free), None)
            return hit if hit is not None else sens(free)[1]

    # with a spring, the force of the sensitivity pass is the plain pass's, bit for bit (the same kernel,
    # rig.model.loading.stiff_series_sens) at 1.0-1.2x its cost: each residual keeps its Jacobian for the
    # step's jac call at the same point (one pass per step, not two: velstep2's coupled fits, 19,446 bins)
    merged = sens is not None and "finite_stiffness" in extensions and "time_delay" not in extensions
    cached: dict = {}

    def resid(free: dict) -> np.ndarray:
        p = _fold({**fixed, **free})
        try:
            if merged:
                pr, J = sens(free)
                cached.clear()
                cached[_key(free)] = J
            else:
                pr = predict(grid, baseline, extensions, p)
        except (ValueError, ZeroDivisionError, OverflowError):
            return np.full(Fm.size, 1e6)
        r = w * (Fm - pr[m])
        if not np.all(np.isfinite(r)):
            return np.full(Fm.size, 1e6)
        return r

    out = least_squares_fit(resid, pset, [internal], max_nfev=max_nfev, diff_step=1e-6, xtol=1e-8, ftol=1e-9,
                            x_scale=1.0, jac=jac)
    free = out.params if out is not None else pset.unpack(np.clip(pset.pack(internal), *pset.bounds()))
    nfev = out.nfev if out is not None else 0
    res = evaluate(grid, baseline, extensions, _fold({**fixed, **free}), nfev=nfev)
    if out is not None and out.jac is not None:
        res.extra["jac"] = (pset, np.asarray(out.extra["z"]), np.asarray(out.jac), np.asarray(out.residuals), m)
    return res


def _key(free: dict) -> tuple:
    """A parameter point as a dict key (the exact values: a Jacobian is reused only at its own point)."""
    return tuple(sorted(free.items()))


def _cov_internal(grid: Grid, res: FitResult):
    """(pset, z, covariance in the internal variables, its ratio to the white-noise one per parameter, s^2).

    rig.fitting.stats.inflated_cov: the white-noise covariance of the fit's Jacobian, each
    parameter's variance inflated by ``n / n_eff`` of its score in time (the residual weighted by
    where the parameter's information is: the effective sample size of Deliver 3 of issue 20,
    computed as identify's whole-record fit computes it)."""
    if "jac" not in res.extra:
        return None
    pset, z, J, r, m = res.extra["jac"]
    n, p = J.shape
    if n <= p + 1:
        return None
    mm = m if m is not None and np.size(m) == grid.t.size else grid.fit_mask()
    if int(mm.sum()) != n:
        return None
    r = _without_normal_wander(grid, res, r, mm)
    try:
        cz, tau, s2 = inflated_cov(J, r, grid.t[mm])
    except (np.linalg.LinAlgError, ValueError):
        return None
    return pset, z, cz, tau, s2


def _without_normal_wander(grid: Grid, res: FitResult, r: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The fit's weighted residual ``r`` (on ``mask``) less its least-squares part along the friction's
    share of the measured normal forces' departure from the nominal, ``pred (N1 + N2 - 2 N_nom) /
    (2 N_nom)``, where the record's normals vary and the model holds friction to the nominal load: the
    slow wander of a regulated normal load (generated records: +-0.5 %, 1.3 cycles a record) is not
    noise about A, B and L, and counted as such it widened their errors twice over (pull 0.5; docs/
    validation.md, "Coverage"). The errors of the model then are those of the friction coefficient over
    the measured normals, as identify's whole-record fit computes them."""
    if not (grid.has_normals and grid.normals_vary) or "normal_force_variation" in res.extensions \
            or grid.normals_in_model:
        return r
    w = np.sqrt(grid.count[mask])
    q = w * res.pred[mask] * (grid.N_tot[mask] / (2.0 * grid.N_nom) - 1.0)
    qq = float(np.dot(q, q))
    if not qq > 0 or q.size != r.size:
        return r
    return r - (float(np.dot(q, r)) / qq) * q


def covariance(grid: Grid, res: FitResult) -> tuple[list[str], np.ndarray, np.ndarray] | None:
    """(names, values, covariance of the values) of ``res``'s free parameters from the Jacobian of
    its fit (:func:`_cov_internal`: cluster-robust in time). The periodic term's internal
    sine/cosine amplitudes are left out. None without a Jacobian."""
    ci = _cov_internal(grid, res)
    if ci is None:
        return None
    pset, z, cz, _, _ = ci
    # internal (ln or scaled) -> the parameter's unit, to first order
    d = np.array([prm.to_value(float(zi)) if prm.log else prm.scale for prm, zi in zip(pset.params, z)])
    cov = cz * np.outer(d, d)
    names = [prm.name for prm in pset.params]
    vals = np.array([prm.to_value(float(zi)) for prm, zi in zip(pset.params, z)])
    keep = [i for i, nm in enumerate(names) if not nm.startswith("_")]
    return [names[i] for i in keep], vals[keep], cov[np.ix_(keep, keep)]


def cost_at(grid: Grid, baseline: str, extensions: list[str], params: dict[str, float]) -> float:
    """Fit-block SSE of a parameter set (for choosing among starting points)."""
    return evaluate(grid, baseline, extensions, params).sse_fit


def multistart(grid: Grid, baseline: str, extensions: list[str], starts: list[dict[str, float]],
               keep: int = 2, max_nfev: int = 400, must: list[dict[str, float]] | None = None,
               plausible=None, fmap=None) -> FitResult:
    """Rank starting points by cost, fit the best ``keep`` of them and every start of ``must``
    (e.g. identify's whole-record fit, the current model), return the best fit: of those off
    their bounds and, with ``plausible`` (params -> bool), physical, the one of least cost.
    ``fmap(args_list)``: the full fits :func:`fit` ``(*args)``, in order (independent: the caller
    may run them on several cores); in this process by default."""
    costs = []
    for s in starts:
        try:
            c = cost_at(grid, baseline, extensions, s)
        except (ValueError, ZeroDivisionError):
            c = math.inf
        costs.append(c if math.isfinite(c) else math.inf)
    ranked = [starts[i] for i in np.argsort(costs)[:keep]]
    if len(ranked) > POLISH_KEEP:
        # a cheap first pass, then polish: starts that run into the same minimum (the second state's
        # five on the 2.8 h sepiolite record all ended at one cost, each after 120 evaluations) are
        # polished once; the starts of ``must`` are always fitted in full
        first = sorted((fit(grid, baseline, extensions, st, max_nfev=FIRST_PASS_NFEV) for st in ranked),
                       key=lambda r: r.sse_fit)
        ranked = []
        for r in first:
            if len(ranked) < POLISH_KEEP and not any(_same_point(r.params, q) for q in ranked):
                ranked.append(r.params)
    args = [(grid, baseline, extensions, st, max_nfev) for st in ranked + list(must or [])]
    best, best_rank = None, None
    for r in (fmap(args) if fmap is not None and len(args) > 1 else [fit(*a) for a in args]):
        r.extra["at_bound"] = at_bound(r.params, grid)
        r.extra["implausible"] = plausible is not None and not plausible(r.params)
        rank = (r.extra["at_bound"] or r.extra["implausible"], r.extra["at_bound"], r.sse_fit)
        if best is None or rank < best_rank:
            best, best_rank = r, rank
    return best


def _same_point(a: dict, b: dict, rel: float = 1e-2) -> bool:
    """Two parameter sets equal to ``rel`` in every parameter (the same minimum)."""
    return all(abs(a[k] - b[k]) <= rel * max(abs(a[k]), abs(b[k]), 1e-12) for k in a if k in b)


def at_bound(params: dict, grid: Grid | None = None) -> bool:
    """True when a fitted parameter sits on its bound (the fit then stands in for something else);
    with a ``grid``, its bounds for that record (``param``)."""
    for nm, v in params.items():
        if nm not in PARAMS or nm in _NOT_CHECKED:
            continue
        if nm == "A_mu" and v <= 1e-9:
            continue
        if param(nm, grid).at_bound(v):
            return True
    return False


PROFILE_POINTS = 7      # ln L grid of the profile likelihood (Deliver 2 of issue 20)
PROFILE_SPAN = 8.0      # from L / span to L * span (within the parameter's bounds)
PROFILE_NFEV = 12       # evaluations per profile point (continued from its neighbour: a few suffice)


def profile(grid: Grid, res: FitResult, name: str = "L_um", mask: np.ndarray | None = None):
    """Profile likelihood of ``res``'s model along ln ``name`` (the flat a-b-L valley): at each of
    PROFILE_POINTS values the other parameters are refitted with ``name`` held (continuation from
    the neighbouring point, outwards from the fit). Returns ``(better, interval)``: a fit polished
    from the best profile point when that point lies below ``res`` (the global optimum along the
    valley that a local search missed; else None), and the +-1 sd interval of ``name`` where the
    profile's rise stays under one residual variance (``s^2``, with the autocorrelation
    inflation of :func:`covariance`), interpolated in ln ``name`` (None without a Jacobian)."""
    from dataclasses import replace as _replace

    if name not in res.params or "jac" not in res.extra:
        return None, None
    pset, z, J, r, m0 = res.extra["jac"]
    m = m0 if mask is None else mask
    ci = _cov_internal(grid, res)
    if ci is None or name not in pset.names:
        return None, None
    # one residual variance, scaled as the covariance scales this parameter's (robust / white)
    s2 = ci[4] * float(ci[3][pset.names.index(name)])
    prm = param(name, grid)
    v0 = float(res.params[name])
    lo, hi = max(prm.lo * 1.0001, v0 / PROFILE_SPAN), min(prm.hi / 1.0001, v0 * PROFILE_SPAN)
    if not lo < v0 < hi:
        return None, None
    grid_v = np.exp(np.linspace(math.log(lo), math.log(hi), PROFILE_POINTS))
    sse0 = float(np.dot(r, r))
    pts = {v0: (sse0, res.params)}
    for side in (grid_v[grid_v > v0], grid_v[grid_v < v0][::-1]):
        start = dict(res.params)
        for v in side:
            g = _replace(grid, known={**grid.known, name: float(v)})
            rv = fit(g, res.baseline, res.extensions, dict(start, **{name: float(v)}), max_nfev=PROFILE_NFEV,
                     mask=m)
            if "jac" not in rv.extra or not np.isfinite(rv.sse_fit):
                break
            sse = float(np.dot(rv.extra["jac"][3], rv.extra["jac"][3]))
            pts[float(v)] = (sse, rv.params)
            start = rv.params
    vs = np.array(sorted(pts))
    ss = np.array([pts[v][0] for v in vs])
    better = None
    k = int(np.argmin(ss))
    if ss[k] < sse0 - 1e-9 * max(sse0, 1.0):
        better = fit(grid, res.baseline, res.extensions, dict(pts[vs[k]][1]), mask=m)
        if not better.sse_fit < res.sse_fit:
            better = None
    if better is not None:
        return better, None  # the caller reports from the better fit (its own profile, if asked again)
    rise = ss - ss.min()
    lv = np.log(vs)
    i0 = int(np.argmin(ss))
    # sqrt(rise) is nearly linear in ln L near the minimum: interpolated so, a coarse grid does not narrow
    # the interval; None: flat to the end of the profile, the interval is open on that side
    lo_e, hi_e = (profile_crossing(lv, rise, s2, idx) for idx in (list(range(i0, -1, -1)), list(range(i0, vs.size))))
    lo_e, hi_e = (None if e is None else float(math.exp(e)) for e in (lo_e, hi_e))
    return None, (lo_e if lo_e is not None else float(vs[0]), hi_e if hi_e is not None else float(vs[-1]),
                  lo_e is None, hi_e is None)


def profile_crossing(xs: np.ndarray, rise: np.ndarray, thr: float, idx: list[int]) -> float | None:
    """Where a profile's sqrt(rise) (its sum of squares above the lowest point) crosses sqrt(``thr``),
    walking the indices ``idx`` out from the minimum: linear interpolation in ``xs`` (the rise is
    quadratic near the minimum, so its root is nearly linear). None where it never does."""
    q, q1 = np.sqrt(np.maximum(rise, 0.0)), math.sqrt(thr)
    for a, b in zip(idx[:-1], idx[1:]):
        if q[b] > q1 >= q[a]:
            return float(xs[a] + (q1 - q[a]) / (q[b] - q[a]) * (xs[b] - xs[a]))
    return None
