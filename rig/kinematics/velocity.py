"""Velocity from a quantized, noisy LVDT position record (µm, s), shared by identification,
the Stribeck analysis, healing and diagnosis (velocity steps: :mod:`rig.kinematics.steps`).

Velocity estimators:

* :func:`velocity_paper` - Dupont & Dunlap's: a 10-point moving average of
  position followed by a central difference (section 4.2, Fig. 8).
* :func:`velocity_local_poly` - a local polynomial (default: quadratic) fit of
  position against time over a centred window of fixed duration, which handles
  uneven sampling and gaps and is unbiased for a constant acceleration. Its
  noise falls as ``window**-1.5``; the LVDT's 0.076 µm quantization and ±0.25 µm
  noise at 25 Hz need a window of about 1-2 s at 1 µm/s.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def velocity_paper(t_s: np.ndarray, x_um: np.ndarray, n_avg: int = 10) -> np.ndarray:
    """10-point moving average, then central difference (µm/s). Ends use one-sided differences."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x_um, dtype=float)
    if x.size < 3:
        return np.zeros_like(x)
    n_avg = max(1, min(int(n_avg), x.size))
    kernel = np.ones(n_avg) / n_avg
    xs = np.convolve(x, kernel, mode="same")
    # correct the edges of 'same' convolution (partial windows)
    norm = np.convolve(np.ones_like(x), kernel, mode="same")
    xs = xs / norm
    return np.gradient(xs, t)


@njit(cache=True)
def _local_poly(t, x, half_window, order):
    n = t.shape[0]
    v = np.empty(n)
    lo = 0
    hi = 0
    for i in range(n):
        while t[lo] < t[i] - half_window:
            lo += 1
        while hi + 1 < n and t[hi + 1] <= t[i] + half_window:
            hi += 1
        m = hi - lo + 1
        deg = order
        if m < deg + 2:
            deg = 1
        if m < 2:
            # isolated sample: difference to a neighbour
            j = i + 1 if i + 1 < n else i - 1
            v[i] = (x[j] - x[i]) / (t[j] - t[i])
            continue
        # least squares on centred time, normal equations (deg <= 2)
        s = np.zeros(5)
        r = np.zeros(3)
        for k in range(lo, hi + 1):
            d = t[k] - t[i]
            dk = 1.0
            for q in range(5):
                s[q] += dk
                if q < 3:
                    r[q] += dk * x[k]
                dk *= d
        if deg >= 2:
            a = np.array([[s[0], s[1], s[2]], [s[1], s[2], s[3]], [s[2], s[3], s[4]]])
            b = np.array([r[0], r[1], r[2]])
            det = np.linalg.det(a)
            if abs(det) > 1e-300:
                sol = np.linalg.solve(a, b)
                v[i] = sol[1]
                continue
        den = s[0] * s[2] - s[1] * s[1]
        if den <= 0.0:
            v[i] = 0.0
        else:
            v[i] = (s[0] * r[1] - s[1] * r[0]) / den
    return v


def velocity_local_poly(t_s: np.ndarray, x_um: np.ndarray, window_s: float | None = None,
                        order: int = 2) -> np.ndarray:
    """Velocity (µm/s) by a local polynomial fit of position over a centred time window.

    ``window_s`` defaults to ten median sample intervals (the paper's 10 points),
    at least 0.04 s. Works with uneven sampling and gaps (a sample whose window
    holds too few points falls back to a linear fit or a difference).
    """
    t = np.ascontiguousarray(t_s, dtype=float)
    x = np.ascontiguousarray(x_um, dtype=float)
    if t.size < 2:
        return np.zeros_like(x)
    if window_s is None:
        window_s = max(10.0 * float(np.median(np.diff(t))), 0.04)
    return _local_poly(t, x, 0.5 * float(window_s), int(min(max(order, 1), 2)))


