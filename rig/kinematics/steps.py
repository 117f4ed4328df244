"""Velocity steps of a record: from the log's events when present, else from the data.

Detection from the data works on the position only, so it is robust to friction noise,
handles steps up and down, uneven sampling and gaps: a velocity with a window of about
``slip_window_um`` of slip at the local speed sets a left and a right window for every
sample; straight lines fitted in both give the velocities just before and after,
r = ln(v_right / v_left) peaks at a step; peaks with |r| > ln(min_ratio), largest within
their windows, are steps, each refined to the intersection of the straight lines before and
after it (the *effective step*). The operator's pauses (:func:`pause_intervals`) are left out
of the steps' segments. Velocity estimators: :mod:`rig.kinematics.velocity`.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

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
