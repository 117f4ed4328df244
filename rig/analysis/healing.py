"""Slide-hold-slide: frictional healing from the holds of a record (``rig heal``).

The friction lab's protocol (Dieterich 1972; Beeler, Tullis & Weeks 1994; Marone 1998):
slide at ``v`` to steady state, stop and rest ``t_h``, re-slide. For each hold:

* ``delta_mu_peak`` = mu_peak - mu_ss: the peak friction on re-sliding over the steady
  friction before the hold (``reference: before``). When the slide after the hold differs
  from the one before it (another velocity, or a reversal, as the rests inside a
  velocity-steps trial), mu_ss is the steady friction at the end of the re-slide
  (``reference: after``), so that the direct effect A ln(v_after/v_before) is not counted
  as healing;
* ``delta_mu_relax`` = mu_ss - mu_end: how far the friction relaxed during the hold (the
  creep of the interface against the loading system's stored force), mu_end at the end of
  the rest;
* the healing rate ``beta_per_decade``: the least-squares slope of delta_mu_peak against
  log10 t_h over the holds with a reference, with its standard error
  ``beta_per_decade_sd`` (s^2 / Sxx, s^2 the residual variance on n - 2 degrees of freedom).

Signs follow the sliding direction (mu of a slide in -x is taken as -mu), so a reversal's
peak is a peak too. Holds are found in the record, not taken from a recipe: rests of the
reference (``position_ref_um``, exact for the rig's logs) or, without one, of the measured
position (local slopes over +-0.25 s that are zero within 3 standard errors), at least
``min_hold_s`` long with sliding on both sides.
A slide ends at a rest or at a change of velocity inside it (a velocity step). A ``hold``
event of the planner (slide_hold_slide) adds the planned hold time.

What the two state laws predict (eqs. 5-6 of Dupont & Dunlap 1995 and the aging law,
rig.model.friction): at rest the Dieterich aging law's state grows as
theta = B ln(1 + v t_h / L) above its steady value, so at a stiff loading
delta_mu_peak ~ B ln(1 + v t_h / L), B ln 10 per decade once t_h >> L/v; the Ruina slip law
evolves only with slip and does not heal at rest (delta_mu_peak ~ 0).
:func:`aging_prediction` is that formula; docs/identification.md has the derivation and
the figure.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from rig.data import TrialData, atomic_write_text
from rig.kinematics import velocity_changes

SCHEMA = "rig.heal/1"
MIN_HOLD_S = 0.5          # shorter rests are ramps' turning points, not holds
PEAK_SMOOTH_S = 0.25       # moving average before the peak (the noise biases a raw maximum up)
STEADY_FRACTION = 0.3     # the steady friction: mean over the last 30 % of a slide
PEAK_FRACTION = 0.5       # the peak is looked for in the first half of the re-slide
END_OF_HOLD_S = 0.5       # mu_end: mean over the last 0.5 s of the rest (at most a fifth of it)
CHANGE_WINDOW_S = 1.0     # velocity changes inside a slide (rig.kinematics.velocity_changes) end it
REST_WINDOW_S = 0.25      # half-window of the local slopes of a measured position (no reference)


def aging_prediction(B_mu: float, L_um: float, v_um_s: float, t_hold_s) -> np.ndarray:
    """delta_mu_peak of the aging law at a stiff loading: B ln(1 + v t_h / L) (per interface)."""
    return B_mu * np.log1p(v_um_s * np.asarray(t_hold_s, dtype=float) / L_um)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index pairs, end exclusive, of the True runs of ``mask``."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def _local_slopes(t: np.ndarray, x: np.ndarray, half_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares slopes of ``x`` over windows of +-``half_s`` and their standard errors."""
    dt = float(np.median(np.diff(t)))
    half = max(2, int(round(half_s / dt)))
    k = np.ones(2 * half + 1)
    tc, xc = t - t.mean(), x - x.mean()
    n = np.convolve(np.ones_like(t), k, "same")
    st, sx = np.convolve(tc, k, "same"), np.convolve(xc, k, "same")
    stt = np.convolve(tc * tc, k, "same") - st * st / n
    stx = np.convolve(tc * xc, k, "same") - st * sx / n
    sxx = np.convolve(xc * xc, k, "same") - sx * sx / n
    ok = stt > 0
    slope = np.where(ok, stx / np.where(ok, stt, 1.0), 0.0)
    ssr = np.maximum(sxx - slope * stx, 0.0)
    se = np.where(ok & (n > 2), np.sqrt(ssr / np.maximum(n - 2, 1) / np.where(ok, stt, 1.0)), np.inf)
    return slope, se


