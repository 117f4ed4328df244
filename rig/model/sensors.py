"""The sensor chain: what lies between the interface's true friction force and the load cell's reading.

In the hardware's order (diagnosis.md for the extensions, the paper's section 3 for the rig):

1. ``normal_force_variation``: the friction force is mu (N1 + N2), not mu 2 N_nom
   (:func:`normal_factor`);
2. ``time_delay`` (Hess & Soom, steady_state baseline): mu_ss of the velocity delay_s ago
   (:func:`delayed`);
3. ``sensor_lag``: a first-order lag tau_s of the force sensing (:func:`lowpass_uneven`);
4. ``force_offset_drift``: a linear offset rate_N_per_s t (:func:`offset_drift`);
5. the transducer's noise, which enters BEFORE its analog filter (:func:`noisy_filtered`);
6. the analog first-order low-pass (100 Hz friction and LVDT, 10 Hz normals), exact for
   an input linear between samples (:func:`lowpass_uneven`, :func:`lowpass_tick` in the
   closed-loop kernel);
7. the ADC's quantization (LVDT 0.076 µm) and range (:func:`quantize`).

The profile's noise figures (``noise_sigma_*``) are the standard deviation of the noise
in the reading (after the filter; ±0.25 figures of the paper are 2 sigma), so the white
noise injected before the filter is scaled up by :func:`prefilter_noise_gain`.
"""

from __future__ import annotations

import math

import numpy as np
from rig.jitstart import kernel


def cutoff_tau_s(cutoff_hz: float) -> float:
    """Time constant (s) of a first-order analog low-pass with cutoff ``cutoff_hz``."""
    return 1.0 / (2.0 * math.pi * cutoff_hz)


def lowpass_uneven(t_s: np.ndarray, y: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass ``tau dy_f/dt = y - y_f`` on unevenly sampled data (exact for a
    piecewise-linear input). ``sensor_lag`` and the analog filters of synthetic records."""
    return _lowpass_uneven(np.ascontiguousarray(t_s, dtype=float), np.ascontiguousarray(y, dtype=float),
                           float(tau_s))


@kernel
def _lowpass_uneven(t, y, tau):
    n = t.shape[0]
    out = np.empty(n)
    out[0] = y[0]
    if tau <= 0.0:
        for i in range(n):
            out[i] = y[i]
        return out
    for i in range(1, n):
        h = t[i] - t[i - 1]
        a = math.exp(-h / tau)
        # exact response to a linear ramp from y[i-1] to y[i] over h
        g = (1.0 - a) * tau / h if h > 0 else 1.0
        out[i] = a * out[i - 1] + (1.0 - g) * y[i] + (g - a) * y[i - 1]
    return out


def lowpass_coefficients(dt_s: float, tau_s: float) -> tuple[float, float]:
    """(a, g) of :func:`lowpass_tick` for a tick ``dt_s``: a = exp(-dt/tau), g = (1 - a) tau / dt."""
    if tau_s <= 0:
        return 0.0, 0.0
    a = math.exp(-dt_s / tau_s)
    return a, (1.0 - a) * tau_s / dt_s


@kernel
def lowpass_tick(y, u_old, u_new, a, g):
    """tau dy/dt = u - y over one tick for u linear from u_old to u_new (as lowpass_uneven)."""
    return a * y + (1.0 - g) * u_new + (g - a) * u_old


def prefilter_noise_gain(dt_s: float, tau_s: float) -> float:
    """Factor from the reading's noise sigma to the sigma of white noise (one value per tick
    ``dt_s``, held over the tick) entering the analog filter: the filter passes the variance
    fraction (1 - a)^2 / (1 - a^2) = (1 - a) / (1 + a) of held white noise, a = exp(-dt/tau)."""
    if tau_s <= 0:
        return 1.0
    a = math.exp(-dt_s / tau_s)
    return math.sqrt((1.0 + a) / (1.0 - a))


@kernel
def quantize(x, q, lo, hi):
    """ADC reading: rounded to the step ``q`` (0 = none) and clipped to [lo, hi]."""
    if q > 0.0:
        x = math.floor(x / q + 0.5) * q
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


def noisy_filtered(t_s: np.ndarray, y: np.ndarray, tau_s: float, sigma: float, rng: np.random.Generator,
                   dt_s: float) -> np.ndarray:
    """A sensor's analog output on the loop grid ``t_s`` (step ``dt_s``): white noise of
    reading sigma ``sigma``, held over each tick, added to ``y`` BEFORE the first-order filter
    ``tau_s`` (by linearity the noise is filtered apart, as the closed-loop kernel does)."""
    out = lowpass_uneven(t_s, y, tau_s)
    if sigma > 0:
        a = math.exp(-dt_s / tau_s) if tau_s > 0 else 0.0
        w = sigma * prefilter_noise_gain(dt_s, tau_s) * rng.standard_normal(out.size)
        from scipy.signal import lfilter  # here, not at import: scipy.signal costs ~1 s of start-up

        out = out + lfilter([1.0 - a], [1.0, -a], w)
    return out


@kernel
def _interp_delay(t, v, delay):
    n = t.shape[0]
    out = np.empty(n)
    j = 0
    for i in range(n):
        tq = t[i] - delay
        if tq <= t[0]:
            out[i] = v[0]
            continue
        while j + 1 < n and t[j + 1] < tq:
            j += 1
        while j > 0 and t[j] > tq:
            j -= 1
        if j + 1 >= n:
            out[i] = v[n - 1]
        else:
            w = (tq - t[j]) / (t[j + 1] - t[j])
            out[i] = v[j] + w * (v[j + 1] - v[j])
    return out


def delayed(t_s: np.ndarray, y: np.ndarray, delay_s: float) -> np.ndarray:
    """``y(t - delay_s)`` by linear interpolation (the first value before the record)."""
    if delay_s <= 0:
        return np.asarray(y, dtype=float)
    return _interp_delay(np.ascontiguousarray(t_s, dtype=float), np.ascontiguousarray(y, dtype=float),
                         float(delay_s))


def offset_drift(t_s: np.ndarray, rate_N_per_s: float) -> np.ndarray:
    """``force_offset_drift``: the offset rate_N_per_s t, t from the record's start (N)."""
    return float(rate_N_per_s) * np.asarray(t_s, dtype=float)


def normal_factor(n_samples: int, N_tot_N: np.ndarray | None, N_nom_N: float, varies: bool) -> np.ndarray:
    """The normal force multiplying mu: the measured N1 + N2 (``normal_force_variation``),
    else twice the nominal per-rider force."""
    if varies and N_tot_N is not None:
        return np.ascontiguousarray(N_tot_N, dtype=float)
    return np.full(n_samples, 2.0 * float(N_nom_N))