def velocity_for_steps(t_s: np.ndarray, x_um: np.ndarray, slip_window_um: float = 5.0,
                       min_window_s: float = 0.1, max_window_s: float = 4.0) -> np.ndarray:
    """Velocity with a window sized for a slip of about ``slip_window_um`` at the local speed.

    A first pass with a long window gives the speed (5 µm of slip keeps the 0.076 µm
    quantization and ±0.25 µm noise below about 2 % of v at 25 Hz while resolving L ~ 20 µm); the final window is
    ``slip_window_um / v`` clipped to [min, max] seconds, so that fast sliding keeps
    time resolution and slow sliding averages the LVDT's quantization out.
    """
    t = np.ascontiguousarray(t_s, dtype=float)
    x = np.ascontiguousarray(x_um, dtype=float)
    v0 = velocity_local_poly(t, x, window_s=max_window_s, order=1)
    w = np.clip(slip_window_um / np.maximum(np.abs(v0), 1e-3), min_window_s, max_window_s)
    return _local_poly_var(t, x, 0.5 * w)


@njit(cache=True)
def _line_sums(t, x, lo, hi, tc):
    """The sums of a least-squares line over samples [lo, hi] with time origin ``tc``:
    count, sum of (t - tc), of (t - tc)^2, of x, of (t - tc) x."""
    s1 = 0.0
    st = 0.0
    stt = 0.0
    sx = 0.0
    stx = 0.0
    for k in range(lo, hi + 1):
        d = t[k] - tc
        s1 += 1.0
        st += d
        stt += d * d
        sx += x[k]
        stx += d * x[k]
    return s1, st, stt, sx, stx


@njit(cache=True)
def _local_poly_var(t, x, half):
    n = t.shape[0]
    v = np.empty(n)
    for i in range(n):
        h = half[i]
        lo = i
        while lo > 0 and t[lo - 1] >= t[i] - h:
            lo -= 1
        hi = i
        while hi + 1 < n and t[hi + 1] <= t[i] + h:
            hi += 1
        if hi - lo < 1:
            j = i + 1 if i + 1 < n else i - 1
            v[i] = (x[j] - x[i]) / (t[j] - t[i])
            continue
        s1, st, stt, sx, stx = _line_sums(t, x, lo, hi, t[i])
        den = s1 * stt - st * st
        v[i] = (s1 * stx - st * sx) / den if den > 0.0 else 0.0
    return v


def estimate_velocity(t_s: np.ndarray, x_um: np.ndarray, method: str = "local_poly") -> np.ndarray:
    """Velocity from the LVDT: ``paper`` (10-point moving average + central difference,
    section 4.2, Fig. 8) or ``local_poly`` (local linear fit over about 2 µm of slip at the
    local speed; handles uneven sampling; much less noisy at µm/s)."""
    if method == "paper":
        return velocity_paper(t_s, x_um, 10)
    if method == "local_poly":
        return velocity_for_steps(t_s, x_um, slip_window_um=2.0, min_window_s=0.04, max_window_s=4.0)
    if method == "local_poly_fixed":
        return velocity_local_poly(t_s, x_um)
    raise ValueError(f"unknown velocity method {method!r} (paper, local_poly)")


def median_dt(t_s: np.ndarray) -> float:
    d = np.diff(np.asarray(t_s, dtype=float))
    return float(np.median(d)) if d.size else math.nan


def velocity_changes(t_s: np.ndarray, v_um_s: np.ndarray, window_s: float = 1.0,
                     min_log_ratio: float = 0.3) -> np.ndarray:
    """Times (s) of the velocity changes: |ln v(t + w) - ln v(t - w)| > min_log_ratio, local
    maxima at least 2 w apart (diagnosis: transient scaling and the figure's markers)."""
    t = np.asarray(t_s, dtype=float)
    lv = np.log(np.maximum(np.abs(np.asarray(v_um_s, dtype=float)), 1e-2))
    a = np.interp(t + window_s, t, lv) - np.interp(t - window_s, t, lv)
    c = np.abs(a)
    out: list[int] = []
    last = -np.inf
    for i in np.flatnonzero(c > min_log_ratio):
        if t[i] - last < 2 * window_s:
            if c[i] > c[out[-1]]:
                out[-1] = i
            last = t[i]
            continue
        out.append(i)
        last = t[i]
    return t[np.asarray(out, dtype=int)] if out else np.zeros(0)


