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


def plot_diagnosis(d: Diagnosis, path: str | Path) -> Path:
    """Write the PNG (Agg): 4 panels; each finding's evidence is marked and captioned."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rig.data import atomic_write_bytes

    g = d.grid
    base, fin = d.baseline, d.final
    rb = g.F_mean - base.pred
    rf = g.F_mean - fin.pred
    s = slip_of(g)
    fig, ax = plt.subplots(4, 1, figsize=(11, 13))
    a = ax[0]
    a.plot(g.t, g.F_mean, ".", ms=1.5, color="0.5", label="data (binned)")
    a.plot(g.t, base.pred, "-", lw=0.9, color="tab:blue", label=f"baseline {base.baseline} "
           f"(hold-out RMS {base.holdout_rms_N:.3g} N)")
    if fin is not base:
        a.plot(g.t, fin.pred, "-", lw=0.9, color="tab:red",
               label=f"extended: {' + '.join(fin.extensions)} (hold-out RMS {fin.holdout_rms_N:.3g} N)")
    hm = g.holdout_mask()
    # shade hold-out blocks
    blocks = np.unique(g.block[hm])
    for b in blocks:
        tb = g.t[g.block == b]
        a.axvspan(tb.min(), tb.max(), color="0.9", zorder=-1, lw=0)
    a.set_ylabel("friction (N)")
    a.set_title(f"rig diagnose: {Path(d.data).name}   (grey bands: hold-out blocks)")
    a.legend(fontsize=7, loc="best")
    a2 = a.twinx()
    a2.plot(g.t, g.v, "-", lw=0.5, color="tab:green", alpha=0.5)
    a2.set_ylabel("velocity (µm/s)", color="tab:green")
    for axi, q, lab in ((ax[1], g.t, "time (s)"), (ax[2], s, "slip (µm)"), (ax[3], g.x, "position (µm)")):
        qb, rbb = _binned(q, rb, g.count)
        qf, rff = _binned(q, rf, g.count)
        axi.plot(q, rb, ".", ms=1, color="tab:blue", alpha=0.25)
        axi.plot(qb, rbb, "-", lw=1.2, color="tab:blue", label="residual, baseline (binned mean)")
        axi.plot(qf, rff, "-", lw=1.2, color="tab:red", label="residual, extended model (binned mean)")
        axi.axhline(0, color="k", lw=0.5)
        axi.set_xlabel(lab)
        axi.set_ylabel("residual (N)")
        lim = max(4 * g.noise_N, float(np.percentile(np.abs(rb), 99.5)))
        axi.set_ylim(-lim, lim)
    # evidence marks
    notes = []
    for i, f in enumerate(d.findings, 1):
        c = f["cause"]
        p = f["params"]
        if c == "position_periodic":
            lam = p["wavelength_um"]
            x0 = float(g.x.min())
            for k in range(int((g.x.max() - x0) / lam) + 1):
                ax[3].axvline(x0 + k * lam, color="tab:purple", lw=0.4, alpha=0.5)
        elif c in ("force_offset_drift",):
            ax[1].plot(g.t, p["rate_N_per_s"] * (g.t - g.t.mean()), "--", color="tab:purple", lw=1)
        elif c == "slip_wear_drift":
            ax[2].plot(s, p["rate_mu_per_mm"] * 2 * g.N_nom * (s - s.mean()) * 1e-3, "--", color="tab:purple", lw=1)
        else:
            # transients: mark the velocity changes (where they start) on the time axis
            for te in velocity_changes(g.kin["t"], g.kin["v"]):
                ax[1].axvline(te, color="tab:purple", lw=0.5, alpha=0.5)
        notes.append(f"[{i}] {c}: {f['evidence'][:150]}  gain {f['gain_pct']:.1f}%")
    for u in d.unexplained:
        notes.append(f"[?] unexplained, follows {u['follows']}: {u['evidence'][:150]}")
    if not notes:
        notes.append("no finding: the baseline explains the data to within the noise")
    fig.text(0.01, 0.005, "\n".join(notes), fontsize=6.5, va="bottom", family="monospace")
    fig.tight_layout(rect=(0, 0.02 + 0.012 * len(notes), 1, 1))
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


__all__ = ["plot_diagnosis", "math"]
