"""Steady-state friction against velocity (the Stribeck curve), Dupont & Dunlap section 4.1.

From a stepped-velocity pass (Fig. 5), on the paper's 25 Hz (block means of a denser
record, :func:`at_level_rate`): the friction of each level is the mean of
``mu`` over the last 50 µm of displacement at that velocity; levels come from the
log's ``level`` events when present (their ``window_*`` times), else from the
velocity steps detected in the data (:func:`rig.kinematics.detect_steps`); a level is a
stretch of one velocity, so consecutive planned levels of the same velocity are one
(:func:`_merge_equal`), as the data show them. Levels reached
by an increase of velocity form the *up* branch, the others the *down* branch
(kept apart, as in Fig. 6: friction after increases exceeded friction after
decreases). Eq. (7), ``mu_ss = mu0 + (A - B) ln(v/V0)``, is fitted by least
squares on the semi-log axes (Fig. 7), to all levels and to each branch; the
errors are the regression's standard errors (residual variance times
``(X^T X)^-1``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.analysis.report import rounded as _r
from rig.kinematics import detect_steps
from rig.data import TrialData, atomic_write_text
from rig.model.friction import V0_UM_S

SCHEMA = "rig.stribeck/1"


#: levels are found and averaged on the paper's 25 Hz (block means of denser records, as the
#: log's /log25 channel is): a 1 kHz and a 25 Hz copy of one trial give the same levels
LEVEL_RATE_HZ = 25.0
MIN_WINDOW_SAMPLES = 3


def at_level_rate(trial: TrialData) -> TrialData:
    """``trial`` as block means at :data:`LEVEL_RATE_HZ` when it is denser (else unchanged).
    Step detection on the 1 kHz record missed the short fast levels (200 µm/s lasts 1.25 s)
    that the 25 Hz block means of the same trial show."""
    t = np.asarray(trial.time_s, float)
    if t.size < 4:
        return trial
    k = int(round(1.0 / (LEVEL_RATE_HZ * float(np.median(np.diff(t))))))
    if k < 2:
        return trial
    m = (t.size // k) * k

    def bm(a):
        return None if a is None else np.asarray(a, float)[:m].reshape(-1, k).mean(axis=1)

    return TrialData(time_s=bm(trial.time_s), position_um=bm(trial.position_um), friction_N=bm(trial.friction_N),
                     normal_1_N=bm(trial.normal_1_N), normal_2_N=bm(trial.normal_2_N),
                     position_ref_um=bm(trial.position_ref_um), valve_cmd=None, extra={},
                     metadata=dict(trial.metadata), events=list(trial.events or []), source=trial.source,
                     warnings=list(trial.warnings))


def _merge_equal(evs: list[dict], rel: float = 0.01) -> tuple[list[dict], list[dict]]:
    """Consecutive level events at the same velocity are one level (no velocity change between
    them: the pass's top velocity is planned twice, up then down, and slides on as one
    stretch); the merged level keeps the first's direction and the last's window."""
    out: list[dict] = []
    merged = []
    for e in evs:
        if out and abs(float(e["v_um_s"]) - float(out[-1]["v_um_s"])) <= rel * abs(float(out[-1]["v_um_s"])):
            keep = dict(e, direction=out[-1].get("direction"))
            merged.append({"v_um_s": float(e["v_um_s"]), "t_s": float(e.get("t_s", math.nan)),
                           "reason": f"same velocity as the level before ({float(out[-1]['v_um_s']):g} µm/s): no "
                                     "velocity change between them, one level (its last window kept)"})
            out[-1] = keep
        else:
            out.append(e)
    return out, merged


def levels_from_trial(trial: TrialData, *, use_events: bool = True, window_um: float = 50.0,
                      min_ratio: float = 1.25) -> tuple[list[dict], str, list[dict]]:
    """(levels, source, rejected): each level's steady friction; ``rejected`` says for every
    planned or detected level that is not in ``levels`` why (merged, too few samples)."""
    trial = at_level_rate(trial)
    t = np.asarray(trial.time_s, float)
    x = np.asarray(trial.position_um, float)
    mu = np.asarray(trial.mu, float)
    out = []
    rejected: list[dict] = []
    evs = [e for e in (trial.events or []) if e.get("kind") == "level" and "v_um_s" in e] if use_events else []
    if evs:
        evs, rejected = _merge_equal(evs)
        for e in evs:
            if "window_t_start_s" in e and "window_t_end_s" in e:
                t0, t1 = float(e["window_t_start_s"]), float(e["window_t_end_s"])
            else:
                t1 = float(e.get("t_end_s", e["t_s"]))
                t0 = t1 - window_um / float(e["v_um_s"])
            sel = (t >= t0) & (t <= t1)
            if sel.sum() < MIN_WINDOW_SAMPLES:
                rejected.append({"v_um_s": float(e["v_um_s"]), "t_s": t0,
                                 "reason": f"{int(sel.sum())} sample(s) in its window ({t0:.4g} - {t1:.4g} s; at least "
                                           f"{MIN_WINDOW_SAMPLES})"})
                continue
            out.append(_level(t, x, mu, sel, float(e["v_um_s"]), e.get("direction")))
        source = "events"
    else:
        steps = detect_steps(trial, use_events=False, min_ratio=min_ratio)
        source = "data"
        if not steps:
            return [], source, rejected
        # level k ends at step k (velocity v1); the last level ends at the last step's segment end
        ends = [(s.pre[0], s.i, s.v1_um_s, s.x_um) for s in steps]
        last = steps[-1]
        ends.append((last.i, last.post[1], last.v2_um_s, float(x[last.post[1] - 1])))
        for lo, hi, v, x_end in ends:
            sel = np.zeros(t.size, bool)
            sel[lo:hi] = True
            sel &= (x >= x_end - window_um) & (x <= x_end)
            if sel.sum() < MIN_WINDOW_SAMPLES:
                rejected.append({"v_um_s": float(v), "t_s": float(t[min(lo, t.size - 1)]),
                                 "reason": f"{int(sel.sum())} sample(s) in its last {window_um:g} µm (at least "
                                           f"{MIN_WINDOW_SAMPLES})"})
                continue
            out.append(_level(t, x, mu, sel, v, None))
    # branches: a level reached by an increase of velocity is 'up'
    prev = None
    for lv in out:
        if lv["direction"] not in ("up", "down"):
            lv["direction"] = "up" if prev is None or lv["v_um_s"] > prev else "down"
        prev = lv["v_um_s"]
    return out, source, rejected


def _level(t, x, mu, sel, v_nom, direction):
    tt, xx, mm = t[sel], x[sel], mu[sel]
    dt = tt - tt.mean()
    v_meas = float(np.dot(dt, xx - xx.mean()) / np.dot(dt, dt)) if np.dot(dt, dt) > 0 else math.nan
    return {"v_um_s": float(v_nom), "v_measured_um_s": v_meas, "mu": float(mm.mean()),
            "mu_sd": float(mm.std(ddof=1)) if mm.size > 1 else math.nan,
            "mu_sem": float(mm.std(ddof=1) / math.sqrt(mm.size)) if mm.size > 1 else math.nan,
            "n": int(mm.size), "t_start_s": float(tt[0]), "t_end_s": float(tt[-1]),
            "x_start_um": float(xx[0]), "x_end_um": float(xx[-1]), "direction": direction}


@dataclass
class Eq7Fit:
    """Eq. (7) fitted to steady-state levels: ``mu = mu0 + (A - B) ln(v/V0)``, with standard errors
    (None with fewer than 3 levels); unrounded, :meth:`report` rounds."""
    n: int
    A_minus_B: float | None = None
    A_minus_B_err: float | None = None
    mu0: float | None = None
    mu0_err: float | None = None
    r2: float | None = None
    rms_mu: float | None = None
    fitted: bool = False

    def report(self) -> dict:
        out = {"n": int(self.n), "A_minus_B": _r(self.A_minus_B), "A_minus_B_err": _r(self.A_minus_B_err),
               "mu0": _r(self.mu0), "mu0_err": _r(self.mu0_err)}
        if self.fitted:
            out.update(r2=_r(self.r2), rms_mu=_r(self.rms_mu))
        return out


def fit_eq7(levels: list[dict]) -> Eq7Fit:
    """Least squares ``mu = mu0 + c ln(v/V0)``; ``c = A - B`` (eq. 7) with standard errors."""
    v = np.array([lv["v_um_s"] for lv in levels], float)
    m = np.array([lv["mu"] for lv in levels], float)
    ok = v > 0
    v, m = v[ok], m[ok]
    n = v.size
    if n < 2 or np.ptp(np.log(v)) == 0:
        return Eq7Fit(int(n))
    X = np.column_stack([np.ones(n), np.log(v / V0_UM_S)])
    coef, *_ = np.linalg.lstsq(X, m, rcond=None)
    r = m - X @ coef
    dof = max(n - 2, 1)
    s2 = float(r @ r) / dof
    cov = np.linalg.inv(X.T @ X) * s2
    err = np.sqrt(np.diag(cov))
    sst = float(((m - m.mean()) ** 2).sum())
    return Eq7Fit(int(n), float(coef[1]), float(err[1]) if n > 2 else None, float(coef[0]),
                  float(err[0]) if n > 2 else None, 1 - float(r @ r) / sst if sst > 0 else None,
                  math.sqrt(float(r @ r) / n), fitted=True)


@dataclass
class StribeckResult:
    """The steady-state friction of every level (unrounded), the branch means and the eq. (7) fits
    (all levels, up, down); :meth:`report` is the rig.stribeck/1 JSON, rounded there."""
    data: object
    window_um: float
    level_source: list[str]
    levels: list[dict]
    rejected: list[dict]
    branches: dict[str, list[dict]]
    fit: Eq7Fit
    fit_up: Eq7Fit
    fit_down: Eq7Fit

    def report(self) -> dict:
        def rounded(d):
            return {k: (_r(v) if isinstance(v, float) else v) for k, v in d.items()}

        return {
            "schema": SCHEMA, "data": self.data, "window_um": self.window_um, "level_source": self.level_source,
            "n_levels": len(self.levels),
            "levels": [rounded(lv) for lv in self.levels],
            "rejected_levels": [rounded(r) for r in self.rejected],
            "branches": {d: [{"v_um_s": b["v_um_s"], "mu": _r(b["mu"]), "n_trials": b["n_trials"],
                              "mu_sd": _r(b["mu_sd"]) if b["mu_sd"] is not None else None} for b in rows]
                         for d, rows in self.branches.items()},
            "fit": self.fit.report(), "fit_up": self.fit_up.report(), "fit_down": self.fit_down.report(),
            "note": "eq. (7): mu_ss = mu0 + (A - B) ln(v/V0), V0 = 1 µm/s; A - B < 0 is a negative slope",
        }


def stribeck(trials: list[TrialData], *, use_events: bool = True, window_um: float = 50.0,
             names: list[str] | None = None) -> dict:
    """The rig.stribeck/1 report of :func:`stribeck_result`."""
    return stribeck_result(trials, use_events=use_events, window_um=window_um, names=names).report()


def stribeck_result(trials: list[TrialData], *, use_events: bool = True, window_um: float = 50.0,
                    names: list[str] | None = None) -> StribeckResult:
    """Levels of every trial, the branch-averaged curves, and the eq. (7) fits."""
    all_levels = []
    all_rejected = []
    sources = set()
    for k, tr in enumerate(trials):
        lv, src, rej = levels_from_trial(tr, use_events=use_events, window_um=window_um)
        sources.add(src)
        for x in lv + rej:
            x["trial"] = k
        all_levels += lv
        all_rejected += rej
    # levels measured in different trials (or detected from the data) differ slightly in
    # velocity: cluster within 5 % and label each cluster by its median
    vs_all = sorted(lv["v_um_s"] for lv in all_levels)
    clusters: list[list[float]] = []
    for v in vs_all:
        if clusters and v <= clusters[-1][0] * 1.05:
            clusters[-1].append(v)
        else:
            clusters.append([v])
    for lv in all_levels:
        for c in clusters:
            if c[0] <= lv["v_um_s"] <= c[-1]:
                lv["v_level_um_s"] = float(np.median(c))
                break
    branches = {}
    for d in ("up", "down"):
        sel = [dict(lv, v_um_s=lv["v_level_um_s"]) for lv in all_levels if lv["direction"] == d]
        vs = sorted({lv["v_um_s"] for lv in sel})
        rows = []
        for v in vs:
            mus = [lv["mu"] for lv in sel if lv["v_um_s"] == v]
            rows.append({"v_um_s": v, "mu": float(np.mean(mus)), "n_trials": len(mus),
                         "mu_sd": float(np.std(mus, ddof=1)) if len(mus) > 1 else None})
        branches[d] = rows
    return StribeckResult(
        data=names if names and len(names) > 1 else (names[0] if names else trials[0].source),
        window_um=window_um, level_source=sorted(sources), levels=all_levels, rejected=all_rejected,
        branches=branches, fit=fit_eq7(all_levels),
        fit_up=fit_eq7([lv for lv in all_levels if lv["direction"] == "up"]),
        fit_down=fit_eq7([lv for lv in all_levels if lv["direction"] == "down"]))


def write_json(rep: dict, path) -> None:
    atomic_write_text(path, json.dumps(rep, indent=2, allow_nan=False) + "\n")


def build_stribeck(rep: dict):
    """Fig. 6 (linear axes, branches apart) and Fig. 7 (semi-log with the eq. 7 fit)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from rig.analysis.plots import PAGE_WIDTH_IN, _plt, pm

    plt = _plt()
    fig, axs = plt.subplots(1, 2, figsize=(PAGE_WIDTH_IN, 3.0), layout="constrained")
    for d, c, mk in (("up", "C3", "^"), ("down", "C0", "v")):
        lv = [x for x in rep["levels"] if x["direction"] == d]
        br = rep["branches"][d]
        n = max([b["n_trials"] for b in br], default=0)
        for ax in axs:
            if n > 1:
                ax.plot([x["v_um_s"] for x in lv], [x["mu"] for x in lv], mk, color=c, alpha=0.35, ms=3)
            ax.plot([b["v_um_s"] for b in br], [b["mu"] for b in br], "-" + mk, color=c, ms=4,
                    label=f"{d} branch ({len(br)} levels" + (f", mean of {n} trials)" if n > 1 else ")"))
    f = rep["fit"]
    if f.get("A_minus_B") is not None:
        vv = np.logspace(np.log10(min(x["v_um_s"] for x in rep["levels"])),
                         np.log10(max(x["v_um_s"] for x in rep["levels"])), 100)
        axs[1].plot(vv, f["mu0"] + f["A_minus_B"] * np.log(vv), "k--", lw=0.8,
                    label=f"eq. (7): A − B = {pm(f['A_minus_B'], f['A_minus_B_err'])}")
    axs[0].set_title("steady-state friction (cf. Fig. 6)")
    axs[1].set_xscale("log")
    axs[1].xaxis.set_major_locator(LogLocator(base=10))
    axs[1].xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axs[1].xaxis.set_minor_formatter(NullFormatter())
    axs[1].set_title("semi-log axes (cf. Fig. 7)")
    for ax in axs:
        ax.set_xlabel("velocity (µm/s)")
    axs[0].set_ylabel(f"μ (mean over the last {rep['window_um']:g} µm of a level)")
    h, lab = axs[1].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncols=3)
    return fig


def plot_stribeck(rep: dict, path: str | Path) -> None:
    from rig.analysis.plots import save

    save(build_stribeck(rep), path)
