"""The diagnosis figure: data, baseline and extended model, residuals against time, slip and position."""

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


def build_diagnosis(d: Diagnosis, warnings: list[dict] | None = None):
    """The figure: data with the baseline and the extended model (velocity below), then the
    residuals against time, slip and position, each titled, each finding's evidence marked,
    and a footnote panel (findings, unexplained structure, parameter warnings) that the
    layout makes room for."""
    from rig.analysis.plots import PAGE_WIDTH_IN, WARN_COLOR, _plt, footnote_axes, footnote_height_in, symlog_velocity
    from rig.model.checks import MARK

    plt = _plt()
    g = d.grid
    base, fin = d.baseline, d.final
    rb = g.F_mean - base.pred
    rf = g.F_mean - fin.pred
    s = slip_of(g)
    notes = []
    for i, f in enumerate(d.findings, 1):
        notes.append(f"[{i}] {f['cause']} (hold-out gain {f['gain_pct']:.1f} %): {f['evidence']}")
    for u in d.unexplained:
        notes.append(f"[?] unexplained, follows {u['follows']}: {u['evidence']}")
    if not notes:
        notes.append("no finding: no catalogue extension passes the hold-out test")
    warn_lines = [f"{MARK} {w['where']}: {w['message']}" for w in (warnings or [])]
    heights = [2.2, 0.9, 1.5, 1.5, 1.5, footnote_height_in(notes + warn_lines)]
    fig = plt.figure(figsize=(PAGE_WIDTH_IN, sum(heights) + 0.8), layout="constrained")
    gs = fig.add_gridspec(len(heights), 1, height_ratios=heights)
    a = fig.add_subplot(gs[0])
    hm = g.holdout_mask()
    for k, b in enumerate(np.unique(g.block[hm])):
        tb = g.t[g.block == b]
        a.axvspan(tb.min(), tb.max(), color="0.92", zorder=-1, lw=0, label="hold-out blocks" if k == 0 else None)
    a.plot(g.t, g.F_mean, ".", ms=1.2, color="0.5", label="data (binned)", rasterized=True)
    a.plot(g.t, base.pred, "-", lw=0.9, color="tab:blue",
           label=f"baseline {base.baseline} (hold-out RMS {base.holdout_rms_N:.3g} N)")
    if fin is not base:
        a.plot(g.t, fin.pred, "-", lw=0.9, color="tab:red",
               label=f"extended: {' + '.join(fin.extensions)} (hold-out RMS {fin.holdout_rms_N:.3g} N)")
    a.set_ylabel("friction (N)")
    a.set_title(f"rig diagnose: {Path(d.data).name}")
    a.tick_params(labelbottom=False)
    av = fig.add_subplot(gs[1], sharex=a)
    av.plot(g.t, g.v, "-", lw=0.6, color="tab:green")
    symlog_velocity(av, np.asarray(g.v, float), max_ticks=5)
    av.set_ylabel("v (µm/s)")
    av.set_xlabel("time (s)")
    # scaled to the steady residual (the sliding bins' 95th percentile of the final model's residual,
    # what a finding is about), not to the start-up and reversal spikes: those are clipped to the
    # panel's edge and marked
    sl = g.sliding if g.sliding is not None and g.sliding.any() else np.ones(g.t.size, bool)
    steady = float(np.percentile(np.abs(np.concatenate([rf[sl], rb[sl]])), 95))
    lim = max(4 * g.noise_N / math.sqrt(max(float(np.median(g.count)), 1.0)), 1.5 * steady, 1e-6)
    res_axes = []
    n_clipped = 0
    for k, (q, lab, title) in enumerate(((g.t, "time (s)", "residual against time (drifts, transients)"),
                                         (s, "slip (µm)", "residual against slip (memory, wear)"),
                                         (g.x, "position (µm)", "residual against position (the surface)"))):
        axi = fig.add_subplot(gs[2 + k])
        qb, rbb = _binned(q, rb, g.count)
        qf, rff = _binned(q, rf, g.count)
        axi.plot(q, np.clip(rb, -lim, lim), ".", ms=0.8, color="tab:blue", alpha=0.25, rasterized=True)
        out = np.abs(rb) > lim
        n_clipped = max(n_clipped, int(out.sum()))
        if out.any():
            axi.plot(q[out], np.sign(rb[out]) * lim * 0.97, "x", ms=3, color=WARN_COLOR,
                     lw=0, label=None)
        axi.plot(qb, np.clip(rbb, -lim, lim), "--", lw=1.0, color="tab:blue")
        if fin is not base:
            axi.plot(qf, np.clip(rff, -lim, lim), "--", lw=1.0, color="tab:red")
        axi.axhline(0, color="k", lw=0.5)
        axi.set_xlabel(lab)
        axi.set_ylabel("residual (N)")
        axi.set_ylim(-lim, lim)
        axi.set_title(title)
        res_axes.append(axi)
    # one legend, above the panels (it covers no data); a model and its residual are separate entries
    from matplotlib.lines import Line2D

    h, lab = a.get_legend_handles_labels()
    h += [Line2D([], [], color="tab:blue", lw=1.0, ls="--"), Line2D([], [], color="tab:red", lw=1.0, ls="--")][
        : 2 if fin is not base else 1]
    lab += ["residual of the baseline (binned mean)", "residual of the extended model (binned mean)"][
        : 2 if fin is not base else 1]
    if n_clipped:
        h.append(Line2D([], [], color=WARN_COLOR, marker="x", lw=0, ms=3))
        lab.append(f"residual beyond ±{lim:.2g} N (start-up, reversals), clipped to the edge")
    fig.legend(h, lab, loc="outside upper center", ncols=2, markerscale=2)
    # evidence marks
    for f in d.findings:
        c = f["cause"]
        p = f["params"]
        if c == "position_periodic":
            lam = p["wavelength_um"]
            x0 = float(g.x.min())
            for k in range(int((g.x.max() - x0) / lam) + 1):
                res_axes[2].axvline(x0 + k * lam, color="tab:purple", lw=0.4, alpha=0.5)
        elif c == "force_offset_drift":
            res_axes[0].plot(g.t, p["rate_N_per_s"] * (g.t - g.t.mean()), "--", color="tab:purple", lw=1)
        elif c == "slip_wear_drift":
            res_axes[1].plot(s, p["rate_mu_per_mm"] * 2 * g.N_nom * (s - s.mean()) * 1e-3, "--", color="tab:purple",
                             lw=1)
        else:
            # transients: mark the velocity changes (where they start) on the time axis
            for te in velocity_changes(g.kin["t"], g.kin["v"]):
                res_axes[0].axvline(te, color="tab:purple", lw=0.5, alpha=0.5)
    footnote_axes(fig, gs[len(heights) - 1], [(n, "k") for n in notes] + [(w, WARN_COLOR) for w in warn_lines])
    return fig


def plot_diagnosis(d: Diagnosis, path: str | Path, warnings: list[dict] | None = None) -> Path:
    """Write the PNG (atomically)."""
    from rig.analysis.plots import save

    save(build_diagnosis(d, warnings), path)
    return Path(path)


__all__ = ["build_diagnosis", "plot_diagnosis"]
