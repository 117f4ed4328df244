"""The rig's controller: digital PID on position error plus a 500 Hz dither (paper, section 3).

"A digital PID controller operates on position error. The derivative term is
approximated using the backward difference method. The integral term is computed as
the scaled sum of prior values. [...] The PID output is combined with a 500 Hz dither
sinusoid. A dither amplitude [of] 0.1 percent of the PID output reduced the effects of
servovalve stiction [...]. The control loop operates at 1 kHz." (Dupont & Dunlap 1995)

Units: error in µm, PID output (force demand) in N, gains ``kp_N_per_um``,
``ki_N_per_um_s``, ``kd_N_s_per_um``. At tick n, with e_n = clamp(x_ref,n - x_n):

    P_n = kp e_n
    I_n = ki dt sum_{k<n} e_k        (prior errors only; anti-windup below)
    D_n = kd (e_n - e_{n-1}) / dt    (backward difference; 0 at the first tick)
    F_n = ff1 v_ref,n                (velocity feed-forward, LinuxCNC's FF1; optional)
    u_n = clamp(bias + P_n + I_n + D_n + F_n + G_n, ±output_max_N)

with G_n an optional per-tick feed-forward force (N) supplied with the reference, like a
driven LinuxCNC ``bias`` pin: the simulated rig feeds the friction force that the friction
model in use predicts along the reference (friction feed-forward, rig.sim.rig.
friction_feedforward_N; the model-based feed-forward of the paper's introduction); 0 when
not given.

with v_ref,n the planner's reference velocity: given explicitly
(:func:`controller_step_v`'s ``v_ref_um_s``) or, as LinuxCNC
does without a ``command-deriv`` input, the backward difference of the reference
(x_ref,n - x_ref,n-1)/dt (exact for the planner's piecewise-linear/ramped reference;
0 at the first tick). ``ff1_N_s_per_um`` is the force per unit reference velocity: for
this valve-controlled actuator the natural value is the leakage slope k_h tau_L (the
valve opening that keeps the actuator moving at v_ref), plus whatever linear share of
the friction's rate dependence one wants to pre-empt; 0 (the default) turns it off.

in the order of LinuxCNC's ``pid.c``: error; integral (the prior error e_{n-1} is added
only if the output was not saturated in the direction of that error at the previous
tick, and the integral term is clamped to ±integral_max_N); derivative; output clamp;
saturated flag.

Dither: d_n = a_n cos(2 pi f_d n dt). At f_d = 500 Hz and 1 kHz, cos(pi n) = (-1)^n (a
sine would be zero at every tick and never reach the valve). Amplitude a_n =
``dither_amplitude_fraction`` times either the low-passed |PID output| (time constant
``dither_smoothing_s``; "0.1 percent of the PID output", the default) or the full scale
force (``dither_reference: full_scale``).

Valve command: v_n = clamp((u_n + d_n) / full_scale_force_N, ±1).

The step is one ``@njit`` function on parameter/state arrays, :func:`controller_step_v`
(:func:`pid_step` then :func:`dither_step`), called tick by tick by both loops: the numba
closed loop of :mod:`rig.sim` (``rig.sim.plant``) and the Python hardware loop
(:mod:`rig.hardware.loop`).
"""

from __future__ import annotations

import math

import numpy as np
from rig.jitstart import kernel

# controller parameter vector
C_KP = 0
C_KI = 1
C_KD = 2
C_DT = 3
C_IMAX = 4     # clamp on |integral term| (N)
C_OMAX = 5     # clamp on |PID output| (N)
C_EMAX = 6     # clamp on |error| (µm)
C_BIAS = 7     # N
C_FFS = 8      # full-scale force (N): valve command = demand / FFS
C_DFREQ = 9    # dither frequency (Hz)
C_DFRAC = 10   # dither amplitude fraction
C_DMODE = 11   # 0: fraction of low-passed |PID output|; 1: fraction of full scale
C_DALPHA = 12  # exp(-dt / dither_smoothing_s)
C_FF1 = 13     # velocity feed-forward gain (N s/µm)
N_CPAR = 14

