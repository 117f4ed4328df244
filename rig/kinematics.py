"""Velocity from a quantized, noisy LVDT position record (µm, s).

The one kinematics module: velocity and velocity steps from a quantized, noisy position
record, shared by identification, the Stribeck analysis and diagnosis.

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

import bisect
import math
from dataclasses import dataclass

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
    """Smoothed position and velocity: best of left, right and centred line fits (see module doc)."""
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


# ---------------------------------------------------------------------------
# Velocity steps: from the log's events when present, else from the data.
#
# Detection from the data works on the position only, so it is robust to friction
# noise, handles steps up and down, uneven sampling and gaps: a velocity with a window of
# about ``slip_window_um`` of slip at the local speed (:func:`velocity_for_steps`) sets a
# left and a right window for every sample; straight lines fitted in both give the
# velocities just before and after, r = ln(v_right / v_left) peaks at a step; peaks with
# |r| > ln(min_ratio), largest within their windows, are steps, each refined to the
# intersection of the straight lines before and after it (the *effective step*).
# ---------------------------------------------------------------------------
VELOCITY_KEYS = ("v2_um_s", "v_um_s", "velocity_um_s", "target_v_um_s", "v_to_um_s", "to_um_s")


@dataclass
class Step:
    """One velocity step. ``i`` is the first sample at or after the effective step time."""

    t_s: float          # effective step time (intersection of the two position lines)
    t_nominal_s: float  # event time or detected peak
    i: int
    v1_um_s: float
    v2_um_s: float
    x_um: float         # position at the effective step
    pre: tuple[int, int]    # sample range [lo, hi) of the segment before (after the previous step)
    post: tuple[int, int]   # sample range [lo, hi) of the segment after (up to the next step)
    source: str = "data"    # "events" or "data"

    @property
    def direction(self) -> str:
        return "up" if self.v2_um_s > self.v1_um_s else "down"


def line_fit(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Least-squares straight line x = a + b t; returns (a, b)."""
    if t.size < 2:
        return (float(x[0]) if x.size else math.nan), math.nan
    tm = t.mean()
    xm = x.mean()
    dt = t - tm
    den = float(np.dot(dt, dt))
    b = float(np.dot(dt, x - xm) / den) if den > 0 else math.nan
    return float(xm - b * tm), b


@njit(cache=True)
def _side_slopes(t, x, half_l, half_r, min_pts):
    """Slopes of lines fitted left [t-hl, t) and right [t, t+hr) of each sample (sample
    count at least ``min_pts`` on each side when available)."""
    n = t.shape[0]
    # prefix sums with a local origin for accuracy
    t0 = t[0]
    x0 = x[0]
    c1 = np.zeros(n + 1)
    ct = np.zeros(n + 1)
    cx = np.zeros(n + 1)
    ctt = np.zeros(n + 1)
    ctx = np.zeros(n + 1)
    for k in range(n):
        tk = t[k] - t0
        xk = x[k] - x0
        c1[k + 1] = c1[k] + 1.0
        ct[k + 1] = ct[k] + tk
        cx[k + 1] = cx[k] + xk
        ctt[k + 1] = ctt[k] + tk * tk
        ctx[k + 1] = ctx[k] + tk * xk
    vl = np.full(n, np.nan)
    vr = np.full(n, np.nan)
    lo = 0
    for i in range(n):
        # left window [lo, i)
        lo = i
        while lo > 0 and (t[i] - t[lo - 1] <= half_l[i] or i - lo < min_pts):
            lo -= 1
        hi = i
        while hi < n and (t[hi] - t[i] < half_r[i] or hi - i < min_pts):
            hi += 1
        for side in range(2):
            a = lo if side == 0 else i
            b = i if side == 0 else hi
            m = c1[b] - c1[a]
            if m < 3:
                continue
            st = ct[b] - ct[a]
            sx = cx[b] - cx[a]
            stt = ctt[b] - ctt[a]
            stx = ctx[b] - ctx[a]
            den = m * stt - st * st
            if den <= 0:
                continue
            s = (m * stx - st * sx) / den
            if side == 0:
                vl[i] = s
            else:
                vr[i] = s
    return vl, vr


