"""Measured loop tuning (``rig tune``): step response, frequency response, model fit, gains.

**Step response** (:func:`step_response`; a ``square`` segment, 1 kHz samples): per edge of the
reference (jump ``delta`` of the square about the slide beneath it) the measured position's
response ``s(t) = (y(t) - y_before) / delta``, ``y`` the LVDT position less the slide, smoothed
over ``SMOOTH_S``: rise time 10 -> 90 %, overshoot (max s - 1), settling time (the last time
|s - 1| leaves the ``SETTLE_BAND``, from the edge's start), and the following error
(x_ref - x, rms and max over the segment).

**Frequency response** (:func:`frf`; a ``sine_sweep`` segment): the H1 estimate of the closed
loop from reference to measured position, T = P_ry / P_rr (cross- over auto-spectrum, Welch,
Hann windows of ``nperseg`` samples, half overlap; the output noise does not bias H1) with
the coherence gamma^2 = |P_ry|^2 / (P_rr P_yy); the slide beneath the sweep (a straight line
through the reference) is taken off both. On the hardware path a loop stall (a ``stall`` event:
the reference is held while the plant moves on) is a disturbance the reference did not cause:
the Welch segments it falls in are left out, and so are those within ``RECOVER_S`` after a
stale stretch of the position stream (the same reading for ``STALE_S`` on a slide: the
sensor's frames held up, e.g. an emulator process descheduled by the VM). The controller is known (rig.control: PID with the
integral of prior errors and a backward-difference D, FF1 and the friction feed-forward on the
reference's backward difference), so the plant follows from the measured closed loop,

    T = P (C + F) / (1 + P C)   ->   P = T / (C + F - T C),   open loop L = P C,

C(z) = kp + ki dt / (z - 1) + kd (1 - 1/z) / dt, F(z) = (ff1 + Z_f(jw)) (1 - 1/z) / dt with
Z_f the linearised friction impedance of the feed-forward's law at the slide velocity V
(eqs. 5-6: Z_f(s) = A/V - (B/L) / (s + V/L), force units 2 N). Gain margin: 1/|L| where the
phase of L crosses -180 deg; phase margin: 180 deg + phase of L where |L| = 1; -3 dB bandwidth:
the first frequency where |T| falls 3 dB below its low-frequency level. Measured and model
are compared up to 50 Hz on 1/6-octave bands (the mean of the coherent bins' ratio H / T_model
in each band), since one bin's own random error, sqrt(1 - g^2) / (g sqrt(2 n_d)) (Bendat &
Piersol), is already 0.5-1 dB at g^2 = 0.8 with 25-40 averages.

**The loop model** (:func:`model_closed_loop`): the same T from ``rig stability``'s linearised
loop (:class:`rig.analysis.stability.LoopModel`, plant ``rig``: spool, actuator with oil
compliance and leakage, moving mass, test piece and fixture, the interface linearised about
steady sliding at V, the LVDT filter; discretised under a zero-order hold at the loop rate),
so the measured and the modelled response of the same profile can be drawn together.

**Autotune** (:func:`fit_plant`, :func:`propose_gains`): the actuator's velocity-force slope
k_h tau_L and a transport delay fitted to the measured T in the coherent band (coherence >= 0.8) by least squares on log T; then the gains by a stated rule on
that plant (:data:`RULE`), and the same rule on the profile's nominal plant is the analytic
advice the proposal is compared with.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from rig.data import TrialData

SCHEMA_FRF = "rig.tune.frf/1"
SCHEMA_STEP = "rig.tune.step/1"
SMOOTH_S = 0.005        # moving average of the step response (the LVDT's noise)
SETTLE_BAND = 0.05      # settled within 5 % of the step
MIN_COHERENCE = 0.8     # frequencies used for margins, comparison and the fit
COMPARE_MAX_HZ = 50.0   # the comparison band: measured vs model up to 50 Hz
RULE = ("kp = sqrt(kp_lo kp_hi): kp_lo = 2 x k_cr of the rig's loop (rig stability's advice), kp_hi = the "
        "smaller of the largest kp with phase margin >= 45 deg and gain margin >= 6 dB and the LVDT-noise bound "
        "2 N A / sigma; kd = 2 x 0.7 sqrt(kp m); ki = kp x 2 pi f_c / 2; FF1 = k_h tau_L")


def segment_window(trial: TrialData, kind: str) -> dict:
    """The last ``kind`` event of the record (``square`` or ``sine_sweep``). ValueError if none."""
    evs = [e for e in (trial.events or []) if e.get("kind") == kind]
    if not evs:
        raise ValueError(f"{trial.source or 'record'}: no {kind} segment in the log (its '{kind}' event); "
                         f"run a recipe with a {kind} segment, e.g. config/recipes/tune-sweep.yaml")
    return evs[-1]


def _window(trial: TrialData, t0: float, t1: float):
    t = np.asarray(trial.time_s, float)
    if trial.position_ref_um is None:
        raise ValueError(f"{trial.source or 'record'}: no position_ref_um column: the reference is needed")
    sel = (t >= t0) & (t <= t1)
    if sel.sum() < 100:
        raise ValueError(f"{trial.source or 'record'}: {int(sel.sum())} samples in {t0:.3f}..{t1:.3f} s "
                         "(the 1 kHz raw channel is needed: rig tune reads it from an .mcap)")
    dt = float(np.median(np.diff(t[sel])))
    return t[sel], np.asarray(trial.position_ref_um, float)[sel], np.asarray(trial.position_um, float)[sel], dt


# ---------------------------------------------------------------------------
# Step response
# ---------------------------------------------------------------------------

def step_response(trial: TrialData) -> dict:
    """Rise, overshoot, settling and following error of each edge of the last square segment."""
    ev = segment_window(trial, "square")
    t, r, y, dt = _window(trial, ev["t_s"] - 0.05, ev["t_end_s"])
    base = ev["x_um"] + ev.get("velocity_um_s", 0.0) * (t - ev["t_s"])
    rd, yd = r - base, y - base
    n_s = max(1, int(round(SMOOTH_S / dt)))
    ys = np.convolve(yd, np.ones(n_s) / n_s, mode="same")
    edges = list(ev["edges_t_s"])
    rows = []
    for k, te in enumerate(edges):
        t_next = edges[k + 1] if k + 1 < len(edges) else ev["t_end_s"]
        pre = (t >= te - 0.02) & (t < te)
        post = (t >= te) & (t < t_next)
        if pre.sum() < 3 or post.sum() < 10:
            continue
        r0 = float(np.mean(rd[pre]))
        r1 = float(rd[post][-1])
        delta = r1 - r0
        if abs(delta) < 1e-9:
            continue
        s = (ys[post] - float(np.mean(yd[pre]))) / delta
        tt = t[post] - te
        i10, i90 = int(np.argmax(s >= 0.1)), int(np.argmax(s >= 0.9))
        reached = bool(s.max() >= 0.9)
        out = np.flatnonzero(np.abs(s - 1.0) > SETTLE_BAND)
        settled = out.size == 0 or out[-1] < s.size - max(3, int(round(0.05 / dt)))
        V, ve = ev.get("velocity_um_s", 0.0), ev.get("edge_speed_um_s", math.inf)
        rows.append({"edge": k, "t_s": float(te), "delta_um": delta,
                     "reverses": bool(V > 0 and delta < 0 and ve > V),
                     "rise_s": float(tt[i90] - tt[i10]) if reached else None,
                     "overshoot": float(s.max() - 1.0),
                     "settling_s": (float(tt[out[-1] + 1]) if out.size else 0.0) if settled else None})
    if not rows:
        raise ValueError(f"{trial.source or 'record'}: no edge of the square segment could be measured")
    e = r - y
    fin = [r_ for r_ in rows if r_["rise_s"] is not None]
    # on a slide, an edge faster than the slide against it reverses the sliding: the friction
    # flips sign and that edge measures friction, not the loop; the means leave such edges out
    used = [r_ for r_ in rows if not r_["reverses"]] or rows

    def mean(key):
        v = [r_[key] for r_ in used if r_[key] is not None]
        return float(np.mean(v)) if v else None

    return {"schema": SCHEMA_STEP, "source": trial.source, "segment": {k: v for k, v in ev.items() if k != "edges_t_s"},
            "edges": rows, "rise_s": mean("rise_s"), "overshoot": mean("overshoot"), "settling_s": mean("settling_s"),
            "following_error_rms_um": float(np.sqrt(np.mean(e * e))), "following_error_max_um": float(np.abs(e).max()),
            "n_reached": len(fin), "settle_band": SETTLE_BAND, "edges_in_means": [r_["edge"] for r_ in used]}


# ---------------------------------------------------------------------------
# Frequency response
# ---------------------------------------------------------------------------

def h1_estimate(r: np.ndarray, y: np.ndarray, fs_hz: float, nperseg: int,
                keep: np.ndarray | None = None, band_of=None,
                overlap: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """(f, H1 = P_ry / P_rr, coherence, segments used, segments averaged per bin) by Welch's method: Hann windows of
    ``nperseg`` samples, ``overlap`` between neighbours, each segment's mean removed. ``keep``
    (per sample, bool): a segment with any sample not kept is left out (a loop stall inside it).
    ``band_of(i0, i1)``: the (lowest, highest) frequency the input has in samples i0..i1 (a
    sweep); each bin then averages only the segments whose band, widened by 1.25x both ways,
    holds it, so the spectra are not diluted by segments in which the sweep is elsewhere (with a
    log sweep every bin gets the same time, T ln(1.25^2) / ln(f1/f0))."""
    nperseg = int(min(nperseg, r.size))
    step = max(1, int(round(nperseg * (1.0 - overlap))))
    win = np.hanning(nperseg)
    starts = [i for i in range(0, r.size - nperseg + 1, step) if keep is None or keep[i:i + nperseg].all()]
    if not starts:
        raise ValueError("no stretch of the sweep free of loop stalls as long as one Welch segment "
                         f"({nperseg} samples); lower --nperseg")
    f = np.fft.rfftfreq(nperseg, 1.0 / fs_hz)
    R = np.array([np.fft.rfft(win * (r[i:i + nperseg] - r[i:i + nperseg].mean())) for i in starts])
    Y = np.array([np.fft.rfft(win * (y[i:i + nperseg] - y[i:i + nperseg].mean())) for i in starts])
    W = np.ones(R.shape)
    if band_of is not None:
        for k, i in enumerate(starts):
            lo, hi = band_of(i, i + nperseg)
            W[k] = (f >= lo / 1.25) & (f <= hi * 1.25)
    n = W.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_rr = (W * np.abs(R) ** 2).sum(axis=0) / n
        p_yy = (W * np.abs(Y) ** 2).sum(axis=0) / n
        p_ry = (W * np.conj(R) * Y).sum(axis=0) / n
        h = p_ry / p_rr
        coh = np.where(n >= 3, np.abs(p_ry) ** 2 / (p_rr * p_yy), 0.0)
    return f, h, np.nan_to_num(coh.real), len(starts), n


STALE_S = 0.010         # the same position reading this long on a slide: the stream was held up
RECOVER_S = 0.5         # segments within this after a stale stretch are left out (the loop's recovery)


def _stale_runs(y: np.ndarray, dt: float) -> list[tuple[int, int]]:
    """Index ranges where the position reading does not change for at least STALE_S."""
    same = np.concatenate([[False], np.diff(y) == 0.0])
    d = np.diff(np.concatenate([[0], same.astype(np.int8), [0]]))
    n = max(2, int(round(STALE_S / dt)))
    return [(int(a) - 1, int(b)) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)) if b - a >= n]


def controller_terms(ctrl: dict, friction: dict | None, V_um_s: float, f_hz: np.ndarray, dt_s: float):
    """C(z) and the feed-forward F(z) on the reference (module docstring) at ``f_hz``."""
    z = np.exp(2j * np.pi * f_hz * dt_s)
    s = 2j * np.pi * f_hz
    diff = (1.0 - 1.0 / z) / dt_s
    C = ctrl["kp_N_per_um"] + ctrl["ki_N_per_um_s"] * dt_s / (z - 1.0) + ctrl["kd_N_s_per_um"] * diff
    F = ctrl.get("ff1_N_s_per_um", 0.0) * diff
    if friction is not None and V_um_s > 0:
        A, B, L = friction["A_N"], friction["B_N"], friction["L_um"]
        F = F + (A / V_um_s - (B / L) / (s + V_um_s / L)) * diff
    return C, F


def plant_response(lm, f_hz: np.ndarray, delay_s: float = 0.0) -> np.ndarray:
    """P(z) = c (zI - Phi)^-1 Gam of the loop model's plant under a zero-order hold (µm per N),
    times a transport delay."""
    from rig.analysis.stability import discrete_plant

    Phi, Gam, c = discrete_plant(lm)
    z = np.exp(2j * np.pi * f_hz * lm.dt_s)
    eye = np.eye(Phi.shape[0])
    P = np.array([c @ np.linalg.solve(zk * eye - Phi, Gam) for zk in z])
    return P * np.exp(-2j * np.pi * f_hz * delay_s)


def loop_model(profile, model, V_um_s: float, **over):
    """rig stability's LoopModel of ``profile`` with the friction ``model`` at V (plant ``rig``)."""
    from rig.analysis.stability import LoopModel

    lm = LoopModel.from_profile(profile, model, V0_um_s=max(V_um_s, 1e-3), plant="rig")
    return replace(lm, **over) if over else lm


