"""Velocity from a quantized, noisy LVDT position record (µm, s).

The one kinematics module. Estimators shared by identification and diagnosis:

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
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        r0 = 0.0
        r1 = 0.0
        for k in range(lo, hi + 1):
            d = t[k] - t[i]
            s0 += 1.0
            s1 += d
            s2 += d * d
            r0 += x[k]
            r1 += d * x[k]
        den = s0 * s2 - s1 * s1
        v[i] = (s0 * r1 - s1 * r0) / den if den > 0.0 else 0.0
    return v


def cumulative_slip_um(t_s: np.ndarray, v_um_s: np.ndarray) -> np.ndarray:
    """Accumulated slip distance (µm), the trapezoidal integral of |v|."""
    t = np.asarray(t_s, dtype=float)
    v = np.abs(np.asarray(v_um_s, dtype=float))
    out = np.zeros_like(t)
    out[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))
    return out


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
