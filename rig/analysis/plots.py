"""PNG figures of the analyses (matplotlib, Agg backend), like the paper's Figs. 6-11.

One style for every figure of the project (:data:`STYLE`, applied by :func:`_plt`): sized to
print, :data:`PAGE_WIDTH_IN` wide (a journal page's text width) at :data:`DPI`, 8 pt text,
plain tick labels. Each figure has a ``build_*`` function that returns the matplotlib figure
(what the tests inspect) and a ``plot_*`` one that writes the PNG atomically.

Parameters that hit a fit bound or are not physical (:mod:`rig.model.checks`) carry the
:data:`rig.model.checks.MARK` in the titles and are listed in a footnote panel.
"""

from __future__ import annotations

import io
import math
import textwrap
from pathlib import Path

import numpy as np

from rig.data import atomic_write_bytes

#: a figure spans a printed page's text width (inches) and is saved at DPI
PAGE_WIDTH_IN = 7.0
DPI = 200
WARN_COLOR = "#b00000"

STYLE = {
    "font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "xtick.labelsize": 7, "ytick.labelsize": 7,
    "legend.fontsize": 7, "figure.titlesize": 9, "lines.linewidth": 1.0, "lines.markersize": 3,
    "axes.spines.top": False, "axes.spines.right": False, "axes.grid": False,
    "axes.formatter.useoffset": False, "axes.formatter.limits": (-3, 4), "axes.formatter.use_mathtext": True,
    "legend.frameon": False, "savefig.dpi": DPI, "figure.dpi": 100,
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(STYLE)
    return plt


def save(fig, path: str | Path) -> None:
    """Save atomically (the PNG is complete or absent)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())


def g3(v, nd: int = 3) -> str:
    """A number for a figure: ``nd`` significant figures, '-' when missing."""
    if v is None or not math.isfinite(float(v)):
        return "-"
    return f"{float(v):.{nd}g}"


_SUP = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def pm(m, e, nd: int = 3) -> str:
    """``m ± e`` (the error to 2 figures; a common power of ten for small or large values,
    '(1.19 ± 0.05)×10⁻³'), or ``m`` alone when there is no error."""
    if m is None or not math.isfinite(float(m)):
        return "-"
    m = float(m)
    has_e = e is not None and math.isfinite(float(e))
    p = math.floor(math.log10(abs(m))) if m != 0 else 0
    if -1 <= p < 4:
        return f"{g3(m, nd)} ± {g3(e, 2)}" if has_e else g3(m, nd)
    f = 10.0 ** p
    exp = f"×10{str(p).translate(_SUP)}"
    return f"({g3(m / f, nd)} ± {g3(float(e) / f, 2)}){exp}" if has_e else f"{g3(m / f, nd)}{exp}"


FOOT_PT = 6.5


def _wrap(lines, width_chars: int) -> list[tuple[str, str | None]]:
    out = []
    for ln in lines:
        text, color = ln if isinstance(ln, tuple) else (ln, None)
        out += [(w, color) for w in (textwrap.wrap(text, width_chars, subsequent_indent="    ") or [""])]
    return out


def footnote_axes(fig, spec, lines: list, width_chars: int = 120, color: str = WARN_COLOR):
    """An axes without frame that holds footnote lines (wrapped; an item may be ``(text, color)``):
    its own grid cell, so the layout reserves the room and nothing is cut off."""
    ax = fig.add_subplot(spec)
    ax.axis("off")
    for k, (text, c) in enumerate(_wrap(lines, width_chars)):
        ax.annotate(text, xy=(0.0, 1.0), xycoords="axes fraction", xytext=(0.0, -1.3 * FOOT_PT * k),
                    textcoords="offset points", va="top", ha="left", fontsize=FOOT_PT, color=c or color)
    return ax


def footnote_height_in(lines: list, width_chars: int = 120) -> float:
    return 0.1 + 1.3 * FOOT_PT / 72.0 * len(_wrap(lines, width_chars))


def symlog_velocity(ax, v: np.ndarray, max_ticks: int = 7) -> None:
    """A symmetric-log velocity axis with plain labels: 0 and the decades ±10^k the data
    reach, the linear range one decade below the typical speed (no crowded labels near 0)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    a = np.abs(v[np.isfinite(v)])
    a = a[a > 0]
    if a.size == 0:
        return
    p1, p99 = (float(np.percentile(v[np.isfinite(v)], q)) for q in (1, 99))
    if p1 > 0 and p99 / p1 < 30:  # one direction within about a decade: a plain linear axis
        return
    typ = float(np.median(a))
    lin = 10.0 ** math.floor(math.log10(max(typ, 1e-6)))
    hi = 10.0 ** math.ceil(math.log10(max(float(a.max()), lin)))
    ax.set_yscale("symlog", linthresh=lin, linscale=1.0)
    decades = [lin * 10 ** k for k in range(int(round(math.log10(hi / lin))) + 1)]
    pos = [d for d in decades if d <= 1.5 * float(np.nanmax(v)) or d == lin]
    neg = [-d for d in decades if d <= 1.5 * -float(np.nanmin(v))] if float(np.nanmin(v)) < -lin else []
    if 1 + len(pos) + len(neg) > max_ticks:  # a short panel: of the returns only their largest speed
        neg = neg[-1:]
    while 1 + len(pos) + len(neg) > max_ticks and len(pos) > 2:  # then every other decade, the top kept
        pos = pos[::-1][::2][::-1]
    ticks = sorted([0.0] + pos + neg)
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:g}"))