# ---------------------------------------------------------------------------
# Edge-preserving smoothing (diagnosis: velocity steps stay steps)
# ---------------------------------------------------------------------------
@njit(cache=True)
def _centred_line_fit(t, x, lo, hi, tc):
    """Least-squares line x = a + b (t - tc) over [lo, hi]; returns a, b, residual mean square."""
    m = hi - lo + 1
    if m < 3:
        return np.nan, np.nan, np.inf
    s1, st, stt, sx, stx = _line_sums(t, x, lo, hi, tc)
    den = s1 * stt - st * st
    if den <= 0.0:
        return np.nan, np.nan, np.inf
    b = (s1 * stx - st * sx) / den
    a = (sx - b * st) / s1
    r = 0.0
    for k in range(lo, hi + 1):
        e = x[k] - a - b * (t[k] - tc)
        r += e * e
    return a, b, r / (m - 2)


@njit(cache=True)
def edge_preserving_line(t, x, half):
    """Smoothed position and velocity (µm, µm/s) that keep a velocity step a step: at each sample
    the best (least residual) of the centred line fit over ``[t - half, t + half]`` and, when
    (nearly) full in time, the left ``[t - 2 half, t]`` and right ``[t, t + 2 half]`` ones."""
    n = t.shape[0]
    xs = np.empty(n)
    vs = np.empty(n)
    lo_l = 0
    lo_c = 0
    hi_c = 0
    hi_r = 0
    for i in range(n):
        w = half[i]
        # left window [t_i - 2w, t_i]
        while t[lo_l] < t[i] - 2.0 * w:
            lo_l += 1
        while lo_l > 0 and t[lo_l - 1] >= t[i] - 2.0 * w:
            lo_l -= 1
        while t[lo_c] < t[i] - w:
            lo_c += 1
        while lo_c > 0 and t[lo_c - 1] >= t[i] - w:
            lo_c -= 1
        if hi_c < i:
            hi_c = i
        while hi_c + 1 < n and t[hi_c + 1] <= t[i] + w:
            hi_c += 1
        while hi_c > i and t[hi_c] > t[i] + w:
            hi_c -= 1
        if hi_r < i:
            hi_r = i
        while hi_r + 1 < n and t[hi_r + 1] <= t[i] + 2.0 * w:
            hi_r += 1
        while hi_r > i and t[hi_r] > t[i] + 2.0 * w:
            hi_r -= 1
        best_r = np.inf
        best_a = x[i]
        best_b = 0.0
        a, b, r = _centred_line_fit(t, x, lo_c, hi_c, t[i])
        if r < best_r:
            best_r, best_a, best_b = r, a, b
        # one-sided windows only when (nearly) full: a short window's scatter is no evidence. Full in
        # time, not in rows: a record logged at 10 Hz before a step and 100 Hz after it has ten times
        # fewer rows in the slow side's window, which is still full (counted in rows, the slow side
        # never qualified and the centred window smeared the step over the second before it)
        span_c = t[hi_c] - t[lo_c]
        if t[i] - t[lo_l] >= 0.8 * span_c and i - lo_l + 1 >= 5:
            a, b, r = _centred_line_fit(t, x, lo_l, i, t[i])
            if r < best_r * 0.999:
                best_r, best_a, best_b = r, a, b
        if t[hi_r] - t[i] >= 0.8 * span_c and hi_r - i + 1 >= 5:
            a, b, r = _centred_line_fit(t, x, i, hi_r, t[i])
            if r < best_r * 0.999:
                best_r, best_a, best_b = r, a, b
        if not np.isfinite(best_r):
            # too few points: difference to a neighbour
            j = i + 1 if i + 1 < n else i - 1
            best_a = x[i]
            best_b = (x[j] - x[i]) / (t[j] - t[i])
        xs[i] = best_a
        vs[i] = best_b
    return xs, vs
