"""Kinematics and a decimated fitting grid from a measured record (diagnosis.md, "Notation").

The interface slips with the LVDT (``delta = x``) unless an extension says
otherwise, so velocity and slip come from the measured position. The LVDT is
quantized (0.076 µm) and noisy (±0.25 µm) and the record may be unevenly
sampled with gaps, so:

1. raw samples are pooled onto a *kinematic grid* of at least 10 ms (sums of
   friction, friction², normals and position kept, so no information on the
   friction side is thrown away: the within-cell scatter is pure noise for the
   model, see :class:`Grid`);
2. position is smoothed by an *edge-preserving local line*: for every grid
   point a straight line is fitted to the position over a window ending at,
   starting at and centred on the point, and the fit with the smallest
   residual is kept. A velocity step therefore stays a step (the window never
   straddles the kink when a clean side exists) while steady sliding averages
   the quantization out. The window spans about ``slip_window_um`` of slip
   (3 µm: ±0.03 µm/s at 1 µm/s and 25 Hz), clipped to [0.2, 4] s;
3. where ``position_ref_um`` is logged, the commanded position carries the
   sharp shape of the trajectory and only the small tracking error
   ``x - x_ref`` is smoothed, which keeps the velocity steps sharp;
4. the grid is then merged into adaptive *fit bins*: long bins (up to 1 s or
   1 µm of slip) while the velocity is steady, short bins growing
   geometrically after every velocity change, never across a hold-out block
   boundary. Fits run on the bins (weighted by sample count); the sum of
   squares of the raw samples is recovered exactly as bin residual + within-bin
   scatter, so hold-out RMS and BIC refer to the raw samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.ndimage import minimum_filter1d, uniform_filter1d

from rig.data import TrialData
from rig.kinematics import edge_preserving_line
from rig.model.forward import slip_increments_um

KIN_DT_MIN_S = 0.01
V_SLIDE_MIN_UM_S = 0.1
STOP_GUARD_S = 3.0
RISE_GUARD_S = 0.0
RISE_DLNV = 0.1  # (0: off)
# rest (the reported rigid models only: rig.diagnosis.core.reported_grid): the measured position's mean
# over the REST_WINDOW_S after a cell differs from that over the REST_WINDOW_S before it by less than
# REST_SIGMAS of its own noise (see _at_rest)
REST_WINDOW_S = 1.0
REST_SIGMAS = 4.0
REST_SPREAD = 0.5  # (of REST_WINDOW_S)


@njit(cache=True)
def _make_bins(t, v, block, dt_max, slip_res, rel_v, growth, dt_min_first):
    """Adaptive fit bins over the kinematic grid (see module doc). Returns bin start indices."""
    n = t.shape[0]
    starts = np.empty(n + 1, dtype=np.int64)
    nb = 0
    starts[0] = 0
    nb = 1
    j0 = 0
    prev_len = dt_min_first
    for j in range(1, n):
        dur = t[j] - t[j0]
        vs = abs(v[j0])
        lim = dt_max
        if vs > 1e-9:
            lim = min(lim, slip_res / vs)
        lim = min(lim, growth * prev_len)
        vel_change = abs(v[j] - v[j0]) > rel_v * max(abs(v[j0]), 0.05) + 0.03
        if block[j] != block[j0] or dur > lim or vel_change:
            starts[nb] = j
            nb += 1
            if vel_change:
                prev_len = dt_min_first
            else:
                prev_len = max(t[j] - t[j0], dt_min_first)
            j0 = j
    starts[nb] = n
    return starts[: nb + 1]


@dataclass
class Grid:
    """Binned record on which models are fitted (all arrays per bin).

    ``F_mean`` mean measured friction (N), ``count`` the bin's raw samples
    weighted by the time each stands for (:func:`time_weights`: 1 per sample
    at the record's usual rate, 10 per sample where it logs ten times
    slower), ``ss_within`` the raw samples' weighted sum of squares about the
    bin mean (N²), so that the raw-sample SSE of a model constant over the
    bin is ``count * (F_mean - pred)² + ss_within``: every statistic weighs
    the record by time, not by row count (diagnosis.md, "The answer depends on
    the physics only").
    """

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    F_mean: np.ndarray
    N_tot: np.ndarray
    count: np.ndarray
    ss_within: np.ndarray
    block: np.ndarray
    N_nom: float
    t0: float
    has_normals: bool
    normals_vary: bool
    noise_N: float
    # kinematic grid (finer), for plots and screening
    kin: dict = field(default_factory=dict)
    slide_ok: np.ndarray | None = None
    # shortest time constant the kinematics can tell from their own rounding of a velocity change (s)
    time_resolution_s: float = 0.0
    # variance of the mean of the raw force noise over one kinematic cell (KIN_DT_MIN_S, m samples)
    # over that of white noise, 1 + 2 sum_{k<m} (1 - k/m) rho_k, clipped to [1, m]: raw samples per
    # independent one (the analog filter's memory at 1 kHz; 1 when a cell holds one sample, <= 100 Hz);
    # see _noise_correlation
    noise_corr: float = 1.0
    # the 20 equal time blocks (the linear-drift check), and how fit / hold-out were split
    time_block: np.ndarray | None = None
    holdout_design: str = "time blocks"
    # the velocity steps identify finds (rig.kinematics.detect_steps), grid time (s); None: not given
    step_times_s: np.ndarray | None = None
    # parameters the file states (measured-data.md: machine_stiffness_kN_per_m), held fixed in every fit
    known: dict = field(default_factory=dict)
    # the lowest stiffness the record's own force-displacement slope allows (kN/m; 0: no bound), the lower
    # fit bound of stiffness_kN_per_m (rig.diagnosis.causes.stiffness_floor_kN_per_m)
    stiffness_floor_kN_per_m: float = 0.0
    # every model on this grid multiplies mu by the measured N1 + N2 (the reported refits: friction
    # follows the normal force on every rig; rig.diagnosis.core.reported_grid), not 2 N_nom
    normals_in_model: bool = False

    @property
    def n_raw(self) -> int:
        return int(self.count.sum())

    @property
    def sliding(self) -> np.ndarray:
        """Bins in forward sliding (v > V_SLIDE_MIN for ±STOP_GUARD_S): the only ones the models are held to.

        At rest friction is statically indeterminate (whatever the loading holds), and the
        catalogue's models are for unidirectional sliding (the paper's regime); stops, returns
        and the starts from rest are still integrated through, but not fitted.
        """
        return self.slide_ok

    @property
    def w(self) -> np.ndarray:
        """Raw-sample count of the sliding bins (0 elsewhere): the weights of every statistic."""
        return self.count * self.sliding

    @property
    def max_state_um(self) -> float:
        """Longest slip-law state distance the record can tell from a drift: half its slip (µm).
        A state whose transient outlasts the record is a linear trend in slip: a drift, not a
        memory (docs/diagnosis.md, "Rules learned from records")."""
        return 0.5 * float(np.sum(slip_increments_um(self.t, self.v)))

    def holdout_mask(self) -> np.ndarray:
        return ((self.block % 2) == 1) & self.sliding

    def fit_mask(self) -> np.ndarray:
        return ((self.block % 2) == 0) & self.sliding


def _robust_noise(y: np.ndarray) -> float:
    """White-noise level from successive differences (robust MAD), N."""
    d = np.diff(np.asarray(y, dtype=float))
    if d.size < 4:
        return float(np.std(y)) if y.size else 0.0
    mad = np.median(np.abs(d - np.median(d)))
    return float(mad / 0.6745 / math.sqrt(2.0))


def _servo_fit(t, xr, x):
    """The load point's response to the commanded position as a critically damped 2nd-order lag.

    Returns (tau_s, modelled position) or (None, None) when the measured position does not follow the
    reference that way (rms misfit over 3x the LVDT noise, or a trend between them).
    """
    from rig.model.sensors import lowpass_uneven

    # the record starts in motion: pad the past with the initial commanded velocity, so the lag
    # model starts in its steady tracking state rather than at rest
    k = int(np.searchsorted(t, t[0] + 2.0)) + 2
    v0 = float(np.polyfit(t[:k] - t[0], xr[:k], 1)[0]) if k >= 3 else 0.0
    dtp = max(float(np.median(np.diff(t))), 1e-3)
    tp = t[0] - dtp * np.arange(400, 0, -1)
    tt = np.concatenate([tp, t])
    xx = np.concatenate([xr[0] + v0 * (tp - t[0]), xr])

    def model(tau):
        if tau <= 0:
            m = xr.copy()
        else:
            m = lowpass_uneven(tt, lowpass_uneven(tt, xx, tau), tau)[400:]
        off = float(np.median(x - m))
        return m + off

    taus = [0.0] + list(np.exp(np.linspace(np.log(0.002), np.log(1.0), 24)))
    sse = []
    for tau in taus:
        m = model(tau)
        sse.append(float(np.mean((x - m) ** 2)))
    k = int(np.argmin(sse))
    tau = taus[k]
    m = model(tau)
    noise = _robust_noise(x)
    rms = math.sqrt(sse[k])
    if rms > 3.0 * max(noise, 0.05) + 0.1:
        return None, None
    return tau, m


TIME_WEIGHT_WINDOW = 11


def time_weights(t: np.ndarray) -> np.ndarray:
    """Per-sample weight proportional to the time a sample stands for: the running median (over
    TIME_WEIGHT_WINDOW intervals) of the local sampling interval over its median in the record.
    1 for every sample of a uniformly sampled record (jitter averages out, a gap is no interval any
    sample stands for); a record that logs at 10 Hz, then at 100 Hz weighs each slow sample 10: the
    fast part does not count ten times more for being logged ten times faster."""
    from scipy.ndimage import median_filter

    t = np.asarray(t, dtype=float)
    if t.size < 3:
        return np.ones(t.size)
    d = np.diff(t)
    d = np.concatenate([d[:1], 0.5 * (d[1:] + d[:-1]), d[-1:]])  # the interval around each sample
    loc = median_filter(d, size=min(TIME_WEIGHT_WINDOW, d.size), mode="nearest")
    ref = float(np.median(loc))
    if not ref > 0:
        return np.ones(t.size)
    u = loc / ref
    # uniform sampling with rounding in the last digits: exactly 1
    u[np.abs(u - 1.0) < 0.05] = 1.0
    return u


def canonical(trial: TrialData) -> TrialData:
    """The record with its clock and position starting at 0 (a copy when they do not already):
    what a file's clock and the position's zero happen to be is no physics."""
    t0 = float(trial.time_s[0])
    x0 = float(trial.position_um[0])
    if t0 == 0.0 and x0 == 0.0:
        return trial
    out = trial.select(np.ones(len(trial), bool))
    # rounded to 1e-9 s and 1e-9 um, far below any acquisition's resolution: 1000.1 - 1000 is
    # 0.10000000000002 in floating point, and a bin limit of exactly 1 s must not depend on it
    out.time_s = np.round(out.time_s - t0, 9)
    out.position_um = np.round(out.position_um - x0, 9)
    if out.position_ref_um is not None:
        out.position_ref_um = np.round(out.position_ref_um - x0, 9)
    return out


def _noise_correlation(t: np.ndarray, F: np.ndarray) -> float:
    """Variance of the mean of the raw force noise over a kinematic cell (KIN_DT_MIN_S) relative
    to white noise's, 1 + 2 sum_{k=1}^{m-1} (1 - k/m) rho_k over the m samples of a cell (m from the
    median sampling interval); rho_k the autocorrelation of the force minus its running mean over
    4 m + 1 samples. Clipped to [1, m]; 1 when a cell holds one sample (records at <= 100 Hz) or the
    record has under 200 samples."""
    if t.size < 200:
        return 1.0
    m = int(round(KIN_DT_MIN_S / max(float(np.median(np.diff(t))), 1e-9)))
    if m < 2:
        return 1.0
    r = F - uniform_filter1d(F, 4 * m + 1, mode="nearest")
    r = r - r.mean()
    v = float(np.dot(r, r))
    if v <= 0:
        return 1.0
    c = 1.0
    for k in range(1, m):
        c += 2.0 * (1.0 - k / m) * float(np.dot(r[k:], r[:-k])) / v
    return min(max(c, 1.0), float(m))


def _drop_reloading(slide_ok: np.ndarray, t: np.ndarray, x: np.ndarray, F: np.ndarray, count: np.ndarray,
                    noise_N: float, frac: float = 0.98, settle_s: float = STOP_GUARD_S,
                    settle_um: float = 0.0) -> np.ndarray:
    """Leave out the re-loading after every rest or return, until the interface breaks away.

    After a stop (or a return at the opposite sign) the friction is statically indeterminate
    until the loading system has stretched to the sliding friction: the LVDT moves by
    ``Delta F / k`` while the interface sticks (on the simulated rig about 3 µm and 5 s for a
    return at -18 N followed by sliding at +20 N through the 10 N/µm fixture). A model whose
    kinematics are the LVDT's (rigid) cannot describe that, and the few bins of it would
    dominate every fit (tens of N of residual against a 0.1 N noise). Each forward-sliding run
    that follows a non-sliding stretch is therefore fitted only from where its friction first
    reaches ``frac`` of the way from its value at the restart to the run's median (the
    breakaway) plus ``settle_s`` (the servo's ringing after the breakaway is not friction) and
    ``settle_um`` of slip (the state after a rest is unknown: the slip law does not age at rest,
    a real contact does; diagnose passes 3 L of identify's whole-record fit); a run
    whose friction does not rise by more than 5 noise sigma keeps all its bins.
    """
    ok = slide_ok.copy()
    n = ok.size
    i = 0
    while i < n:
        if not ok[i]:
            i += 1
            continue
        j = i
        while j < n and ok[j]:
            j += 1
        seg = F[i:j]
        w = count[i:j]
        order = np.argsort(seg)
        cw = np.cumsum(w[order])
        med = float(seg[order][np.searchsorted(cw, 0.5 * cw[-1])])
        f0 = float(seg[0])
        rise = med - f0
        # a run from the record's first bin re-loads too when its friction starts under half the
        # sliding friction: a start from rest that the velocity estimate smeared into sliding (a
        # transient of friction is a few per cent of it, never half)
        if (i > 0 or abs(f0) < 0.5 * abs(med)) and abs(rise) > 5.0 * max(noise_N, 1e-9):
            thr = f0 + frac * rise
            reached = np.flatnonzero((seg - thr) * np.sign(rise) >= 0)
            k = int(reached[0]) if reached.size else j - i
            if k < j - i:
                kt = int(np.searchsorted(t[i:j], t[i + k] + settle_s))
                kx = int(np.argmax(np.append(x[i + k:j] - x[i + k] >= settle_um, True))) + k
                k = max(kt, kx)
            ok[i:i + k] = False
        i = j
    return ok


MIN_STEPS_ALIGNED = 4
# records with MIN_STEPS_ALIGNED or more steps: leave-every-other-step-out. A transient cause must
# then also gain on the swapped split (core.try_candidate: a jump of friction inside one segment
# gave a 93 kN/m "spring" without that check), and unexplained structure is ranked on the time
# blocks (core.find_unexplained)
ALIGN_TO_STEPS = True
# the least share of the sliding samples each half (fit, hold-out) of a step-aligned split must hold
ALIGNED_MIN_SHARE = 0.25
# records with fewer steps: equal time blocks phased so that the (first) step's transient is fitted
PHASE_TO_STEP = True
SUBWINDOWS = 0  # 200 tried: see _holdout_blocks
SUBWINDOW_MIN_S = 0.5


def _holdout_blocks(tk: np.ndarray, vs: np.ndarray, time_blk: np.ndarray, T: float, n_blocks: int,
                    step_times: np.ndarray | None = None, aligned: bool = True):
    """Fit / hold-out blocks that respect a velocity step (docs/diagnosis.md, "Hold-out design").

    Each velocity transient is fitted or held out whole: with at least MIN_STEPS_ALIGNED changes
    between two forward sliding speeds, a block runs from one such change to the next
    (alternately fit and hold-out: leave-every-other-step-out). With fewer (one- or two-step
    records) equal time blocks would put the peak in one block and the decay in the other;
    instead SUBWINDOWS short windows (at least SUBWINDOW_MIN_S) alternate, so that fit and
    hold-out both sample every part of the one transient (cross-validation over sub-windows).
    Returns (block per kinematic cell, a description)."""
    from rig.kinematics import velocity_changes

    # the steps identify finds (rig.kinematics.detect_steps, passed by diagnose) when given: the
    # ln-v detector below also fires on the stick-slip and bursty sampling of real records
    tc = velocity_changes(tk, vs) if step_times is None else np.asarray(step_times, dtype=float)
    fwd = []
    for t_c in tc:
        v_b = float(np.interp(t_c - 1.5, tk, vs))
        v_a = float(np.interp(t_c + 1.5, tk, vs))
        if v_b > V_SLIDE_MIN_UM_S and v_a > V_SLIDE_MIN_UM_S:
            fwd.append(t_c)
    if aligned and ALIGN_TO_STEPS and len(fwd) >= MIN_STEPS_ALIGNED:
        # the boundary just before the change (the window of velocity_changes is +-1 s)
        bnd = np.asarray(fwd) - 1.0
        return np.searchsorted(bnd, tk).astype(np.int64), f"blocks aligned to {len(fwd)} velocity steps"
    if PHASE_TO_STEP and 0 < len(fwd) and (len(fwd) < MIN_STEPS_ALIGNED or not aligned):
        # one to three steps: the equal time blocks, phased so that the first step's transient
        # starts (1 s before the step) at the start of a fit block; unphased, a crop that moves the
        # boundaries decides whether the single step's peak is fitted or held out (held out whole, the
        # rigid fit never sees the direct effect: docs/diagnosis.md, "Rules learned from records")
        Tb = T / n_blocks
        # the fit block starts at most a quarter block before the step (1 s, the change detector's
        # window, only where blocks are long): a fixed 1 s lead on blocks shorter than it put the
        # step of a 4.5 s record in a hold-out block once a trim changed the block length
        lead = min(1.0, 0.25 * Tb)
        phase = (fwd[0] - lead - tk[0]) % Tb
        blk = np.floor((tk - tk[0] - phase) / Tb).astype(np.int64) + 1
        j = int(np.floor((fwd[0] - lead - tk[0] - phase) / Tb + 1e-9)) + 1
        if j % 2:
            blk = blk + 1
        return blk, f"{n_blocks} time blocks phased to the step at {fwd[0]:.4g} s (fitted)"
    if SUBWINDOWS <= 0:
        # sub-window cross-validation is off (SUBWINDOWS = 0; docs/diagnosis.md, "Rules learned from
        # records"); equal time blocks for now
        return time_blk, f"{n_blocks} time blocks ({len(fwd)} velocity step(s): too few to hold out whole)"
    n_sub = int(max(2 * n_blocks, min(SUBWINDOWS, T / SUBWINDOW_MIN_S)))
    blk = np.minimum((tk - tk[0]) / (T / n_sub), n_sub - 1).astype(np.int64)
    return blk, f"{n_sub} alternating sub-windows ({len(fwd)} velocity step(s): too few to hold out whole)"


def prepare(trial: TrialData, n_blocks: int = 20, slip_window_um: float = 3.0,
            bin_dt_max_s: float = 1.0, bin_slip_um: float = 1.0, restart_guard_um: float = 0.0,
            step_times_s: np.ndarray | None = None, align_to_steps: bool = True, rest: bool = False) -> Grid:
    """Kinematic grid + adaptive fit bins + hold-out blocks from a trial (see module doc). ``rest``: the
    velocity is zero where the measured position rests (:func:`_at_rest`; the reported rigid models'
    grid only, rig.diagnosis.core.reported_grid: the decisions are made on the line fit's velocity)."""
    t_raw = np.asarray(trial.time_s, dtype=float)
    if t_raw.size < 20:
        raise ValueError(f"{trial.source or 'trial'}: too few samples ({t_raw.size}) to diagnose")
    t0 = float(t_raw[0])
    tr = t_raw - t0
    F = np.asarray(trial.friction_N, dtype=float)
    x_raw = np.asarray(trial.position_um, dtype=float)
    noise_N = _robust_noise(F)
    noise_corr = _noise_correlation(tr, F)
    if x_raw[-1] < x_raw[0] and float(np.median(F)) < 0:
        # sliding backwards throughout: the model is odd in v, so mirror the record
        x_raw, F = -x_raw, -F
        if trial.position_ref_um is not None:
            trial = trial.select(np.ones(len(trial), bool))
            trial.position_ref_um = -trial.position_ref_um
    k = _cells(trial, tr, F, x_raw)  # 1. kinematic grid cells
    xs, vs, time_res = _kinematics(k, slip_window_um, rest)  # 2./3. kinematics
    tk = k["t"]
    steps_k = None if step_times_s is None else np.asarray(step_times_s) - t0
    for aligned in ((True, False) if align_to_steps else (False,)):  # 4. blocks and bins
        T = float(tk[-1] - tk[0]) if tk.size > 1 else 1.0
        time_blk_k = np.minimum((tk - tk[0]) / (T / n_blocks), n_blocks - 1).astype(np.int64)
        blk_k, holdout_design = _holdout_blocks(tk, vs, time_blk_k, T, n_blocks, steps_k, aligned=aligned)
        b = _bins(k, xs, vs, blk_k, time_blk_k, bin_dt_max_s, bin_slip_um)
        slide_ok = _sliding(k, vs, b, noise_N, restart_guard_um)
        n_hold = int(np.count_nonzero(slide_ok & (b["block"] % 2 == 1)))
        if not holdout_design.startswith("blocks aligned") or (
                min(n_hold, int(slide_ok.sum()) - n_hold) >= ALIGNED_MIN_SHARE * max(int(slide_ok.sum()), 1)):
            break
        # the steps leave one half (fit or hold-out) with too little of the sliding that is used
        # (steps that bunch up, segments dropped as reloading): the design for fewer steps instead
    normals_vary = bool(trial.has_normals and float(np.std(k["N"])) > 0.0)
    return Grid(t=b["t"], x=b["x"], v=b["v"], F_mean=b["F"], N_tot=b["N"], count=b["count"], ss_within=b["ssw"],
                block=b["block"], N_nom=float(trial.normal_force_N), t0=t0, has_normals=trial.has_normals,
                normals_vary=normals_vary, noise_N=noise_N, noise_corr=noise_corr, slide_ok=slide_ok,
                time_resolution_s=time_res, time_block=b["time_block"], holdout_design=holdout_design,
                step_times_s=None if step_times_s is None else np.asarray(step_times_s, dtype=float) - t0,
                kin={"t": tk, "x": xs, "v": vs, "F": k["Fs"] / k["count"], "N": k["N"], "count": k["count"],
                     "x_meas": k["x"]})


def _cells(trial: TrialData, tr: np.ndarray, F: np.ndarray, x_raw: np.ndarray) -> dict:
    """The kinematic grid: cells of at least KIN_DT_MIN_S, each sample weighted by the time it
    stands for (:func:`time_weights`): cell time, measured position, friction sums, normal force
    (and the reference position's mean, ``xr``, when the record has one)."""
    dt_med = float(np.median(np.diff(tr)))
    cell = max(KIN_DT_MIN_S, dt_med * 0.999)
    if dt_med >= KIN_DT_MIN_S:
        idx = np.arange(tr.size)
    else:
        idx = np.floor(tr / cell).astype(np.int64)
        _, idx = np.unique(idx, return_inverse=True)
    ncell = int(idx.max()) + 1
    u = time_weights(tr)
    cnt = np.bincount(idx, weights=u, minlength=ncell)

    def cmean(y):
        return np.bincount(idx, weights=y * u, minlength=ncell) / cnt

    tk = cmean(tr)
    Nk = cmean(np.asarray(trial.total_normal_N, dtype=float))
    if trial.has_normals and tk.size > 5:
        # the normal load cells' noise (±0.6 N) would otherwise enter mu (N1 + N2): centred 0.5 s mean
        kk = max(1, int(round(0.25 / max(float(np.median(np.diff(tk))), 1e-6))))
        ker = np.ones(2 * kk + 1)
        Nk = np.convolve(Nk, ker, mode="same") / np.convolve(np.ones_like(Nk), ker, mode="same")
    use_ref = trial.position_ref_um is not None and np.all(np.isfinite(trial.position_ref_um))
    return {"t": tk, "x": cmean(x_raw), "count": cnt, "Fs": np.bincount(idx, weights=F * u, minlength=ncell),
            "F2s": np.bincount(idx, weights=F * F * u, minlength=ncell), "N": Nk,
            "xr": cmean(np.asarray(trial.position_ref_um, dtype=float)) if use_ref else None}


def _kinematics(k: dict, slip_window_um: float, rest: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, velocity, time resolution (s)) of the cells: from the reference and the servo's
    lag when the record has a reference, else an edge-preserving line fit over a window of
    ``slip_window_um`` of slip at the slower side of any nearby velocity change; with ``rest``, zero
    where the measured position rests (:func:`_at_rest`)."""
    tk, xk = k["t"], k["x"]
    v_rough = np.gradient(xk, tk) if tk.size > 2 else np.zeros_like(tk)
    # rough speed over ~2 s for the window length
    k2 = max(1, int(round(2.0 / max(np.median(np.diff(tk)), 1e-6))))
    if tk.size > 2 * k2 + 1:
        ker = np.ones(2 * k2 + 1) / (2 * k2 + 1)
        v_s = np.convolve(v_rough, ker, mode="same") / np.convolve(np.ones_like(v_rough), ker, mode="same")
    else:
        v_s = np.full_like(tk, (xk[-1] - xk[0]) / max(tk[-1] - tk[0], 1e-9))
    # size the window by the slower side of any nearby velocity change (running minimum over ±2 s)
    v_min = minimum_filter1d(np.abs(v_s), size=2 * k2 + 1, mode="nearest")
    half = 0.5 * np.clip(slip_window_um / np.maximum(v_min, 0.05), 0.2, 4.0)
    servo_tau = None
    use_ref = k["xr"] is not None
    if use_ref:
        servo_tau, xm = _servo_fit(tk, k["xr"], xk)
        if servo_tau is None:
            use_ref = False
    if use_ref:
        # the reference carries the trajectory's shape; the tracking residual is nearly constant
        es, ev = edge_preserving_line(tk, xk - xm, np.full_like(tk, 2.0))
        xs = xm + es
        vs = np.gradient(xm, tk) + ev
    else:
        xs, vs = edge_preserving_line(tk, xk, half)
    if rest:
        vs = np.where(_at_rest(tk, xk, vs), 0.0, vs)
    # without a reference, a line fit cannot resolve the actuator's rounded velocity change (the
    # paper's steps rise in up to 0.5 s): time constants below ~0.15 s are the estimator's own
    dtk0 = float(np.median(np.diff(tk))) if tk.size > 1 else KIN_DT_MIN_S
    time_res = max(3.0 * dtk0, 2.0 * servo_tau) if use_ref else max(3.0 * dtk0, 0.15)
    return xs, vs, time_res


def _at_rest(tk: np.ndarray, xk: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """The cells where the interface is at rest: the measured position's mean over the REST_WINDOW_S
    after the cell and over the REST_WINDOW_S before it differ by less than REST_SIGMAS standard
    errors of that difference (from the position's own white noise), and the cells of both windows
    of such a centre within REST_SPREAD of a window (a 2 s hold rests whole, not only its middle). A
    line fitted over a window that reaches into the motion on either side of a hold smears it into
    sliding (the simulated rig's main job: -4 to +3 um/s through a 2 s hold), and the state the model
    integrates through it is then not the interface's: the misfit after each restart tripled the
    reported errors (docs/validation.md, "Coverage"). A stick whose LVDT moves with the fixture's
    deflection (the re-loading at a restart or a return) is not seen. None is at rest when the
    record's forward sliding is slower than twice the threshold: its noise cannot tell rest from slip.
    Only for the reported rigid models (rig.diagnosis.core.reported_grid): on the decisions' grid it
    named false second states on the paper protocol."""
    rest = np.zeros(tk.size, dtype=bool)
    if tk.size < 10:
        return rest
    c = np.concatenate([[0.0], np.cumsum(xk)])
    lo = np.searchsorted(tk, tk - REST_WINDOW_S)
    hi = np.searchsorted(tk, tk + REST_WINDOW_S, side="right")
    i = np.arange(tk.size)
    n_b, n_a = i - lo + 1, hi - i
    # both windows at least half their length: near the record's ends the two means lie too close in
    # time for a slide to move them apart by the threshold
    span_b = tk - tk[lo]
    span_a = tk[np.maximum(hi - 1, i)] - tk
    ok = (n_b >= 3) & (n_a >= 3) & (span_b >= 0.5 * REST_WINDOW_S) & (span_a >= 0.5 * REST_WINDOW_S)
    before = (c[i + 1] - c[lo]) / np.maximum(n_b, 1)
    after = (c[hi] - c[i]) / np.maximum(n_a, 1)
    sigma = _robust_noise(xk) * np.sqrt(1.0 / np.maximum(n_b, 1) + 1.0 / np.maximum(n_a, 1))
    thr = REST_SIGMAS * sigma
    fwd = vs[vs > V_SLIDE_MIN_UM_S]
    # the threshold as a speed (the two means are REST_WINDOW_S apart in time, on average)
    if fwd.size == 0 or float(np.median(thr)) / REST_WINDOW_S > 0.5 * float(np.median(fwd)):
        return rest
    centre = ok & (np.abs(after - before) < thr)
    # a centre's two windows rest with it: the whole of a hold as long as them, not only its middle
    cc = np.concatenate([[0], np.cumsum(centre)])
    a = np.searchsorted(tk, tk - REST_SPREAD * REST_WINDOW_S)
    b = np.searchsorted(tk, tk + REST_SPREAD * REST_WINDOW_S, side="right")
    return (cc[b] - cc[a]) > 0


def _bins(k: dict, xs: np.ndarray, vs: np.ndarray, blk_k: np.ndarray, time_blk_k: np.ndarray,
          bin_dt_max_s: float, bin_slip_um: float) -> dict:
    """The adaptive fit bins over the cells (inside the blocks): their means weighted by the raw
    count, the friction's within-bin sum of squares, and the cells where each starts."""
    tk, cnt = k["t"], k["count"]
    dtk = float(np.median(np.diff(tk)))
    starts = _make_bins(tk, vs, blk_k, bin_dt_max_s, bin_slip_um, 0.08, 1.1, max(dtk, 0.02))
    seg = np.repeat(np.arange(starts.size - 1), np.diff(starts))
    nb = starts.size - 1
    bc = np.bincount(seg, weights=cnt, minlength=nb)

    def bmean_w(y):  # weighted by raw count
        return np.bincount(seg, weights=y * cnt, minlength=nb) / bc

    Fsum = np.bincount(seg, weights=k["Fs"], minlength=nb)
    F2sum = np.bincount(seg, weights=k["F2s"], minlength=nb)
    Fm = Fsum / bc
    return {"t": bmean_w(tk), "x": bmean_w(xs), "v": bmean_w(vs), "N": bmean_w(k["N"]), "F": Fm, "count": bc,
            "ssw": np.maximum(F2sum - Fsum * Fm, 0.0), "block": blk_k[starts[:-1]],
            "time_block": time_blk_k[starts[:-1]], "starts": starts, "dtk": dtk}


def _sliding(k: dict, vs: np.ndarray, b: dict, noise_N: float, restart_guard_um: float) -> np.ndarray:
    """The bins the fits use: forward sliding, away from stops, starts from rest and returns, and
    from the velocity changes' rise."""
    tk, starts, dtk = k["t"], b["starts"], b["dtk"]
    kg = max(1, int(round(STOP_GUARD_S / max(dtk, 1e-6))))
    vmin_k = minimum_filter1d(vs, size=2 * kg + 1, mode="nearest")
    slide_ok = np.minimum.reduceat(vmin_k, starts[:-1]) > V_SLIDE_MIN_UM_S
    if slide_ok.sum() < 0.1 * slide_ok.size:  # a record with hardly any steady sliding: keep what slides
        slide_ok = b["v"] > V_SLIDE_MIN_UM_S
    slide_ok = _drop_reloading(slide_ok, b["t"], b["x"], b["F"], b["count"], noise_N, settle_um=restart_guard_um)
    # the velocity changes themselves: within RISE_GUARD_S (or the kinematics' own resolution) of
    # a change of ln v the measured velocity is not the interface's to the precision the direct
    # effect needs (the peak is a few samples at 25 Hz, their timing set by the estimator, not by
    # friction); as in the paper's identification the transient is fitted from the end of the rise
    h = RISE_GUARD_S
    lv = np.log(np.maximum(np.abs(vs), 1e-2))
    dlv = np.abs(np.interp(tk + h, tk, lv) - np.interp(tk - h, tk, lv))
    rise_k = dlv > RISE_DLNV
    rise_b = np.maximum.reduceat(rise_k, starts[:-1]) if rise_k.any() else np.zeros(starts.size - 1, bool)
    if h > 0 and (slide_ok & ~rise_b).sum() > 0.5 * slide_ok.sum():
        slide_ok = slide_ok & ~rise_b
    return slide_ok