def _friction_terms(lm) -> dict:
    return {"A_N": lm.A_N, "B_N": lm.B_N, "L_um": lm.L_um}


def closed_loop(P, C, F) -> np.ndarray:
    return P * (C + F) / (1.0 + P * C)


def margins(f_hz: np.ndarray, L: np.ndarray) -> dict:
    """Phase margin (deg) at the last frequency where |L| = 1 (the crossover f_c): 180 - |phase of L|,
    the phase in (-180, 180]; gain margin (dB) where L next crosses the negative real axis above
    f_c. (Below f_c, where the rate-weakening friction makes the sliding plant open-loop
    unstable, stability is k_cr's matter: eq. 8 and rig stability's k_cr_loop.)"""
    mag = np.abs(L)
    out = {"gain_margin_db": None, "gain_margin_hz": None, "phase_margin_deg": None, "crossover_hz": None}
    i0 = 0
    k = np.flatnonzero((mag[:-1] - 1.0) * (mag[1:] - 1.0) <= 0)
    if k.size:
        i = int(k[-1])
        w = math.log(mag[i]) / (math.log(mag[i]) - math.log(mag[i + 1])) if mag[i] != mag[i + 1] else 0.0
        Lc = L[i] * (L[i + 1] / L[i]) ** w
        out["crossover_hz"] = float(f_hz[i] + w * (f_hz[i + 1] - f_hz[i]))
        out["phase_margin_deg"] = float(180.0 - abs(math.degrees(np.angle(Lc))))
        i0 = i
    im = L.imag[i0:]
    k = np.flatnonzero((im[:-1] * im[1:] <= 0) & (L.real[i0:-1] < 0) & (L.real[i0 + 1:] < 0))
    if k.size:
        i = int(k[0]) + i0
        w = L.imag[i] / (L.imag[i] - L.imag[i + 1]) if L.imag[i] != L.imag[i + 1] else 0.0
        m = mag[i] * (mag[i + 1] / mag[i]) ** w
        out["gain_margin_db"] = float(-20 * math.log10(m))
        out["gain_margin_hz"] = float(f_hz[i] + w * (f_hz[i + 1] - f_hz[i]))
    return out