def _thin(t: np.ndarray, x: np.ndarray, min_dt: float = 0.02):
    """Block-average a densely sampled record to about ``min_dt`` (detection only)."""
    dtm = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    k = int(min_dt / dtm) if dtm > 0 else 1
    if k <= 1:
        return t, x, np.arange(t.size)
    m = (t.size // k) * k
    tb = t[:m].reshape(-1, k).mean(axis=1)
    xb = x[:m].reshape(-1, k).mean(axis=1)
    idx = np.arange(0, m, k) + k // 2
    return tb, xb, idx


def _steps_from_events(trial, min_ratio: float) -> list[tuple[float, dict]]:
    """(time, event) for every event that announces a velocity change."""
    out = []
    for ev in trial.events or []:
        kind = str(ev.get("kind", "")).lower()
        if "t_s" not in ev:
            continue
        v_new = None
        for key in VELOCITY_KEYS:
            if key in ev and ev[key] is not None:
                try:
                    v_new = float(ev[key])
                except (TypeError, ValueError):
                    v_new = None
                break
        if v_new is None and not ("step" in kind and "velocity" in kind):
            continue
        out.append((float(ev["t_s"]), v_new, ev))
    out.sort(key=lambda e: e[0])
    # keep changes only
    kept = []
    last_v = None
    for tk, vk, ev in out:
        v_old = ev.get("v1_um_s", last_v)
        if vk is not None and v_old is not None and v_old > 0 and vk > 0 and \
                abs(math.log(vk / v_old)) < math.log(min_ratio):
            last_v = vk
            continue
        if vk is not None and v_old is not None and (v_old <= 0 or vk <= 0):
            last_v = vk
            continue
        kept.append((tk, ev))
        if vk is not None:
            last_v = vk
    return kept


def pause_intervals(events) -> list[tuple[float, float]]:
    """The operator's pauses of a trial from its log's events: ``(t_pause_s, t_resume_s)`` of each hold
    (``pause`` ... ``resume``; a pause never resumed lasts to infinity). The rig held the position then:
    an unplanned hold, which heals the contact (rig.session.pausing)."""
    out, t0 = [], None
    for ev in sorted((e for e in events or [] if e.get("kind") in ("pause", "resume")), key=lambda e: e["t_s"]):
        if ev["kind"] == "pause" and t0 is None:
            t0 = float(ev["t_s"])
        elif ev["kind"] == "resume" and t0 is not None:
            out.append((t0, float(ev["t_s"])))
            t0 = None
    if t0 is not None:
        out.append((t0, math.inf))
    return out


def clip_steps_to_pauses(steps: list["Step"], t_s: np.ndarray, intervals) -> list["Step"]:
    """Leave the paused samples out of the steps' segments: a segment that reaches into a pause ends
    where it began (before the step) or starts where it ended (after); a step inside a pause is dropped."""
    if not intervals:
        return steps
    t = np.asarray(t_s, dtype=float)
    out = []
    for s in steps:
        if any(a <= s.t_s <= b for a, b in intervals):
            continue
        lo, hi = s.pre[0], s.post[1]
        for a, b in intervals:
            ia, ib = int(np.searchsorted(t, a)), int(np.searchsorted(t, b, side="right"))
            if ib <= s.i and ib > lo:  # a pause before the step, within its segment
                lo = ib
            if ia >= s.i and ia < hi:  # after it
                hi = ia
        s.pre, s.post = (lo, s.pre[1]), (s.post[0], hi)
        out.append(s)
    return out


def detect_steps(trial, *, use_events: bool = True, min_ratio: float = 1.25, slip_window_um: float = 8.0,
                 min_points: int = 8, max_window_s: float = 30.0, guard_s: float = 0.6,
                 fit_span_s: float = 300.0) -> list[Step]:
    """Velocity steps of ``trial`` (a :class:`rig.data.TrialData`), sorted in time."""
    t = np.asarray(trial.time_s, dtype=float)
    x = np.asarray(trial.position_um, dtype=float)
    source = "data"
    times: list[float] = []
    info = None
    if use_events and trial.events:
        ev = _steps_from_events(trial, min_ratio)
        keep = [(tk, e) for tk, e in ev if t[0] < tk < t[-1]]
        times = [tk for tk, _ in keep]
        info = [e for _, e in keep]
        if times:
            source = "events"
    strength = [1.0] * len(times)
    if not times:
        times, strength = _detect_times(t, x, min_ratio=min_ratio, slip_window_um=slip_window_um,
                                        min_points=min_points, max_window_s=max_window_s)
    # refine (on a block-averaged copy of a dense record; indices mapped back after);
    # candidates rejected there (starts from rest, stops) must not limit their
    # neighbours' segments, so refine again with the kept ones until nothing changes
    tf = t
    tb, xb, _ = _thin(t, x)
    steps = []
    for _ in range(len(times) + 1):
        steps = _refine(tb, xb, times, source=source, guard_s=guard_s, fit_span_s=fit_span_s,
                        min_ratio=min_ratio, info=info)
        kept = {s.t_nominal_s for s in steps}
        rejected = [j for j, tk in enumerate(times) if tk not in kept]
        if not rejected:
            break
        if source == "events":
            drop = set(rejected)  # events are genuine; these are starts from rest and the like
        else:
            # a spurious candidate can make its genuine neighbour fail too (a candidate's segment
            # ends at its neighbours): of adjacent rejected candidates keep only those stronger
            # than their rejected neighbours, drop the rest, and refine again (a pair loses its
            # weaker one; a long run of rejected candidates -- a sawtooth's ~700 reversals -- most
            # of its members at once: a few rounds, not one per candidate and O(K^2) segment fits)
            rej = set(rejected)
            drop = set()
            for j in rejected:
                nb = [q for q in (j - 1, j + 1) if q in rej]
                if not nb or any(strength[q] >= strength[j] for q in nb):
                    drop.add(j)
            if len(drop) == len(rej) and len(rej) > 1 and all(
                    any(q in rej for q in (j - 1, j + 1)) for j in rej):
                drop.discard(max(rejected, key=lambda j: strength[j]))  # ties: keep the strongest
        sel = [j for j in range(len(times)) if j not in drop]
        times = [times[j] for j in sel]
        strength = [strength[j] for j in sel]
        info = [info[j] for j in sel] if info else None
    if tb is not tf:
        def full(j):
            return int(np.searchsorted(tf, tb[j] - 0.5 * (tb[1] - tb[0]))) if j < tb.size else tf.size
        for s in steps:
            s.i = int(np.searchsorted(tf, s.t_s))
            s.pre = (full(s.pre[0]), s.i)
            s.post = (s.i, full(s.post[1]))
    return clip_steps_to_pauses(steps, tf, pause_intervals(getattr(trial, "events", None)))


def _detect_times(t, x, *, min_ratio, slip_window_um, min_points, max_window_s) -> list[float]:
    if t.size < 4 * min_points:
        return [], []
    tb, xb, _ = _thin(t, x)
    dtm = float(np.median(np.diff(tb)))
    # pass 1: side slopes over a fixed number of samples give the speed on each side
    nfix = np.full(tb.size, 2.0 * min_points * dtm)
    vl0, vr0 = _side_slopes(tb, xb, nfix, nfix, 2 * min_points)
    vl0 = np.where(np.isfinite(vl0), vl0, vr0)
    vr0 = np.where(np.isfinite(vr0), vr0, vl0)
    # pass 2: each side's window holds about slip_window_um of slip at that side's speed
    half_l = np.clip(slip_window_um / np.maximum(np.abs(vl0), 1e-3), min_points * dtm, max_window_s)
    half_r = np.clip(slip_window_um / np.maximum(np.abs(vr0), 1e-3), min_points * dtm, max_window_s)
    for _ in range(2):
        vl, vr = _side_slopes(tb, xb, half_l, half_r, min_points)
        vl = np.where(np.isfinite(vl), vl, vl0)
        vr = np.where(np.isfinite(vr), vr, vr0)
        half_l = np.clip(slip_window_um / np.maximum(np.abs(vl), 1e-3), min_points * dtm, max_window_s)
        half_r = np.clip(slip_window_um / np.maximum(np.abs(vr), 1e-3), min_points * dtm, max_window_s)
    vl, vr = _side_slopes(tb, xb, half_l, half_r, min_points)
    v = 0.5 * (vl0 + vr0)
    floor = max(0.02 * float(np.nanmedian(np.abs(v))), 1e-3)
    ok = np.isfinite(vl) & np.isfinite(vr) & (vl > floor) & (vr > floor)
    r = np.zeros(tb.size)
    r[ok] = np.log(vr[ok] / vl[ok])
    thr = math.log(min_ratio)
    cand = np.flatnonzero(np.abs(r) > thr)
    if cand.size == 0:
        return [], []
    # group contiguous runs of candidates (same sign), take the peak of each
    order = cand
    groups = np.split(order, np.flatnonzero((np.diff(order) > 1) | (np.diff(np.sign(r[order])) != 0)) + 1)
    peaks = []
    for g in groups:
        j = g[np.argmax(np.abs(r[g]))]
        peaks.append(j)
    # non-maximum suppression within the smaller of the two windows
    # (chosen peaks kept sorted in time: only those within the largest window can suppress, so each
    # test looks at a few neighbours, not at every chosen peak -- a sawtooth has thousands of peaks)
    peaks.sort(key=lambda j: -abs(r[j]))
    radius = np.maximum(half_l, half_r)
    r_max = float(radius.max()) if radius.size else 0.0
    chosen: list[int] = []
    ct: list[float] = []
    for j in peaks:
        tj = float(tb[j])
        lo = bisect.bisect_left(ct, tj - r_max)
        hi = bisect.bisect_right(ct, tj + r_max)
        if all(abs(tj - tb[c]) > radius[c] for c in chosen[lo:hi]):
            k = bisect.bisect_left(ct, tj)
            ct.insert(k, tj)
            chosen.insert(k, j)
    return [float(tb[j]) for j in chosen], [float(abs(r[j])) for j in chosen]


def _robust_sd(r: np.ndarray) -> float:
    if r.size < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _first_run(bad: np.ndarray, run: int) -> int:
    """Index of the first run of ``run`` consecutive True values (``bad.size`` if none)."""
    if bad.size < run:
        return bad.size
    c = np.convolve(bad.astype(np.int64), np.ones(run, dtype=np.int64), mode="valid")
    hit = np.flatnonzero(c == run)
    return int(hit[0]) if hit.size else bad.size


def _grow(t, x, lo, hi, lim_lo, lim_hi, backward: bool, tol_um: float, run: int = 5):
    """Extend the fit range [lo, hi) backward (or forward) up to the limit while the
    position stays on the fitted straight line (a stop, a rest or another velocity ends
    the segment: ``run`` consecutive samples off the line by more than the noise and the
    line's own extrapolation uncertainty). Returns (lo, hi, a, b)."""
    for _ in range(60):
        tt = t[lo:hi]
        a, b = line_fit(tt, x[lo:hi])
        sd = max(_robust_sd(x[lo:hi] - (a + b * tt)), 1e-3)
        tc = float(tt.mean())
        sb = sd * math.sqrt(12.0 / max(tt.size, 2)) / max(float(tt[-1] - tt[0]), 1e-9)
        n = hi - lo
        if backward:
            if lo <= lim_lo:
                break
            c_lo = max(lim_lo, lo - max(n // 2, run))
            seg_t = t[c_lo:lo][::-1]
            dev = np.abs(x[c_lo:lo][::-1] - (a + b * seg_t))
            tol = max(tol_um, 5.0 * sd) + 4.0 * sb * np.abs(seg_t - tc)
            j = _first_run(dev > tol, run)
            if j == 0:
                break
            lo = lo - j
            if j < seg_t.size:
                break
        else:
            if hi >= lim_hi:
                break
            c_hi = min(lim_hi, hi + max(n // 2, run))
            seg_t = t[hi:c_hi]
            dev = np.abs(x[hi:c_hi] - (a + b * seg_t))
            tol = max(tol_um, 5.0 * sd) + 4.0 * sb * np.abs(seg_t - tc)
            j = _first_run(dev > tol, run)
            new_hi = hi + j
            if new_hi <= hi:
                break
            hi = new_hi
            if j < seg_t.size:
                break
    a, b = line_fit(t[lo:hi], x[lo:hi])
    return lo, hi, a, b


def _best_split(t: np.ndarray, x: np.ndarray, min_pts: int = 5) -> int:
    """Index j that best splits (t, x) into two straight lines (least total squared error);
    all splits at once from cumulative sums."""
    n = t.size
    if n < 2 * min_pts + 1:
        return n // 2
    tt = t - t.mean()
    xx = x - x.mean()

    def sse_prefix(tv, xv):
        c1 = np.arange(1, tv.size + 1, dtype=float)
        st, sx = np.cumsum(tv), np.cumsum(xv)
        stt, sxx, stx = np.cumsum(tv * tv), np.cumsum(xv * xv), np.cumsum(tv * xv)
        vt = stt - st * st / c1
        vx = sxx - sx * sx / c1
        cx = stx - st * sx / c1
        with np.errstate(divide="ignore", invalid="ignore"):
            s = vx - np.where(vt > 0, cx * cx / vt, 0.0)
        return s

    left = sse_prefix(tt, xx)            # left[j-1]: SSE of [0, j)
    right = sse_prefix(tt[::-1], xx[::-1])[::-1]  # right[j]: SSE of [j, n)
    j = np.arange(min_pts, n - min_pts)
    tot = left[j - 1] + right[j]
    return int(j[np.argmin(tot)])


def _refine(t, x, times, *, source, guard_s, fit_span_s, min_ratio, info=None, min_slip_um=10.0) -> list[Step]:
    """Effective step times and the constant-velocity segment around each step."""
    steps: list[Step] = []
    order = np.argsort(times)
    times = [times[j] for j in order]
    info = [info[j] for j in order] if info else [None] * len(times)
    bounds = [t[0] - 1.0] + list(times) + [t[-1] + 1.0]
    dtm = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    for k, tk in enumerate(times):
        ev = info[k] or {}
        t_prev, t_next = bounds[k], bounds[k + 2]
        if source == "data":
            # re-centre a detected step on the best two-line split nearby (detection windows
            # of unequal length can place the peak of ln(v_r/v_l) off the step)
            w = min(30.0, 0.5 * (tk - t_prev), 0.5 * (t_next - tk))
            j0, j1 = int(np.searchsorted(t, tk - w)), int(np.searchsorted(t, tk + w))
            if j1 - j0 > 12:
                tk = float(t[j0 + _best_split(t[j0:j1], x[j0:j1])])
        lim_lo = int(np.searchsorted(t, t_prev + guard_s))
        lim_hi = int(np.searchsorted(t, t_next - guard_s))
        t_post0 = max(tk, float(ev.get("ramp_end_s", tk))) + guard_s
        if "t_end_s" in ev:
            lim_hi = min(lim_hi, int(np.searchsorted(t, float(ev["t_end_s"]))))
        if "slip_before_um" in ev and ev.get("v1_um_s"):
            lim_lo = max(lim_lo, int(np.searchsorted(t, tk - float(ev["slip_before_um"]) / float(ev["v1_um_s"]))))
        pre_hi = int(np.searchsorted(t, tk - guard_s))
        post_lo = int(np.searchsorted(t, t_post0))
        n0 = max(12, int(2.0 / dtm) if dtm > 0 else 12)
        a_lo = max(lim_lo, pre_hi - n0)
        b_hi = min(lim_hi, post_lo + n0)
        if pre_hi - a_lo < 4 or b_hi - post_lo < 4:
            continue
        a_lo, pre_hi, a1, v1 = _grow(t, x, a_lo, pre_hi, max(lim_lo, pre_hi - int(fit_span_s / dtm)), lim_hi,
                                     True, 0.5)
        post_lo, b_hi, a2, v2 = _grow(t, x, post_lo, b_hi, lim_lo, lim_hi, False, 0.5)
        if not (np.isfinite(v1) and np.isfinite(v2)) or v1 <= 0 or v2 <= 0:
            continue
        if abs(math.log(v2 / v1)) < math.log(min_ratio) * 0.8:
            continue
        # both sides must be steady sliding over some slip (a start from rest, a stop or a
        # reversal is not a velocity step)
        if (x[pre_hi - 1] - x[a_lo]) < min_slip_um or (x[b_hi - 1] - x[post_lo]) < min_slip_um \
                or pre_hi - a_lo < 10 or b_hi - post_lo < 10:
            continue
        ts = (a2 - a1) / (v1 - v2)
        if not (t[pre_hi - 1] - guard_s <= ts <= t[post_lo] + guard_s):
            ts = tk
        xs = a1 + v1 * ts
        i = int(np.searchsorted(t, ts))
        # the whole constant-velocity stretch after the step (the fit above may stop early)
        _, seg_hi, _, _ = _grow(t, x, post_lo, b_hi, lim_lo, lim_hi, False, 0.5)
        steps.append(Step(t_s=float(ts), t_nominal_s=float(times[k]), i=i, v1_um_s=float(v1), v2_um_s=float(v2),
                          x_um=float(xs), pre=(a_lo, i), post=(i, max(seg_hi, i + 1)), source=source))
    return steps