# ---------------------------------------------------------------------------
# identify
# ---------------------------------------------------------------------------
def _n(n: int, what: str) -> str:
    """'1 step', '3 steps' ('what' is the plural)."""
    return f"{n} {what[:-1] if n == 1 and what.endswith('s') else what}"


def _title_params(mean: dict, sem: dict | None, flags: set[str]) -> str:
    sem = sem or {}
    parts = []
    for k, label, unit in (("A_mu", "A", ""), ("B_mu", "B", ""), ("L_um", "L", " µm")):
        parts.append(f"{label} = {pm(mean.get(k), sem.get(k))}{unit}" + (" (!)" if k in flags else ""))
    if "k_cr_kN_per_m" in flags:
        parts.append(f"k_cr = {g3(mean.get('k_cr_kN_per_m'))} kN/m (!)")
    return ", ".join(parts)


def build_identification(idn, max_steps: int = 9):
    """The identification figure: the record (friction, whole-record model; velocity below),
    then friction after each step against slip with the eq. (12) fit of each window and the
    windows shaded (Figs. 9-11), a legend for all of them and the warnings. With several files,
    the record drawn is the first file's, and each step says its file."""
    from rig.model.checks import MARK

    plt = _plt()
    warns = idn.warnings
    results = idn.steps[:max_steps]
    n_more = len(idn.steps) - len(results)
    ncol = max(1, min(3, len(results)))
    nrow_steps = math.ceil(len(results) / ncol) if results else 0
    notes = [f"{MARK} {w['where']}: {w['message']}" for w in warns]
    rejected = [f"rejected step at t = {g3(r.step.t_s, 6)} s: {r.reason}" for r in idn.rejected]
    if n_more:
        notes.append(f"{n_more} more step(s) not drawn (the first {len(results)} are)")
    foot = rejected + notes
    heights = [2.0, 1.0] + ([2.1] * nrow_steps) + ([0.45] if results else []) + \
        ([footnote_height_in(foot)] if foot else [])
    fig = plt.figure(figsize=(PAGE_WIDTH_IN, sum(heights) + 0.6), layout="constrained")
    gs = fig.add_gridspec(len(heights), ncol, height_ratios=heights)
    files = _file_names(idn)
    ax = fig.add_subplot(gs[0, :])
    record_handles = _record_panels(ax, fig.add_subplot(gs[1, :], sharex=ax), idn, files)
    if not results:
        ax.legend(loc="best", markerscale=4)
    ax.set_title(_identification_title(idn, files))
    for k, r in enumerate(results):
        _step_panel(fig.add_subplot(gs[2 + k // ncol, k % ncol]), idn, r, files)
        if k % ncol == 0:
            fig.axes[-1].set_ylabel("μ")
    if results:
        _step_legend(fig.add_subplot(gs[2 + nrow_steps, :]), record_handles)
    if foot:
        footnote_axes(fig, gs[len(heights) - 1, :], foot)
    return fig


def _file_names(idn) -> list[str]:
    """The identified files' names (the report's ``data``), one per trial."""
    data = idn.data
    names = [Path(d).name for d in data] if isinstance(data, list) else [Path(str(data)).name]
    return names if len(names) == len(idn.trials) else [f"trial {i}" for i in range(len(idn.trials))]


def _record_panels(ax, axv, idn, files: list[str]) -> list:
    """The first record: measured friction with the whole-record fit(s) and trend, the steps, the velocity
    below; returns the legend handles of the record panel."""
    from rig.kinematics import estimate_velocity

    tr = idn.trials[0]
    step = max(1, tr.time_s.size // 50000)
    t = tr.time_s[::step]
    own = f" ({files[0]})" if len(files) > 1 else ""
    ax.plot(t, tr.mu[::step], ".", ms=1.0, color="0.55", label=f"measured μ{own}", rasterized=True)
    fits0 = idn.laws[0] if idn.laws else ({"": idn.fits[0]} if idn.fits else {})
    for (lw, w0), col in zip(fits0.items(), ("C3", "C4")):
        if w0.curve is None:
            continue
        tc, mc, _, _, trend = w0.curve
        ax.plot(tc, mc, "-", color=col, lw=0.9, label=f"whole-record fit ({w0.model}){own}")
        d = w0.reported.get("detrend", {})
        if d.get("method", "none") != "none" and col == "C3":
            # the trend (mu per mm of slip), drawn about the fit's mean level
            ax.plot(tc, float(np.nanmean(mc)) + trend - float(np.nanmean(trend)), "--", color="C1", lw=0.8,
                    label=f"trend ({d['method']}): {g3(d.get('rate_mu_per_mm'), 2)} μ/mm")
    for k, r in enumerate(idn.results[0]):
        for a in (ax, axv):
            a.axvline(r.step.t_s, color="C0", lw=0.6, ls=":", label="velocity step" if (k == 0 and a is ax) else None)
    ax.set_ylabel("μ = F / (N1 + N2)")
    ax.tick_params(labelbottom=False)
    v = estimate_velocity(t, tr.position_um[::step], idn.velocity_method)
    axv.plot(t, v, "-", color="C2", lw=0.6)
    symlog_velocity(axv, v)
    axv.set_ylabel("v (µm/s)")
    axv.set_xlabel("time (s)")
    return ax.get_legend_handles_labels()[0]


def _identification_title(idn, files: list[str]) -> str:
    """The files, the mean A, B, L over steps (or trials), and one file's whole-record fit with its intervals."""
    from rig.model.checks import flagged

    warns = idn.warnings
    name = files[0] if len(files) == 1 else (", ".join(files) if len(files) <= 3 else f"{len(files)} files")
    if idn.n_steps:
        n = idn.n_steps if idn.sem_over == "steps" else len(idn.trials)
        head = (f"{name}: {_title_params(idn.mean, idn.sem, flagged(warns, 'mean over ' + idn.sem_over))} "
                f"(mean over {_n(n, idn.sem_over)})")
    else:
        head = f"{name}: no accepted step ({len(idn.rejected)} rejected)"
    wr = idn.fits[0].report() if idn.law is not None and len(idn.fits) == 1 else None
    if wr is not None and "params" in wr:
        spec = {k: v for k, v in wr["params"].items() if k not in ("a", "b", "Dc_um", "a_minus_b", "k_per_um")}
        head += "\nwhole-record fit: " + _title_params({**spec, "k_cr_kN_per_m": wr.get("k_cr_kN_per_m")},
                                                        wr.get("err_corr"), flagged(warns, "whole-record fit"))
        unc = _uncertainty_line(wr)
        head += "\n" + unc if unc else ""
        if idn.law == "both" and len(idn.comparisons) == 1:
            c = idn.comparisons[0]
            head += f"\npreferred law: {c.preferred_law} (ΔBIC {g3(c.delta_bic, 3)}; 6 or more decides)"
    return head


def _step_panel(a, idn, r, files: list[str]) -> None:
    """Friction after one step against slip: mu1, each window's eq. (12) fit, the window kept shaded."""
    from rig.model.checks import flagged

    tr = idn.trials[r.trial]
    lo, hi = r.step.post
    pre = max(r.step.pre[0], r.step.i - 200)
    x = tr.position_um
    j_end = max([f["j1"] for f in r.fits], default=hi)
    sl = slice(pre, min(hi, j_end + 50))
    a.plot(x[sl] - r.step.x_um, tr.mu[sl], ".", ms=1.2, color="0.5", rasterized=True)
    a.axhline(r.mu1, color="C0", lw=0.8, ls="--")
    for f in r.fits:
        best = f["window_um"] == r.window_um
        d0 = x[f["j0"]] - r.step.x_um
        d1 = x[min(f["j1"], x.size) - 1] - r.step.x_um
        a.axvspan(d0, d1, color="C1" if best else "0.8", alpha=0.3 if best else 0.35, lw=0)
        dd = np.linspace(0, max(d1, 1.0), 300)
        a.plot(dd, f["mu2"] + f["a"] * np.exp(-dd / f["L_um"]), "-" if best else ":",
               color="k" if best else "C4", lw=1.1 if best else 0.8)
    fl = flagged(idn.warnings, r.where(len(idn.trials)))
    line2 = ", ".join(f"{lab} = {g3(val, 2 if lab in ('A', 'B') else 3)}{u}" + (" (!)" if key in fl else "")
                      for lab, key, val, u in (("A", "A_mu", r.A_mu, ""), ("B", "B_mu", r.B_mu, ""),
                                               ("L", "L_um", r.L_um, " µm")))
    a.set_title(f"{g3(r.step.v1_um_s)} → {g3(r.step.v2_um_s)} µm/s" +
                (f" ({files[r.trial]})" if len(idn.trials) > 1 else "") + f", r² = {g3(r.r2, 2)}\n" + line2 +
                ("" if r.ok else "\nrejected (see below)"), color="k" if r.ok else WARN_COLOR, fontsize=7)
    a.set_xlabel("slip after the step (µm)")


def _step_legend(lax, record_handles: list) -> None:
    """One legend for the record's lines and the step panels' marks."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    lax.axis("off")
    handles = record_handles[1:] + [Line2D([], [], ls="", marker=".", color="0.5", label="measured μ"),
               Line2D([], [], ls="--", color="C0", label="μ1: mean before the step"),
               Line2D([], [], ls="-", color="k", label="eq. (12) fit, window kept (best r²)"),
               Line2D([], [], ls=":", color="C4", label="eq. (12) fit, other windows"),
               Patch(color="C1", alpha=0.3, label="μ2 window kept"),
               Patch(color="0.8", alpha=0.35, label="other μ2 windows tried")]
    lax.legend(handles=handles, loc="center", ncols=3)


def _uncertainty_line(w: dict) -> str:
    """The whole-record fit's 68 % interval of each parameter (asymmetric where the likelihood is, as
    for L) and the correlations of A, B, L: two lines under the figure's title."""
    iv = w.get("intervals", {})
    c = w.get("correlation", {})
    nm = c.get("names", [])
    units = {"L_um": " µm", "stiffness_kN_per_m": " kN/m"}
    short = {"A_mu": "A", "B_mu": "B", "L_um": "L", "stiffness_kN_per_m": "k", "rate_mu_per_mm": "trend"}
    parts = [f"{short[k]} [{g3(iv[k][0], 3)}, {g3(iv[k][1], 3)}]{units.get(k, '')}"
             for k in short if iv.get(k) and None not in iv[k]]
    corr = [f"corr({a[0]},{b[0]}) {c['matrix'][nm.index(a)][nm.index(b)]:+.2f}"
            for a, b in (("A_mu", "B_mu"), ("A_mu", "L_um"), ("B_mu", "L_um")) if a in nm and b in nm]
    lines = []
    if parts:  # A, B, L on the first line; the stiffness, the trend and the correlations on the next
        lines.append(f"68 % intervals ({w.get('uncertainty', {}).get('method', 'jacobian')}): " + ", ".join(parts[:3]))
    rest = parts[3:] + corr
    if rest:
        lines.append(", ".join(rest))
    return "\n".join(lines)


def plot_identification(idn, path: str | Path, max_steps: int = 9) -> None:
    save(build_identification(idn, max_steps), path)


# ---------------------------------------------------------------------------
# reproduce
# ---------------------------------------------------------------------------
REPRODUCE_PANELS = (("A_mu", "A (direct effect, eq. 5)", 1e3, "A × 10³"),
                    ("B_mu", "B (state effect, eq. 6)", 1e3, "B × 10³"),
                    ("L_um", "L (slip distance, eq. 6)", 1.0, "L (µm)"),
                    ("k_cr_kN_per_m", "k_cr (eq. 13, per rider)", 1.0, "k_cr (kN/m)"))


def build_reproduce(rep: dict, warnings: list[dict] | None = None):
    """Bars: paper vs truth vs recovered (vs whole-record) for A, B, L, k_cr per lubricant."""
    from rig.model.checks import MARK

    plt = _plt()
    warnings = warnings or []
    foot = [f"{MARK} {w['where']}: {w['message']}" for w in warnings]
    lubs = list(rep["lubricants"])
    heights = [2.3, 2.3] + ([footnote_height_in(foot)] if foot else [])
    fig = plt.figure(figsize=(PAGE_WIDTH_IN, sum(heights) + 0.7), layout="constrained")
    gs = fig.add_gridspec(len(heights), 2, height_ratios=heights)
    x = np.arange(len(lubs))
    series = [("paper", "Table 2 (paper)", "0.55"), ("truth", "simulated trials' truth", "C2"),
              ("recovered", "recovered (eqs. 10-12)", "C0"), ("whole_record", "whole-record fit", "C3")]
    present = [s for s in series if s[0] == "paper" or all(s[0] in rep["lubricants"][lb] for lb in lubs)]
    w = 0.8 / len(present)
    for p, (k, title, scale, ylabel) in enumerate(REPRODUCE_PANELS):
        ax = fig.add_subplot(gs[p // 2, p % 2])
        for j, (key, label, c) in enumerate(present):
            m, e = [], []
            for lub in lubs:
                r = rep["lubricants"][lub]
                src = r["paper"][k] if key == "paper" else {"mean": r[key]["mean"].get(k), "sem": r[key]["sem"].get(k)}
                m.append((src["mean"] if src["mean"] is not None else np.nan) * scale)
                e.append((src["sem"] if src["sem"] is not None else 0.0) * scale)
            ax.bar(x + w * (j - (len(present) - 1) / 2), m, w, yerr=e, color=c, label=label, capsize=2,
                   error_kw={"lw": 0.7})
        ax.set_xticks(x, lubs)
        ax.set_ylabel(ylabel)
        bad = [w_ for w_ in warnings if w_["param"] == k]
        ax.set_title(title + (f" {MARK}" if bad else ""), color=WARN_COLOR if bad else "k")
        ax.axhline(0, color="k", lw=0.5)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(present))
    fig.suptitle(f"Table 2 reproduced: {rep['n_trials']} simulated trials per lubricant (mean ± s.e. of the mean)")
    if foot:
        footnote_axes(fig, gs[2, :], foot)
    return fig


def plot_reproduce(rep: dict, path: str | Path, warnings: list[dict] | None = None) -> None:
    save(build_reproduce(rep, warnings), path)


# ---------------------------------------------------------------------------
# stability
# ---------------------------------------------------------------------------
def _controller(s: dict) -> str:
    ctl = f"PID, ki = {s['ki_N_per_um_s']:g} N/(µm s)" if s["ki_N_per_um_s"] > 0 else "PD"
    return ctl + ("\nsensor noise off" if not s.get("sensor_noise", True) else "")


def build_stability_map(scans: list[dict], title: str = "", *, spread_max: float, onset_spread: float):
    """Stability map: each scanned kp (x, kN/m) per lubricant (column) and controller (row: PD,
    PID, PID with the sensor noise off): stick-slip (x) or steady sliding (o) by the scan's
    criterion, with the paper's eq. (8) for the fixture (2 N, kd, m), the discrete-time analysis
    of the rig's loop and the simulated boundary; one legend for all panels. ``spread_max`` and
    ``onset_spread`` are the scan's criterion (:mod:`rig.analysis.stability`, which calls this)."""
    SPREAD_MAX, ONSET_SPREAD = spread_max, onset_spread

    plt = _plt()
    lubs = list(dict.fromkeys(s["lubricant"] for s in scans))

    def row_key(s):
        return (s["ki_N_per_um_s"] > 0, not s.get("sensor_noise", True))

    rows = sorted({row_key(s) for s in scans})
    ncol = max(1, len(lubs))
    fig, axs = plt.subplots(len(rows), ncol, figsize=(PAGE_WIDTH_IN, 0.6 + 2.3 * len(rows) + 0.4),
                            squeeze=False, layout="constrained")
    legend = {}
    for s in scans:
        ax = axs[rows.index(row_key(s)), lubs.index(s["lubricant"])]
        kp = np.array([r["kp_N_per_um"] for r in s["runs"]]) * 1e3
        sp = np.array([r["spread"] for r in s["runs"]])
        bad = np.array([r["stick_slip"] for r in s["runs"]], bool)
        pos = sp[sp > 0]
        lo = max(float(pos.min()) / 2 if pos.size else 1e-3, 1e-4)
        sp = np.maximum(sp, lo)  # a spread of exactly 0 (noise-free steady sliding) drawn on the axis floor
        ax.scatter(kp[bad], sp[bad], marker="x", color="C3", s=14, lw=0.9, label="stick-slip (simulated)")
        ax.scatter(kp[~bad], sp[~bad], marker="o", facecolors="none", color="C2", s=14, lw=0.9,
                   label="steady sliding (simulated)")
        ax.axhline(SPREAD_MAX, color="0.6", lw=0.6, label=f"criterion: spread = {SPREAD_MAX:g} V0")
        lin = np.array([r.get("spread_linear_noise", np.nan) for r in s["runs"]], dtype=float)
        ok = np.isfinite(lin) & (lin > 0)
        if ok.any():  # what the LVDT noise alone drives in the linear loop (stability.noise_spread)
            order = np.argsort(kp[ok])
            ax.plot(kp[ok][order], lin[ok][order], color="C0", lw=0.8, alpha=0.7,
                    label="loop analysis + LVDT noise")
        if s.get("k_cr_eq8_N_per_um"):
            ax.axvline(s["k_cr_eq8_N_per_um"] * 1e3, color="k", ls="--", label="paper's eq. (8), 2N (PD: no I term)")
        if s.get("k_cr_loop_N_per_um"):
            ax.axvline(s["k_cr_loop_N_per_um"] * 1e3, color="C0", ls="-", label="rig loop analysis (1 kHz)")
        b_lo, b_hi = s.get("bracket_N_per_um") or (None, None)
        if b_lo and b_hi:
            ax.axvspan(b_lo * 1e3, b_hi * 1e3, color="C1", alpha=0.15, lw=0, label="simulated boundary (bracket)")
        lines = [f"{s['lubricant']}, {_controller(s)}"]
        if s.get("rel_bracket") is not None:
            r0, r1 = s["rel_bracket"]
            lines.append(f"sim/analysis−1 ∈ [{r0 * 100:+.1f}, {r1 * 100:+.1f}]%")  # the bracket (fits the panel)
        if not s.get("k_cr_loop_N_per_um") and not b_hi and not bad.any():
            lines.append("steady at every kp scanned")
        if s.get("onset_rel_diff") is not None:
            lines.append(f"onset (spread > {ONSET_SPREAD:g} V0): {s['onset_rel_diff'] * 100:+.1f}%")
            ax.axvline(s["k_onset_N_per_um"] * 1e3, color="C4", ls="-.", label="onset of oscillation")
        top = max(float(sp.max()), float(lin[ok].max()) if ok.any() else 0.0)
        y0, y1 = min(lo, SPREAD_MAX / 2), max(top * 2, SPREAD_MAX * 2)
        _log_axis(ax, y0, y1)
        ax.set_title("\n".join(lines), fontsize=7 if ncol > 1 else 8)
        ax.set_xlabel("kp (kN/m)")
        ax.set_ylabel("velocity spread / V0")
        for h, lab in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(lab, h)
    used = {(rows.index(row_key(s)), lubs.index(s["lubricant"])) for s in scans}
    for i in range(len(rows)):
        for j in range(ncol):
            if (i, j) not in used:
                axs[i, j].axis("off")
    if legend:
        fig.legend(list(legend.values()), list(legend.keys()), loc="outside lower center", ncols=3)
    if title:
        fig.suptitle(title)
    return fig


def _log_axis(ax, y0: float, y1: float) -> None:
    """A log y axis from y0 to y1 with plain labels (2 and 5 between the decades when it spans less than ~1.5)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_yscale("log")
    ax.set_ylim(y0, y1)
    ax.yaxis.set_major_locator(LogLocator(base=10, numticks=6))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:g}"))
    if y1 / y0 < 30:
        ax.yaxis.set_minor_locator(LogLocator(base=10, subs=(2.0, 5.0)))
        ax.yaxis.set_minor_formatter(FuncFormatter(lambda y, _: f"{y:g}"))
    else:
        ax.yaxis.set_minor_formatter(NullFormatter())


def plot_stability_map(scans: list[dict], path: str | Path, title: str = "", *, spread_max: float,
                       onset_spread: float) -> None:
    save(build_stability_map(scans, title, spread_max=spread_max, onset_spread=onset_spread), path)