# controller state vector
K_SUM = 0      # sum of prior errors times dt (µm s)
K_PREV_E = 1   # previous error (µm)
K_SAT = 2      # saturation sign of the previous output (-1, 0, +1)
K_FIRST = 3    # 1.0 until the first step
K_AMP = 4      # low-passed |PID output| (N)
K_N = 5        # tick counter
K_PREV_REF = 6  # previous reference (µm), for the FF1 backward difference
N_CSTATE = 7


def make_controller_params(kp_N_per_um: float, ki_N_per_um_s: float, kd_N_s_per_um: float, dt_s: float,
                           integral_max_N: float = 500.0, output_max_N: float = 1e4, error_max_um: float = 1e9,
                           bias_N: float = 0.0, full_scale_force_N: float = 1e4, dither_frequency_hz: float = 500.0,
                           dither_amplitude_fraction: float = 0.001, dither_reference: str = "pid_output",
                           dither_smoothing_s: float = 0.05, ff1_N_s_per_um: float = 0.0) -> np.ndarray:
    """Pack controller parameters (physical units) for :func:`controller_step_v`."""
    c = np.zeros(N_CPAR)
    c[C_KP] = kp_N_per_um
    c[C_KI] = ki_N_per_um_s
    c[C_KD] = kd_N_s_per_um
    c[C_DT] = dt_s
    c[C_IMAX] = integral_max_N
    c[C_OMAX] = output_max_N
    c[C_EMAX] = error_max_um
    c[C_BIAS] = bias_N
    c[C_FFS] = full_scale_force_N
    c[C_DFREQ] = dither_frequency_hz
    c[C_DFRAC] = dither_amplitude_fraction
    if dither_reference not in ("pid_output", "full_scale"):
        raise ValueError(f"dither_reference must be 'pid_output' or 'full_scale', not {dither_reference!r}")
    c[C_DMODE] = 0.0 if dither_reference == "pid_output" else 1.0
    c[C_DALPHA] = math.exp(-dt_s / dither_smoothing_s) if dither_smoothing_s > 0 else 0.0
    if not (math.isfinite(ff1_N_s_per_um) and ff1_N_s_per_um >= 0):
        raise ValueError(f"ff1_N_s_per_um must be a finite number >= 0, not {ff1_N_s_per_um!r}")
    c[C_FF1] = ff1_N_s_per_um
    return c


def controller_params_from_profile(profile) -> np.ndarray:
    """Controller parameter vector from a :class:`rig.config.profile.RigProfile`."""
    c = profile.controller
    return make_controller_params(
        c.kp_N_per_um, c.ki_N_per_um_s, c.kd_N_s_per_um, profile.dt_s, c.integral_max_N, profile.output_max_N,
        c.error_max_um, c.bias_N, profile.actuator.full_scale_force_N, c.dither_frequency_hz,
        c.dither_amplitude_fraction, c.dither_reference, c.dither_smoothing_s, c.ff1_N_s_per_um)


CONTROLLER_SWITCHES = ("ff1", "friction_ff")


def apply_switches(c: np.ndarray, switches: dict | None) -> np.ndarray:
    """The recipe's feed-forward switches (``controller:`` of a recipe, a compiled plan's
    ``controller``) applied to a controller parameter vector, in place: ``ff1`` False sets
    FF1 to 0 for this run (the gain stays the profile's otherwise). ``friction_ff`` is a
    per-tick force array (rig.model.feedforward), not a gain. None: the profile as it is."""
    sw = dict(switches or {})
    unknown = set(sw) - set(CONTROLLER_SWITCHES)
    if unknown:
        raise ValueError(f"controller switches: unknown {sorted(unknown)} (known: {', '.join(CONTROLLER_SWITCHES)})")
    if not sw.get("ff1", True):
        c[C_FF1] = 0.0
    return c


