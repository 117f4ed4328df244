"""The diagnosis figure: data, baseline and final model (as reported: refitted on all sliding data),
residuals against time, slip and position."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rig.kinematics import velocity_changes

from .core import Diagnosis, slip_of


def _binned(q, r, w, nb=120):
    edges = np.linspace(q.min(), q.max(), nb + 1)
    b = np.clip(np.searchsorted(edges, q, side="right") - 1, 0, nb - 1)
    num = np.bincount(b, weights=w * r, minlength=nb)
    den = np.bincount(b, weights=w, minlength=nb)
    ok = den > 0
    c = 0.5 * (edges[1:] + edges[:-1])
    return c[ok], num[ok] / den[ok]


def _notes(d: Diagnosis) -> list[str]:
    notes = [f"[{i}] {f.cause} (hold-out gain {f.gain_pct:.1f} %): {f.evidence}"
             for i, f in enumerate(d.findings, 1)]
    notes += [f"[?] unexplained, follows {u['follows']}: {u['evidence']}" for u in d.unexplained]
    return notes or ["no finding: no catalogue extension passes the hold-out test"]


def _drawn_models(d: Diagnosis):
    """(baseline, final model) as drawn: the models the report gives, refitted on all sliding data
    (``baseline_fit``/``final_fit``), or the split fits where those were not made."""
    base = d.baseline_fit if d.baseline_fit is not None else d.baseline
    fin = d.final_fit if d.final_fit is not None else d.final
    extended = bool(fin.extensions) or fin is not base
    return base, fin, extended


def _data_panel(a, d: Diagnosis, base, fin, extended: bool) -> None:
    g = d.grid
    hm = g.holdout_mask()
    for k, b in enumerate(np.unique(g.block[hm])):
        tb = g.t[g.block == b]
        a.axvspan(tb.min(), tb.max(), color="0.92", zorder=-1, lw=0, label="hold-out blocks" if k == 0 else None)
    a.plot(g.t, g.F_mean, ".", ms=1.2, color="0.5", label="data (binned)", rasterized=True)
    # the split fits' hold-out RMS (what chose the model) beside the reported model, refitted on all data
    a.plot(g.t, base.pred, "-", lw=0.9, color="tab:blue",
           label=f"baseline {base.baseline}, refitted on all sliding data "
                 f"(split fit: hold-out RMS {d.baseline.holdout_rms_N:.3g} N)")
    if extended:
        a.plot(g.t, fin.pred, "-", lw=0.9, color="tab:red",
               label=f"final model: {' + '.join(fin.extensions)}, refitted on all sliding data "
                     f"(split fit: hold-out RMS {d.final.holdout_rms_N:.3g} N)")
    a.set_ylabel("friction (N)")
    a.set_title(f"rig diagnose: {Path(d.data).name}")
    a.tick_params(labelbottom=False)


def _residual_limit(g, rb: np.ndarray, rf: np.ndarray) -> float:
    """The residual panels' half-range: the steady residual (the sliding bins' 95th percentile of
    both residuals, what a finding is about), not the start-up and reversal spikes (clipped, marked)."""
    sl = g.sliding if g.sliding is not None and g.sliding.any() else np.ones(g.t.size, bool)
    steady = float(np.percentile(np.abs(np.concatenate([rf[sl], rb[sl]])), 95))
    return max(4 * g.noise_N / math.sqrt(max(float(np.median(g.count)), 1.0)), 1.5 * steady, 1e-6)


def _residual_panels(fig, gs, g, rb, rf, extended: bool, lim: float):
    """The three residual panels (time, slip, position); returns them and the most clipped points."""
    from rig.analysis.plots import WARN_COLOR

    res_axes, n_clipped = [], 0
    for k, (q, lab, title) in enumerate(((g.t, "time (s)", "residual against time (drifts, transients)"),
                                         (slip_of(g), "slip (µm)", "residual against slip (memory, wear)"),
                                         (g.x, "position (µm)", "residual against position (the surface)"))):
        axi = fig.add_subplot(gs[2 + k])
        axi.plot(q, np.clip(rb, -lim, lim), ".", ms=0.8, color="tab:blue", alpha=0.25, rasterized=True)
        out = np.abs(rb) > lim
        n_clipped = max(n_clipped, int(out.sum()))
        if out.any():
            axi.plot(q[out], np.sign(rb[out]) * lim * 0.97, "x", ms=3, color=WARN_COLOR, lw=0, label=None)
        qb, rbb = _binned(q, rb, g.count)
        axi.plot(qb, np.clip(rbb, -lim, lim), "--", lw=1.0, color="tab:blue")
        if extended:
            qf, rff = _binned(q, rf, g.count)
            axi.plot(qf, np.clip(rff, -lim, lim), "--", lw=1.0, color="tab:red")
        axi.axhline(0, color="k", lw=0.5)
        axi.set_xlabel(lab)
        axi.set_ylabel("residual (N)")
        axi.set_ylim(-lim, lim)
        axi.set_title(title)
        res_axes.append(axi)
    return res_axes, n_clipped


def _legend(fig, a, extended: bool, n_clipped: int, lim: float) -> None:
    """One legend, above the panels (it covers no data); a model and its residual are separate entries."""
    from matplotlib.lines import Line2D

    from rig.analysis.plots import WARN_COLOR

    n = 2 if extended else 1
    h, lab = a.get_legend_handles_labels()
    h += [Line2D([], [], color="tab:blue", lw=1.0, ls="--"), Line2D([], [], color="tab:red", lw=1.0, ls="--")][:n]
    lab += ["residual of the baseline (binned mean)", "residual of the final model (binned mean)"][:n]
    if n_clipped:
        h.append(Line2D([], [], color=WARN_COLOR, marker="x", lw=0, ms=3))
        lab.append(f"residual beyond ±{lim:.2g} N (start-up, reversals), clipped to the edge")
    fig.legend(h, lab, loc="outside upper center", ncols=1 if max(map(len, lab)) > 45 else 2, markerscale=2)


def _evidence_marks(d: Diagnosis, res_axes) -> None:
    g = d.grid
    for f in d.findings:
        c = f.cause
        p = f.params
        if c == "position_periodic":
            lam = p["wavelength_um"]
            x0 = float(g.x.min())
            for k in range(int((g.x.max() - x0) / lam) + 1):
                res_axes[2].axvline(x0 + k * lam, color="tab:purple", lw=0.4, alpha=0.5)
        elif c == "force_offset_drift":
            res_axes[0].plot(g.t, p["rate_N_per_s"] * (g.t - g.t.mean()), "--", color="tab:purple", lw=1)
        elif c == "slip_wear_drift":
            s = slip_of(g)
            res_axes[1].plot(s, p["rate_mu_per_mm"] * 2 * g.N_nom * (s - s.mean()) * 1e-3, "--", color="tab:purple",
                             lw=1)
        else:
            # transients: mark the velocity changes (where they start) on the time axis
            for te in velocity_changes(g.kin["t"], g.kin["v"]):
                res_axes[0].axvline(te, color="tab:purple", lw=0.5, alpha=0.5)


def build_diagnosis(d: Diagnosis, warnings: list[dict] | None = None):
    """The figure: data with the baseline and the final model (the report's: refitted on all
    sliding data; velocity below), then the residuals against time, slip and position, each
    titled, each finding's evidence marked, and a footnote panel (findings, unexplained
    structure, parameter warnings) that the layout makes room for."""
    from rig.analysis.plots import PAGE_WIDTH_IN, WARN_COLOR, _plt, footnote_axes, footnote_height_in, symlog_velocity
    from rig.model.checks import MARK

    plt = _plt()
    g = d.grid
    base, fin, extended = _drawn_models(d)
    rb, rf = g.F_mean - base.pred, g.F_mean - fin.pred
    notes = _notes(d)
    warn_lines = [f"{MARK} {w['where']}: {w['message']}" for w in (warnings or [])]
    heights = [2.2, 0.9, 1.5, 1.5, 1.5, footnote_height_in(notes + warn_lines)]
    fig = plt.figure(figsize=(PAGE_WIDTH_IN, sum(heights) + 0.8), layout="constrained")
    gs = fig.add_gridspec(len(heights), 1, height_ratios=heights)
    a = fig.add_subplot(gs[0])
    _data_panel(a, d, base, fin, extended)
    av = fig.add_subplot(gs[1], sharex=a)
    av.plot(g.t, g.v, "-", lw=0.6, color="tab:green")
    symlog_velocity(av, np.asarray(g.v, float), max_ticks=5)
    av.set_ylabel("v (µm/s)")
    av.set_xlabel("time (s)")
    lim = _residual_limit(g, rb, rf)
    res_axes, n_clipped = _residual_panels(fig, gs, g, rb, rf, extended, lim)
    _legend(fig, a, extended, n_clipped, lim)
    _evidence_marks(d, res_axes)
    footnote_axes(fig, gs[len(heights) - 1], [(n, "k") for n in notes] + [(w, WARN_COLOR) for w in warn_lines])
    return fig


def plot_diagnosis(d: Diagnosis, path: str | Path, warnings: list[dict] | None = None) -> Path:
    """Write the PNG (atomically)."""
    from rig.analysis.plots import save

    save(build_diagnosis(d, warnings), path)
    return Path(path)


__all__ = ["build_diagnosis", "plot_diagnosis"]