def bandwidth_3db(f_hz: np.ndarray, T: np.ndarray) -> float | None:
    """First frequency where |T| falls 3 dB below its level at the lowest frequencies."""
    g = 20 * np.log10(np.maximum(np.abs(T), 1e-300))
    ref = float(np.median(g[: max(3, g.size // 20)]))
    k = np.flatnonzero(g < ref - 3.0)
    if not k.size or k[0] == 0:
        return None
    i = int(k[0])
    w = (ref - 3.0 - g[i - 1]) / (g[i] - g[i - 1])
    return float(f_hz[i - 1] + w * (f_hz[i] - f_hz[i - 1]))


def _compare_model(fb: np.ndarray, ratio: np.ndarray, g2: np.ndarray, n_bin: np.ndarray, f0_hz: float) -> dict:
    """Measured over modelled response (``ratio``) at the coherent frequencies ``fb`` below COMPARE_MAX_HZ:
    the verdict on 1/6-octave bands (the mean ratio of the coherent bins in each): a bin's own random error,
    sqrt(1 - g^2) / (g sqrt(2 n_d)) (Bendat & Piersol), is 0.5-1 dB at g^2 = 0.8; and, when the model misses,
    the phase slope a pure delay would show."""
    dg, dp = 20 * np.log10(np.abs(ratio)), np.degrees(np.angle(ratio))
    edges = f0_hz * 2.0 ** (np.arange(0, 60) / 6.0)
    idx = np.searchsorted(edges, fb)
    bands = [(float(np.exp(np.mean(np.log(fb[idx == k])))), ratio[idx == k].mean()) for k in np.unique(idx)]
    bg = np.array([20 * math.log10(abs(b)) for _, b in bands])
    bp = np.array([math.degrees(np.angle(b)) for _, b in bands])
    # segments averaged per bin; with 75 % overlap about half of them are independent
    n_d = np.maximum(n_bin / 2.0, 1.0)
    rand_db = 20 * np.log10(1 + np.sqrt(1 - g2) / (np.sqrt(g2) * np.sqrt(2 * n_d)))
    out = {"max_hz": COMPARE_MAX_HZ, "n": int(fb.size), "n_bands": len(bands),
           "band_hz": [b for b, _ in bands], "band_gain_db": bg.tolist(),
           "band_phase_deg": bp.tolist(),
           "gain_db_max_abs": float(np.abs(bg).max()), "phase_deg_max_abs": float(np.abs(bp).max()),
           "bin_gain_db_max_abs": float(np.abs(dg).max()),
           "bin_phase_deg_max_abs": float(np.abs(dp).max()),
           "gain_db_rms": float(np.sqrt(np.mean(dg ** 2))),
           "phase_deg_rms": float(np.sqrt(np.mean(dp ** 2))),
           "bin_random_error_db_median": float(np.median(rand_db)),
           "within_1db_5deg": bool(np.abs(bg).max() <= 1.0 and np.abs(bp).max() <= 5.0)}
    # why not: a pure delay shows as phase growing with frequency at equal gain
    if not out["within_1db_5deg"]:
        slope = float(np.polyfit(fb, dp, 1)[0]) if fb.size > 2 else 0.0
        out["phase_slope_deg_per_hz"] = slope
        out["delay_ms"] = float(-slope / 360.0 * 1e3)
    return out


def frf(trial: TrialData, profile, model, switches: dict | None = None, nperseg: int = 1024) -> dict:
    """The measured frequency response of the last sine sweep, its margins and bandwidth, and the
    loop model's response of ``profile`` (friction ``model``) at the same frequencies."""
    ev = segment_window(trial, "sine_sweep")
    taper = float(ev.get("taper_s", 0.0))
    t, r, y, dt = _window(trial, ev["t_s"] + taper, ev["t_end_s"] - taper)
    fs = 1.0 / dt
    line = np.polyfit(t - t[0], r, 1)
    base = np.polyval(line, t - t[0])
    V = float(ev.get("velocity_um_s", 0.0))
    # loop stalls (the hardware loop's 'stall' events: the reference held, the plant not) spoil
    # the segments they fall in
    keep = np.ones(t.size, bool)
    stalls = [e for e in (trial.events or []) if e.get("kind") == "stall" and t[0] <= e["t_s"] <= t[-1]]
    for e in stalls:
        keep[(t >= e["t_s"] - 0.01) & (t <= e["t_s"] + 0.05)] = False
    # a stale position stream (the same reading for STALE_S while the slide moves: the sensor's
    # frames held up) is a disturbance too, and the loop's recovery from it lasts a while
    stale = _stale_runs(y, dt) if V > 0 else []
    for i0, i1 in stale:
        keep[(t >= t[i0] - 0.01) & (t <= t[min(i1, t.size - 1)] + RECOVER_S)] = False
    kk = math.log(ev["f1_hz"] / ev["f0_hz"]) / ev["duration_s"]
    tau0 = t[0] - ev["t_s"]

    def band_of(i0, i1):  # the log sweep's instantaneous frequency over samples i0..i1
        return (ev["f0_hz"] * math.exp(kk * (tau0 + i0 * dt)), ev["f0_hz"] * math.exp(kk * (tau0 + i1 * dt)))

    f, H, coh, n_seg, n_bin = h1_estimate(r - base, y - base, fs, nperseg, keep, band_of, overlap=0.75)
    band = (f >= ev["f0_hz"]) & (f <= ev["f1_hz"])
    f, H, coh, n_bin = f[band], H[band], coh[band], n_bin[band]
    sw = {"ff1": True, "friction_ff": False, **(switches or {})}
    ctrl = profile.controller.model_dump()
    if not sw["ff1"]:
        ctrl["ff1_N_s_per_um"] = 0.0
    notes = []
    lm = None
    try:
        lm = loop_model(profile, model, V)
    except ValueError as exc:
        notes.append(f"no loop model: {exc}")
    fric = _friction_terms(lm) if (lm is not None and sw["friction_ff"]) else None
    C, F = controller_terms(ctrl, fric, V, f, dt)
    with np.errstate(divide="ignore", invalid="ignore"):
        P_meas = H / (C + F - H * C)
    L_meas = P_meas * C
    out = {"schema": SCHEMA_FRF, "source": trial.source,
           "segment": {k: v for k, v in ev.items()}, "nperseg": int(nperseg),
           "frequency_hz": f, "gain_db": 20 * np.log10(np.abs(H)), "phase_deg": np.degrees(np.unwrap(np.angle(H))),
           "coherence": coh, "controller": {k: ctrl[k] for k in ("kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um",
                                                                 "ff1_N_s_per_um")},
           "switches": sw, "slide_um_s": V, "segments_used": n_seg, "stalls_in_sweep": len(stalls),
           "stale_position_runs": len(stale)}
    good = coh >= MIN_COHERENCE
    out["coherent_fraction"] = float(good.mean()) if good.size else 0.0
    out["bandwidth_3db_hz"] = bandwidth_3db(f[good], H[good]) if good.sum() > 5 else None
    out.update({k: v for k, v in margins(f[good], L_meas[good]).items()} if good.sum() > 5 else
               margins(f, L_meas))
    if V <= 0:
        notes.append("the sweep has no slide beneath it: the interface sticks and slips within each cycle and "
                     "friction is not linear; a sweep on a slide (velocity_um_s > 2 pi f1 amplitude_um) "
                     "linearises it about steady sliding, as the loop model does")
    elif 2 * math.pi * ev["f1_hz"] * ev["amplitude_um"] >= V:
        notes.append(f"the velocity reverses above f = {V / (2 * math.pi * ev['amplitude_um']):.3g} Hz "
                     "(2 pi f amplitude > slide velocity): friction is not linear there")
    if lm is not None:
        T_model = closed_loop(plant_response(lm, f), C, F)
        out["model"] = {"gain_db": 20 * np.log10(np.abs(T_model)),
                        "phase_deg": np.degrees(np.unwrap(np.angle(T_model))),
                        "V0_um_s": V, "note": "rig stability's LoopModel of the profile (plant 'rig'), linearised "
                                              "about steady sliding at the slide velocity"}
        cmp_ = good & (f <= COMPARE_MAX_HZ)
        if cmp_.any():
            out["compare"] = _compare_model(f[cmp_], H[cmp_] / T_model[cmp_], coh[cmp_], n_bin[cmp_], ev["f0_hz"])
    out["notes"] = notes
    return out


# ---------------------------------------------------------------------------
# Autotune: a plant fit to the measured response, then the gains
# ---------------------------------------------------------------------------

FIT_PARAMS = ("tau_leak_s", "delay_s")
ZETA = 0.7              # damping ratio of the actuator mass on the loop stiffness (kd)
PM_MIN_DEG = 45.0       # the largest kp keeps these margins on the (fitted) plant
GM_MIN_DB = 6.0


def fit_plant(rep: dict, profile, model, max_hz: float | None = None) -> dict:
    """Fit the leakage time constant (the actuator's velocity-force slope k_h tau_L, per unit of
    the force demand) and a transport delay to the measured closed loop ``rep`` (:func:`frf`),
    on the coherent band, by least squares on log T (log gain and phase in rad).

    Not fitted, and said so: the moving mass (the actuator's resonance on its oil,
    sqrt(k_h / m), 160 Hz for the profile, lies above a sweep the stroke allows) and the force
    gain (valve command to force): below the leakage corner 1 / (2 pi tau_L) (80 Hz) the plant
    is g / (k_h tau_L s), so the sweep sees only their ratio (fitted together they came out
    0.86 and 1.75 ms against 1 and 2 ms, each +-21-23 %, their ratio within 2 %). The profile's
    full-scale force and mass are kept."""
    from scipy.optimize import least_squares

    f = np.asarray(rep["frequency_hz"], float)
    coh = np.asarray(rep["coherence"], float)
    H = 10 ** (np.asarray(rep["gain_db"]) / 20) * np.exp(1j * np.radians(rep["phase_deg"]))
    use = coh >= MIN_COHERENCE
    if max_hz is not None:
        use &= f <= max_hz
    if use.sum() < 8:
        raise ValueError(f"only {int(use.sum())} frequencies with coherence >= {MIN_COHERENCE:g}: too few to fit "
                         "the plant (a longer sweep, a larger amplitude, or a slide beneath it)")
    f, H = f[use], H[use]
    V = rep["slide_um_s"]
    lm0 = loop_model(profile, model, V)
    fric = _friction_terms(lm0) if rep["switches"].get("friction_ff") else None
    C, F = controller_terms(rep["controller"], fric, V, f, lm0.dt_s)
    x0 = np.log([lm0.tau_leak_s, 2e-4])

    def T_of(q):
        tl, d = np.exp(q)
        return closed_loop(plant_response(replace(lm0, tau_leak_s=tl), f, d), C, F)

    def resid(q):
        r = np.log(T_of(q) / H)
        return np.concatenate([r.real, r.imag])

    sol = least_squares(resid, x0, bounds=(x0 - np.log([10, 1e3]), x0 + np.log([10, 50])))
    r = sol.fun
    n, p = r.size, sol.x.size
    s2 = float(r @ r) / max(n - p, 1)
    try:
        rel = np.sqrt(np.maximum(np.diag(np.linalg.inv(sol.jac.T @ sol.jac) * s2), 0.0))  # of the logs
    except np.linalg.LinAlgError:
        rel = np.full(p, np.nan)
    tl, d = np.exp(sol.x)
    return {"params": {"gain": 1.0, "tau_leak_s": float(tl), "delay_s": float(d)},
            "rel_err": {"gain": 0.0, **dict(zip(FIT_PARAMS, rel.tolist()))},
            "nominal": {"gain": 1.0, "tau_leak_s": lm0.tau_leak_s, "delay_s": 0.0},
            "mass_kg": lm0.mass_kg, "mass_note": "not resolved by the sweep: the profile's",
            "gain_note": "not separable from the leakage below its corner: the profile's full scale",
            "rms_log": float(math.sqrt(float(r @ r) / n)), "n_freq": int(f.size),
            "band_hz": [float(f[0]), float(f[-1])]}


def propose_gains(profile, model, plant: dict | None = None, margin: float = 2.0, V_um_s: float = 100.0) -> dict:
    """Gains on the plant (``plant``: :func:`fit_plant`'s result; None: the profile's nominal plant,
    which makes this the analytic advice):

    * kp = sqrt(kp_lo kp_hi), as far from either limit by the same factor: kp_lo = ``margin`` x
      k_cr of the rig's loop (rig stability's advice: PID, the profile's ki, at 1 µm/s), kp_hi
      the smaller of the largest kp with a phase margin >= 45 deg and a gain margin >= 6 dB
      (PD, on a 1.25x grid, the plant sliding at ``V_um_s``, the sweep's slide) and the noise
      bound 2 N A / (g sigma_LVDT): the LVDT's noise through kp no larger than the friction's
      direct effect per e-fold of velocity (eq. 5);
    * kd = 2 zeta sqrt(kp g m), zeta = 0.7: the actuator mass damped on the loop stiffness;
    * ki = kp x 2 pi f_c / 2, the integral's corner an octave below the PD loop's crossover
      f_c (it costs atan(1/2) = 27 deg of phase margin there, and the integral takes over the
      friction's constant level, 2 N mu0, which the feed-forward leaves to it, within about
      2 / (2 pi f_c));
    * FF1 = k_h tau_L + c_a / g: the actuator's velocity-force slope (leakage), per unit of the
      force demand.

    Stated with them: the margin to k_cr of the loop with the proposed gains (PID, 1 µm/s)."""
    from rig.analysis.stability import k_cr_loop

    g, tl, delay = 1.0, None, 0.0
    if plant is not None:
        g, tl, delay = plant["params"]["gain"], plant["params"]["tau_leak_s"], plant["params"]["delay_s"]
    over = {"tau_leak_s": tl} if tl is not None else {}
    lm = loop_model(profile, model, 1.0, **over)
    lm_v = loop_model(profile, model, V_um_s, **over)
    k_cr_advice = k_cr_loop(lm)
    if not k_cr_advice:
        k_cr_advice = k_cr_loop(replace(lm, ki_N_per_um_s=0.0))
    if not k_cr_advice:
        raise ValueError("the loop model has no finite k_cr: no lower bound for kp")
    kp_lo = margin * k_cr_advice / g
    f = np.geomspace(1e-3, 0.49 / lm.dt_s, 800)
    P = g * plant_response(lm_v, f, delay)
    m_N = lm.mass_kg * 1e-6  # N s²/µm
    diff = (1 - np.exp(-2j * np.pi * f * lm.dt_s)) / lm.dt_s
    kp_margin, kp = None, kp_lo
    while kp < 1e3:
        kd = 2 * ZETA * math.sqrt(kp * g * m_N) / g
        mg = margins(f, P * (kp + kd * diff))
        if mg["phase_margin_deg"] is None or mg["phase_margin_deg"] < PM_MIN_DEG or \
                (mg["gain_margin_db"] is not None and mg["gain_margin_db"] < GM_MIN_DB):
            break
        kp_margin = kp
        kp *= 1.25
    if kp_margin is None:
        raise ValueError(f"kp = {kp_lo:.3g} N/µm ({margin:g} x k_cr) already breaks the margins on this plant")
    sigma = profile.sensors.lvdt.noise_sigma_um
    kp_noise = lm.A_N / (g * sigma) if sigma > 0 else math.inf
    kp_hi = min(kp_margin, kp_noise)
    kp = math.sqrt(kp_lo * max(kp_hi, kp_lo))
    kd = 2 * ZETA * math.sqrt(kp * g * m_N) / g
    fc = margins(f, P * (kp + kd * diff))["crossover_hz"]
    ki = kp * 2 * math.pi * fc / 2.0
    z = np.exp(2j * np.pi * f * lm.dt_s)
    mg = margins(f, P * (kp + ki * lm.dt_s / (z - 1.0) + kd * diff))
    ff1 = lm.k_h_N_per_um * lm.tau_leak_s + lm.c_a_N_s_per_um / g
    k_cr = k_cr_loop(replace(lm, kd_N_s_per_um=kd, ki_N_per_um_s=ki))
    return {"kp_N_per_um": kp, "ki_N_per_um_s": ki, "kd_N_s_per_um": kd, "ff1_N_s_per_um": ff1,
            "kp_lo_N_per_um": kp_lo, "kp_hi_N_per_um": kp_hi, "kp_margin_limit_N_per_um": kp_margin,
            "kp_noise_limit_N_per_um": kp_noise, "crossover_hz": fc, "phase_margin_deg": mg["phase_margin_deg"],
            "gain_margin_db": mg["gain_margin_db"], "k_cr_N_per_um": k_cr,
            "margin_to_k_cr": (kp * g / k_cr) if k_cr else None,
            "no_finite_k_cr": k_cr == 0.0}


def build_frf(rep: dict):
    """Bode plot: the measured H1 (coherent points solid, the rest faint) and the loop model, with
    the coherence beneath."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    from rig.analysis.plots import PAGE_WIDTH_IN, _plt

    plt = _plt()
    fig, axs = plt.subplots(3, 1, figsize=(PAGE_WIDTH_IN, 5.2), layout="constrained", sharex=True,
                            gridspec_kw={"height_ratios": [3, 3, 1.4]})
    f = np.asarray(rep["frequency_hz"], float)
    coh = np.asarray(rep["coherence"], float)
    good = coh >= MIN_COHERENCE
    for ax, key, unit in ((axs[0], "gain_db", "gain (dB)"), (axs[1], "phase_deg", "phase (deg)")):
        y = np.asarray(rep[key], float)
        ax.plot(f, np.where(good, np.nan, y), ".", color="C0", alpha=0.25, ms=2)
        ax.plot(f, np.where(good, y, np.nan), ".-", color="C0", ms=3, label="measured H1 (coherence >= 0.8)")
        if "model" in rep:
            ax.plot(f, rep["model"][key], "-", color="C3", lw=1.0, label="loop model (rig stability, same profile)")
        ax.set_ylabel(unit)
        shown = np.concatenate([y[good], np.asarray(rep["model"][key], float) if "model" in rep else []])
        if shown.size:
            pad = 0.15 * max(float(np.ptp(shown)), 1.0)
            ax.set_ylim(float(shown.min()) - pad, float(shown.max()) + pad)
    c = rep.get("compare")
    sub = (f"\nmeasured vs model up to {c['max_hz']:g} Hz (1/6-octave bands): max {c['gain_db_max_abs']:.2f} dB, "
           f"{c['phase_deg_max_abs']:.1f} deg (single bins: rms {c['gain_db_rms']:.2f} dB, {c['phase_deg_rms']:.1f} deg)"
           if c else "")
    axs[0].set_title(f"closed loop, reference to LVDT position: -3 dB at {g3n(rep['bandwidth_3db_hz'])} Hz, phase "
                     f"margin {g3n(rep['phase_margin_deg'])} deg, gain margin {g3n(rep['gain_margin_db'])} dB{sub}")
    axs[2].plot(f, coh, "-", color="0.3")
    axs[2].axhline(MIN_COHERENCE, color="0.6", lw=0.5, ls="--")
    axs[2].set_ylim(0, 1.05)
    axs[2].set_ylabel("coherence")
    axs[2].set_xlabel("frequency (Hz)")
    axs[2].set_xscale("log")
    ticks = [m * 10.0 ** e for e in range(-2, 4) for m in (1, 2, 5)]
    axs[2].xaxis.set_major_locator(FixedLocator([v for v in ticks if f.size and f.min() <= v <= f.max()] or ticks))
    axs[2].xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axs[2].xaxis.set_minor_formatter(NullFormatter())
    h, lab = axs[0].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncols=2)
    return fig


def g3n(v) -> str:
    return "-" if v is None else f"{v:.3g}"


def plot_frf(rep: dict, path) -> None:
    from rig.analysis.plots import save

    save(build_frf(rep), path)


__all__ = ["build_frf", "plot_frf", "step_response", "frf", "h1_estimate", "margins", "bandwidth_3db", "fit_plant", "propose_gains",
           "segment_window", "SCHEMA_FRF", "SCHEMA_STEP", "RULE"]