def new_controller_state() -> np.ndarray:
    s = np.zeros(N_CSTATE)
    s[K_FIRST] = 1.0
    return s


@kernel
def pid_step(c, s, x_ref_um, x_meas_um, v_ref_um_s=math.nan, ff_N=0.0):
    """One PID tick (LinuxCNC order) with FF1 and a feed-forward force ``ff_N`` (N). Returns
    (output_N, p_N, i_N, d_N); updates ``s``. ``v_ref_um_s`` NaN: the backward difference of
    the reference."""
    dt = c[C_DT]
    first = s[K_FIRST] > 0.5
    if v_ref_um_s != v_ref_um_s:
        v_ref_um_s = 0.0 if first else (x_ref_um - s[K_PREV_REF]) / dt
    s[K_PREV_REF] = x_ref_um
    e = x_ref_um - x_meas_um
    emax = c[C_EMAX]
    if e > emax:
        e = emax
    elif e < -emax:
        e = -emax
    if s[K_FIRST] > 0.5:
        s[K_PREV_E] = e
        s[K_FIRST] = 0.0
    else:
        # integral: add the prior error unless the output was saturated in its direction
        e_prev = s[K_PREV_E]
        if s[K_SAT] * e_prev <= 0.0:
            s[K_SUM] += e_prev * dt
        ki = c[C_KI]
        if ki > 0.0:
            smax = c[C_IMAX] / ki
            if s[K_SUM] > smax:
                s[K_SUM] = smax
            elif s[K_SUM] < -smax:
                s[K_SUM] = -smax
    p = c[C_KP] * e
    i = c[C_KI] * s[K_SUM]
    d = c[C_KD] * (e - s[K_PREV_E]) / dt
    out = c[C_BIAS] + p + i + d + c[C_FF1] * v_ref_um_s + ff_N
    omax = c[C_OMAX]
    if out > omax:
        out = omax
        s[K_SAT] = 1.0
    elif out < -omax:
        out = -omax
        s[K_SAT] = -1.0
    else:
        s[K_SAT] = 0.0
    s[K_PREV_E] = e
    return out, p, i, d


@kernel
def dither_step(c, s, pid_out_N):
    """Dither value (N) for this tick: a_n cos(2 pi f n dt); advances the tick counter."""
    alpha = c[C_DALPHA]
    s[K_AMP] = alpha * s[K_AMP] + (1.0 - alpha) * abs(pid_out_N)
    if c[C_DMODE] > 0.5:
        amp = c[C_DFRAC] * c[C_FFS]
    else:
        amp = c[C_DFRAC] * s[K_AMP]
    n = s[K_N]
    s[K_N] = n + 1.0
    f = c[C_DFREQ]
    if f <= 0.0 or amp == 0.0:
        return 0.0
    ph = f * c[C_DT] * n
    ph = ph - math.floor(ph)  # keep the phase exact for long runs
    return amp * math.cos(2.0 * math.pi * ph)


@kernel
def controller_step_v(c, s, x_ref_um, x_meas_um, v_ref_um_s, ff_N=0.0):
    """One tick: PID (+ FF1) + dither -> valve command, clamped to ±1. Returns
    (valve_cmd, p_N, i_N, d_N, dither_N). ``v_ref_um_s``: the planner's reference velocity
    (µm/s; NaN: the backward difference of the reference); ``ff_N``: a feed-forward force (N)."""
    out, p, i, d = pid_step(c, s, x_ref_um, x_meas_um, v_ref_um_s, ff_N)
    dz = dither_step(c, s, out)
    v = (out + dz) / c[C_FFS]
    if v > 1.0:
        v = 1.0
    elif v < -1.0:
        v = -1.0
    return v, p, i, d, dz