def _slope_se(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of ``x`` over ``t`` and its standard error (0 for an exact line)."""
    if t.size < 3:
        return 0.0, math.inf
    tc = t - t.mean()
    stt = float(np.dot(tc, tc))
    if stt <= 0:
        return 0.0, math.inf
    b = float(np.dot(tc, x - x.mean())) / stt
    r = x - x.mean() - b * tc
    return b, math.sqrt(float(np.dot(r, r)) / (t.size - 2) / stt)


def find_rests(trial: TrialData, min_hold_s: float = MIN_HOLD_S) -> tuple[list[tuple[int, int]], np.ndarray, str]:
    """Rests of the record (index ranges, end exclusive), the velocity used, and its source.

    From the reference when the record has one (its velocity is exact: a rest is where it is 0);
    else from the measured position: local slopes over +-0.25 s, a rest where the slope is
    indistinguishable from zero (below 3 standard errors of the local fit) and below 15 % of
    the record's typical sliding speed (its 90th percentile)."""
    t = np.asarray(trial.time_s, float)
    ref = trial.position_ref_um
    exact = ref is not None and bool(np.isfinite(ref).all()) and np.ptp(ref) > 0
    if exact:
        x = np.asarray(ref, float)
        v = np.gradient(x, t)
        rest = np.abs(v) < 1e-6 * max(1.0, float(np.abs(v).max()))
    else:
        v, se = _local_slopes(t, np.asarray(trial.position_um, float), REST_WINDOW_S)
        vs = float(np.percentile(np.abs(v), 90))
        rest = (np.abs(v) < 3.0 * se) & (np.abs(v) < 0.15 * vs)
        # the noise breaks a long rest now and then: close gaps shorter than the window
        gap = max(1, int(round(2 * REST_WINDOW_S / float(np.median(np.diff(t))))))
        for i, j in _runs(~rest):
            if 0 < i and j < rest.size and j - i <= gap:
                rest[i:j] = True
    runs = [(i, j) for i, j in _runs(rest) if t[j - 1] - t[i] >= min_hold_s]
    return runs, v, "position_ref_um" if exact else "position_um"


def _smooth(a: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or a.size < n:
        return a
    return np.convolve(a, np.ones(n) / n, mode="valid")


def _cruise(v: np.ndarray) -> float:
    """The velocity of a slide: the median where |v| is within 20 % of its largest (ramps left out)."""
    av = np.abs(v)
    return float(np.median(v[av >= 0.8 * av.max()]))


def _hold(t, mu, v, before: tuple[int, int], rest: tuple[int, int], after: tuple[int, int], dt: float,
          x: np.ndarray | None = None) -> dict:
    """One hold. ``x``: a measured position (no reference): the slides' velocities are then line
    fits over each slide, and their equality is judged within 20 % (5 % from the reference)."""
    b0, b1 = before
    a0, a1 = after
    r0, r1 = rest
    if x is None:
        vb, va, same_tol = _cruise(v[b0:b1]), _cruise(v[a0:a1]), 0.05
    else:
        vb, va, same_tol = _slope_se(t[b0:b1], x[b0:b1])[0], _slope_se(t[a0:a1], x[a0:a1])[0], 0.2
    sb, sa = (1.0 if vb >= 0 else -1.0), (1.0 if va >= 0 else -1.0)
    guard = max(1, int(round(0.1 / dt)))  # the ramps at both ends of a slide
    win_b = slice(b0 + int((b1 - b0) * (1 - STEADY_FRACTION)), max(b0 + 1, b1 - guard))
    mu_before = float(np.mean(sb * mu[win_b]))
    n_end = max(1, min(int(round(END_OF_HOLD_S / dt)), (r1 - r0) // 5))
    mu_end = float(np.mean(sb * mu[r1 - n_end:r1]))
    pk_end = a0 + max(3, int((a1 - a0) * PEAK_FRACTION))
    seg = sa * mu[a0:pk_end]
    sm = _smooth(seg, max(1, int(round(PEAK_SMOOTH_S / dt))))
    k = int(np.argmax(sm))
    mu_peak = float(sm[k])
    t_peak = float(t[a0 + k + (seg.size - sm.size) // 2])
    win_a = slice(a0 + int((a1 - a0) * (1 - STEADY_FRACTION)), max(a0 + 1, a1 - guard))
    mu_after = float(np.mean(sa * mu[win_a]))
    same = sa == sb and abs(va - vb) <= same_tol * abs(vb)
    ref, ref_mu = ("before", mu_before) if same else ("after", mu_after)
    return {"t_s": float(t[r0]), "t_end_s": float(t[r1 - 1]), "hold_s": float(t[r1 - 1] - t[r0]),
            "v_before_um_s": vb, "v_after_um_s": va, "reversal": bool(sa != sb), "reference": ref,
            "mu_ss": ref_mu, "mu_before": mu_before, "mu_after": mu_after, "mu_end_of_hold": mu_end,
            "mu_peak": mu_peak, "t_peak_s": t_peak,
            "delta_mu_peak": mu_peak - ref_mu, "delta_mu_relax": mu_before - mu_end}


def healing_rate(t_hold_s, dmu) -> tuple[float | None, float | None]:
    """Least-squares slope of delta_mu against log10 t_hold and its standard error."""
    lx = np.log10(np.asarray(t_hold_s, float))
    y = np.asarray(dmu, float)
    if y.size < 2 or np.ptp(lx) < 0.05:
        return None, None
    sxx = float(np.sum((lx - lx.mean()) ** 2))
    beta = float(np.sum((lx - lx.mean()) * (y - y.mean())) / sxx)
    if y.size < 3:
        return beta, None
    r = y - (y.mean() + beta * (lx - lx.mean()))
    return beta, float(math.sqrt(float(np.dot(r, r)) / (y.size - 2) / sxx))


def heal(trial: TrialData, *, min_hold_s: float = MIN_HOLD_S) -> dict:
    """The holds of ``trial`` and the healing rate (module docstring). Raises ValueError when
    the record has no hold with sliding on both sides."""
    t = np.asarray(trial.time_s, float)
    if t.size < 10:
        raise ValueError(f"{t.size} samples: too few to find holds")
    mu = np.asarray(trial.mu, float)
    dt = float(np.median(np.diff(t)))
    rests, v, source = find_rests(trial, min_hold_s)
    x = np.asarray(trial.position_ref_um if source == "position_ref_um" else trial.position_um, float)
    # a slide ends at a change of velocity (a velocity step inside it), not only at a rest
    changes = velocity_changes(t, v, CHANGE_WINDOW_S, 0.3)
    planned = [e for e in (trial.events or []) if e.get("kind") == "hold" and "hold_s" in e]
    holds = []
    for k, (r0, r1) in enumerate(rests):
        if r0 == 0 or r1 >= t.size:
            continue  # a rest at either end of the record has no slide on one side
        b0 = rests[k - 1][1] if k > 0 else 0
        a1 = rests[k + 1][0] if k + 1 < len(rests) else t.size
        inside = changes[(changes > t[b0] + 2 * CHANGE_WINDOW_S) & (changes < t[r0] - 2 * CHANGE_WINDOW_S)]
        if inside.size:
            b0 = int(np.searchsorted(t, inside[-1] + CHANGE_WINDOW_S))
        inside = changes[(changes > t[r1 - 1] + 2 * CHANGE_WINDOW_S) & (changes < t[a1 - 1] - 2 * CHANGE_WINDOW_S)]
        if inside.size:
            a1 = int(np.searchsorted(t, inside[0] - CHANGE_WINDOW_S))
        if r0 - b0 < 5 or a1 - r1 < 5:
            continue
        h = _hold(t, mu, v, (b0, r0), (r0, r1), (r1, a1), dt, None if source == "position_ref_um" else x)
        # a rest is a hold when the record shows it standing still against both slides: the
        # rest's own slope below 10 % of theirs, known to 5 % of them (slow sliding on a noisy
        # record, which the local slopes cannot tell from rest, is not a hold)
        v_slide = min(abs(h["v_before_um_s"]), abs(h["v_after_um_s"]))
        v_rest, se_rest = _slope_se(t[r0:r1], x[r0:r1])
        if abs(v_rest) > 0.1 * v_slide or se_rest > 0.05 * v_slide:
            continue
        ev = min(planned, key=lambda e: abs(e["t_s"] - h["t_s"]), default=None)
        if ev is not None and abs(ev["t_s"] - h["t_s"]) < max(1.0, 0.1 * h["hold_s"]):
            h["hold_s_planned"] = float(ev["hold_s"])
        h["hold"] = len(holds)
        holds.append(h)
    if not holds:
        raise ValueError(f"no hold of at least {min_hold_s:g} s between two slides was found ({len(rests)} "
                         f"candidate rest(s) in {source}, none standing still against slides on both sides)")
    use = [h for h in holds if not h["reversal"]] or holds
    th = [h.get("hold_s_planned", h["hold_s"]) for h in use]
    beta, beta_sd = healing_rate(th, [h["delta_mu_peak"] for h in use])
    beta_r, beta_r_sd = healing_rate(th, [h["delta_mu_relax"] for h in use])
    notes = []
    if beta is None:
        notes.append("healing rate not estimated: the holds span less than a tenth of a decade of hold time"
                     if len(use) > 1 else "healing rate not estimated: one hold")
    if any(h["reversal"] for h in holds):
        notes.append(f"{sum(h['reversal'] for h in holds)} hold(s) between slides in opposite directions "
                     "(e.g. a velocity-steps trial's rests): delta_mu_peak relative to the steady friction after "
                     "the hold" + ("; left out of the healing rate" if len(use) < len(holds) else ""))
    return {"schema": SCHEMA, "source": trial.source, "rests_from": source, "n_holds": len(holds),
            "holds": holds, "beta_per_decade": beta, "beta_per_decade_sd": beta_sd,
            "relax_per_decade": beta_r, "relax_per_decade_sd": beta_r_sd,
            "holds_in_rate": [h["hold"] for h in use], "notes": notes,
            "normal_force_N": float(trial.normal_force_N)}


def _clean(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def write_json(rep: dict, path) -> None:
    atomic_write_text(path, json.dumps(_clean(rep), indent=2, allow_nan=False) + "\n")


def build_heal(rep: dict, trial: TrialData | None = None):
    """Left: mu against time with the holds shaded (when the record is given); right: the
    field's convention, delta_mu_peak and delta_mu_relax against log hold time, with the
    fitted healing rate."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from rig.analysis.plots import PAGE_WIDTH_IN, _plt, pm

    plt = _plt()
    ncol = 2 if trial is not None else 1
    fig, axs = plt.subplots(1, ncol, figsize=(PAGE_WIDTH_IN, 2.8), layout="constrained", squeeze=False)
    axs = axs[0]
    if trial is not None:
        ax = axs[0]
        ax.plot(trial.time_s, trial.mu, color="0.3", lw=0.6, label="μ")
        for h in rep["holds"]:
            ax.axvspan(h["t_s"], h["t_end_s"], color="C0", alpha=0.15, lw=0)
            ax.plot(h["t_peak_s"], h["mu_peak"] * (1 if h["v_after_um_s"] >= 0 else -1), "v", color="C3", ms=4)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("μ")
        ax.set_title("record: holds shaded, peaks marked")
    ax = axs[-1]
    holds = rep["holds"]
    th = np.array([h.get("hold_s_planned", h["hold_s"]) for h in holds])
    ax.plot(th, [h["delta_mu_peak"] for h in holds], "o", color="C3", label="Δμ_peak")
    ax.plot(th, [h["delta_mu_relax"] for h in holds], "s", color="C0", mfc="none", label="Δμ_relax")
    if rep["beta_per_decade"] is not None:
        use = [holds[i] for i in rep["holds_in_rate"]]
        tu = np.array([h.get("hold_s_planned", h["hold_s"]) for h in use])
        lx = np.log10(tu)
        y = np.array([h["delta_mu_peak"] for h in use])
        tt = np.logspace(lx.min(), lx.max(), 50)
        ax.plot(tt, y.mean() + rep["beta_per_decade"] * (np.log10(tt) - lx.mean()), "--", color="C3", lw=0.8,
                label=f"β = {pm(rep['beta_per_decade'], rep['beta_per_decade_sd'])} per decade")
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.axhline(0.0, color="0.6", lw=0.5)
    ax.set_xlabel("hold time (s)")
    ax.set_ylabel("Δμ")
    ax.set_title("healing: Δμ against log hold time")
    h_, lab = ax.get_legend_handles_labels()
    fig.legend(h_, lab, loc="outside lower center", ncols=3)
    return fig


def plot_heal(rep: dict, path: str | Path, trial: TrialData | None = None) -> None:
    from rig.analysis.plots import save

    save(build_heal(rep, trial), path)


__all__ = ["heal", "find_rests", "healing_rate", "aging_prediction", "write_json", "build_heal", "plot_heal",
           "SCHEMA"]
