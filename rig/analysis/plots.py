"""PNG figures of the analyses (matplotlib, Agg backend), like the paper's Figs. 6-11."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from rig.data import atomic_write_bytes


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | Path) -> None:
    """Save atomically (the PNG is complete or absent)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())


def plot_identification(idn, path: str | Path, max_steps: int = 9) -> None:
    """Top: the record (friction, velocity, whole-record model). Below: friction after each
    step against slip, the fitted exponential (eq. 12) for each window, the windows shaded
    (Figs. 9-11)."""
    from rig.kinematics import estimate_velocity

    plt = _plt()
    results = [r for g in idn.results for r in g][:max_steps]
    ncol = 3
    nrow = 1 + max(1, math.ceil(len(results) / ncol))
    fig = plt.figure(figsize=(13, 3.2 * nrow))
    gs = fig.add_gridspec(nrow, ncol)
    ax = fig.add_subplot(gs[0, :])
    tr = idn.trials[0]
    step = max(1, tr.time_s.size // 50000)
    t = tr.time_s[::step]
    mu = tr.mu[::step]
    ax.plot(t, mu, ".", ms=1.5, color="0.5", label="measured mu")
    if idn.whole and idn.whole[0].get("_curve") is not None:
        tc, mc, _, _ = idn.whole[0]["_curve"]
        ax.plot(tc, mc, "-", color="C3", lw=1.0, label=f"whole-record fit ({idn.whole[0]['model']})")
    for r in idn.results[0]:
        ax.axvline(r.step.t_s, color="C0", lw=0.6, ls=":")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mu = F / (N1 + N2)")
    ax2 = ax.twinx()
    v = estimate_velocity(t, tr.position_um[::step], idn.report.get("velocity_method", "local_poly"))
    ax2.plot(t, v, "-", color="C2", lw=0.7, alpha=0.7)
    ax2.set_ylabel(f"velocity (µm/s, {idn.report.get('velocity_method')})", color="C2")
    ax2.set_yscale("symlog", linthresh=0.5)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(f"{Path(str(idn.report.get('data'))).name if isinstance(idn.report.get('data'), str) else 'trials'}: "
                 f"A_mu={idn.report['mean']['A_mu']}, B_mu={idn.report['mean']['B_mu']}, "
                 f"L={idn.report['mean']['L_um']} µm (mean over {idn.report['sem_over']})", fontsize=9)
    for k, r in enumerate(results):
        a = fig.add_subplot(gs[1 + k // ncol, k % ncol])
        tr = idn.trials[r.trial]
        lo, hi = r.step.post
        pre = max(r.step.pre[0], r.step.i - 200)
        x = tr.position_um
        m = tr.mu
        j_end = max([f["j1"] for f in r.fits], default=hi)
        sl = slice(pre, min(hi, j_end + 50))
        a.plot(x[sl] - r.step.x_um, m[sl], ".", ms=2, color="0.45")
        a.axhline(r.mu1, color="C0", lw=0.8, ls="--")
        for f in r.fits:
            best = f["window_um"] == r.window_um
            d0 = x[f["j0"]] - r.step.x_um
            d1 = x[min(f["j1"], x.size) - 1] - r.step.x_um
            a.axvspan(d0, d1, color="C1" if best else "0.85", alpha=0.25 if best else 0.3)
            dd = np.linspace(0, max(d1, 1.0), 300)
            a.plot(dd, f["mu2"] + f["a"] * np.exp(-dd / f["L_um"]), "-" if best else ":",
                   color="C3" if best else "C4", lw=1.2 if best else 0.8)
        a.set_title(f"{r.step.v1_um_s:.3g}->{r.step.v2_um_s:.3g} µm/s: A={r.A_mu:.2e} B={r.B_mu:.2e} "
                    f"L={r.L_um:.1f} µm r2={r.r2:.2f}" + ("" if r.ok else " (rejected)"), fontsize=7.5)
        a.set_xlabel("slip after step (µm)", fontsize=8)
        a.tick_params(labelsize=7)
    fig.tight_layout()
    save(fig, path)
