"""Numba kernels of the simulated servohydraulic double-shear friction rig.

Units: position µm, velocity µm/s, force N, time s, mass kg, stiffness N/µm (= MN/m).
The equations (docs/sim.md has the full derivation):

Servovalve (first-order spool, optional stiction band ``b`` in command units):
    tau_v dx_sp/dt = u* - x_sp,   u* = u if b = 0, else the spool only moves when
    |u - x_sp| > b and then towards u -/+ b (a play/stiction band the dither overcomes).
Actuator (load pressure p_L = F_a / A_p, leakage C_L, bulk modulus beta):
    dF_a/dt = (F_fs x_sp - F_a) / tau_L - k_h v_a,
    k_h = 4 beta A_p^2 / V_t,  tau_L = V_t / (4 beta C_L);  static gain of a blocked
    actuator: F_a = F_fs x_sp, so the position loop acts as a stiffness kp (eq. 8).
Moving mass (piston + grip + test piece):
    m dv_a/dt = F_a - F_s - c_a v_a,  dx_a/dt = v_a.
Series compliance between actuator and interface, massless (quasi-static): test piece
k_tp (actuator to LVDT point), then the LVDT-to-interface compliance c_li, which is the
fixture + friction load cell's 1/k_fx, or a model's ``finite_stiffness`` 1/k in its place
(rig.model.loading: the diagnosed stiffness replaces the fixture's, it does not add):
1/k_m = 1/k_tp + c_li,
    dF_s/dt = k_m (v_a - v_s),
with v_s the slip velocity of the interfaces and F_s the force in the chain, equal to
the friction force of the double-shear fixture (massless interface):
    F_s = mu(v_s, theta) (N_1 + N_2)        (eq. 5 via rig.model.friction, regularised)
The LVDT point (unstressed test piece next to the interfaces) is x_t = x_a - F_s / k_tp.
Normal forces from soft rider springs k_r on test-piece faces with taper and waviness:
    N_i = N_i0 + k_r h_i(x_t),  h_i = s_i (x_t - x_home)/1000 + a_i sin(2 pi x_t / lambda_i + phi_i).

Integration per substep h: spool exact (zero-order hold); (F_a, v_a) trapezoidal; F_s
implicit in the slip velocity: the unknown v_s is the mean slip velocity over the
substep, found from the scalar force balance P + Q v_s = (N_1 + N_2) mu(v_s) by a
Newton iteration in mu that converges monotonically (no NaN at v_s -> 0, sticking is
the v_s ~ 0 solution); the state theta is then advanced exactly over the slip
``v_s h`` (rig.model.friction.advance_state); position-periodic friction at the
interface position x_0 + delta (delta the slip since reset). Memoryless friction models (steady_state with
time_delay or a slope <= 0) are ill posed on a massless interface and get an interface
mass instead (:func:`solve_slip_mass`). Sensors: first-order low-passes (exact for a
ramp within the tick) sampled at each tick, Gaussian noise entering before each filter (the
hardware's order, rig.model.sensors), LVDT quantisation and range.
"""

from __future__ import annotations

import math

from rig.jitstart import kernel, preload_cython_blas

from rig.model.friction import (P_A, P_MU0, P_STATE_ON, P_V0, P_VREG, S_THETA, S_THETA2, advance_state,
                                mu_regularized, periodic_term, wear_term)
from rig.model.sensors import lowpass_tick, quantize
from rig.control import controller_step_v

preload_cython_blas()  # the simulation's first kernel call loads numba's target without scipy.linalg

# ---------------------------------------------------------------------------
# plant parameter vector
# ---------------------------------------------------------------------------
Q_H = 0          # substep (s)
Q_NSUB = 1       # substeps per tick
Q_DT = 2         # tick (s)
Q_AV = 3         # exp(-h / tau_v)
Q_STIC = 4       # spool stiction band (command units)
Q_FFS = 5        # full-scale force (N)
Q_TAUL = 6       # leakage time constant (s)
Q_KH = 7         # hydraulic stiffness (N/µm)
Q_MKG = 8        # moving mass (kg)
Q_CA = 9         # seal damping (N s/µm)
Q_CTP = 10       # 1/k_tp (µm/N)
Q_CSPARE = 11    # (unused)
Q_CLI = 12       # LVDT point -> interface compliance (µm/N): the fixture's, or the model's finite_stiffness
Q_KM = 13        # series stiffness (N/µm)
Q_K = 14         # 9 entries: inverse of the substep's linear system (row major)
Q_QV = 23        # 3 entries: sensitivity of (F_a, v_a, F_s) to v_s
Q_N10 = 26       # nominal normal force rider 1 (N)
Q_N20 = 27
Q_KR = 28        # rider spring stiffness (N/µm)
Q_TAP1 = 29      # face taper (µm/mm)
Q_TAP2 = 30
Q_WA1 = 31       # waviness amplitude (µm)
Q_WA2 = 32
Q_WL1 = 33       # waviness wavelength (µm)
Q_WL2 = 34
Q_WP1 = 35       # waviness phase (rad)
Q_WP2 = 36
Q_XORG = 37      # position where the taper is zero (µm)
Q_LV_A = 38      # LVDT low-pass exp(-dt/tau)
Q_LV_SIG = 39    # noise input per tick: sigma (1 - a) sqrt((1 + a)/(1 - a)) (rig.model.sensors)
Q_LV_Q = 40
Q_LV_MIN = 41
Q_LV_MAX = 42
Q_FL_A = 43      # friction load cell
Q_FL_SIG = 44
Q_NL_A = 45      # normal load cells
Q_NL_SIG = 46
Q_SL_ON = 47     # sensor_lag extension on
Q_SL_A = 48      # exp(-dt/tau_s)
Q_DRIFT = 49     # force_offset_drift (N/s)
Q_DELAY = 50     # time_delay in ticks (0 = none)
Q_STEADY = 51    # 1: memoryless model on an interface with mass (time_delay, or slope <= 0)
Q_MIH = 52       # interface mass / substep, in N s/µm (m_i 1e-6 / h)
Q_SPARE = 53
Q_LV_G = 54      # (1 - a) tau / dt of each filter: exact response to a ramp within the tick
Q_FL_G = 55
Q_NL_G = 56
Q_SL_G = 57
N_QPAR = 58

# ---------------------------------------------------------------------------
# plant state vector
# ---------------------------------------------------------------------------
Z_XA = 0         # actuator position (µm)
Z_VA = 1         # actuator velocity (µm/s)
Z_FA = 2         # actuator force (N)
Z_FS = 3         # force in the compliant chain = friction force (N)
Z_XSP = 4        # spool position (command units)
Z_VS = 5         # slip velocity of the last substep (µm/s)
Z_MU = 6         # friction coefficient of the last substep
Z_XT = 7         # LVDT point, true (µm)
Z_N1 = 8         # true normal forces (N)
Z_N2 = 9
Z_LVF = 10       # filter states
Z_SLF = 11
Z_FLF = 12
Z_N1F = 13
Z_N2F = 14
Z_TICK = 15      # ticks since reset
Z_RPOS = 16      # ring-buffer position
Z_DELTA = 17     # signed slip since reset (µm)
Z_X0 = 18        # interface position at reset (µm); the interface is at Z_X0 + Z_DELTA
Z_LVE = 19       # sensor noise after each analog filter (the noise enters before the filter)
Z_FLE = 20
Z_N1E = 21
Z_N2E = 22
N_ZSTATE = 23


@kernel
def normal_forces(q, x_t):
    """True normal forces (N) of riders 1 and 2 at LVDT-point position ``x_t``."""
    dx_mm = (x_t - q[Q_XORG]) * 1e-3
    h1 = q[Q_TAP1] * dx_mm + q[Q_WA1] * math.sin(2.0 * math.pi * x_t / q[Q_WL1] + q[Q_WP1])
    h2 = q[Q_TAP2] * dx_mm + q[Q_WA2] * math.sin(2.0 * math.pi * x_t / q[Q_WL2] + q[Q_WP2])
    n1 = q[Q_N10] + q[Q_KR] * h1
    n2 = q[Q_N20] + q[Q_KR] * h2
    if n1 < 0.0:
        n1 = 0.0
    if n2 < 0.0:
        n2 = 0.0
    return n1, n2


@kernel
def friction_law(q, fp, fs, x_i, v_mag):
    """(base, a) of mu(v) = sign(v) R(|v|) with the interface at position ``x_i``.

    Rate-and-state models (and steady_state ones with a positive slope): R = a asinh(|v|/(2
    V0) e^{base/a}) (a > 0) or a smooth sign of height ``base`` (a = 0), with the state(s),
    the position-periodic term (at the interface's position, as the forward model of
    rig.model.loading evaluates it) and the wear term (rig.model.friction) folded into ``base``.
    Memoryless models on the interface mass (Q_STEADY): a = 0 and base = mu_ss(v_mag), the
    log argument held at v_reg near 0 (as rig.model.friction.mu_of does), ``v_mag`` being the
    delayed (time_delay) or the previous substep's slip velocity.
    """
    extra = fs[S_THETA2] + periodic_term(fp, x_i) + wear_term(fp, fs)
    if fp[P_STATE_ON] > 0.5:
        return fp[P_MU0] + fs[S_THETA] + extra, fp[P_A]
    if q[Q_STEADY] < 0.5:
        return fp[P_MU0] + extra, fp[P_A]
    vd = max(abs(v_mag), fp[P_VREG])
    return fp[P_MU0] + extra + fp[P_A] * math.log(vd / fp[P_V0]), 0.0


@kernel
def solve_slip_mass(p2, q2, ntot, base, vreg, mih, v_old):
    """Interface with mass m_i: solve m_i (v - v_old)/h = p2 + q2 v - ntot base s(v) for v,
    s(v) = v / sqrt(v^2 + v_reg^2) (backward Euler; the left side minus the right is
    increasing in v, so the root is unique). Safeguarded Newton. Returns (v, mu)."""
    k = mih - q2
    rhs = mih * v_old + p2
    b = base if base > 0.0 else 0.0
    nb = ntot * b
    lo = (rhs - nb) / k
    hi = (rhs + nb) / k
    v = min(max(v_old, lo), hi)
    vr2 = vreg * vreg
    for _ in range(200):
        r2 = v * v + vr2
        sr = math.sqrt(r2)
        g = k * v - rhs + nb * v / sr
        if g > 0.0:
            hi = v
        else:
            lo = v
        gp = k + nb * vr2 / (r2 * sr)
        vn = v - g / gp
        if not (lo < vn < hi):
            vn = 0.5 * (lo + hi)
        if abs(vn - v) <= 1e-13 * (abs(v) + vreg):
            v = vn
            break
        v = vn
    return v, b * v / math.sqrt(v * v + vr2)


@kernel
def _v_of_mu(mu, base, a, v0, vreg):
    """Inverse of R (mu >= 0): slip speed and d v / d mu."""
    if a > 0.0:
        e1 = math.exp((mu - base) / a)
        if mu > 20.0 * a:  # exp(-2 mu / a) < 4e-18: the backward term is negligible
            return v0 * e1, v0 / a * e1
        e2 = math.exp((-mu - base) / a)
        return v0 * (e1 - e2), v0 / a * (e1 + e2)
    b = base if base > 1e-9 else 1e-9
    m = mu / b
    if m >= 1.0:
        m = 1.0 - 1e-16
    r = 1.0 - m * m
    sr = math.sqrt(r)
    return vreg * m / sr, vreg / b / (r * sr)


@kernel
def solve_slip(p2, q2, ntot, base, a, v0, vreg):
    """Solve p2 + q2 v = ntot mu(v) for the slip velocity v (q2 < 0). Returns (v, mu).

    h(mu) = |p2| - |q2| v(mu) - ntot mu is decreasing and concave for mu >= 0, so Newton
    from an upper bound of the root converges monotonically. Upper bounds: |p2|/ntot
    (friction alone) and R(|p2|/|q2|) (the chain relaxed completely), the second only
    needed (and computed) when the first lies far out on the exponential.
    """
    qq = -q2
    if qq <= 0.0:
        qq = 1e-300
    if ntot <= 0.0:
        return p2 / qq, 0.0
    c = abs(p2)
    if c == 0.0:
        return 0.0, 0.0
    sgn = 1.0 if p2 > 0.0 else -1.0
    b = base
    mu = c / ntot
    if a > 0.0:
        if (mu - b) / a > 20.0:
            mu_b = mu_regularized(c / qq, b, 0.0, a, v0, vreg)
            if mu_b < mu:
                mu = mu_b
        tol = 1e-4 * a
    else:
        if b < 1e-9:
            b = 1e-9
        if mu > 0.999 * b:
            mu_b = mu_regularized(c / qq, b, 0.0, a, v0, vreg)
            if mu_b < mu:
                mu = mu_b
        tol = 1e-7 * b
    for _ in range(200):
        v, dv = _v_of_mu(mu, b, a, v0, vreg)
        h = c - qq * v - ntot * mu
        hp = -qq * dv - ntot
        dmu = h / hp
        mu -= dmu
        if mu < 0.0:
            mu = 0.0
        if abs(dmu) <= tol:
            # quadratic convergence: the error left is at most ~ dmu^2 / a < 1e-8 a
            # (in the friction-dominated regime far less)
            break
    v -= dv * dmu  # v at the final mu, to first order (dmu is below the tolerance)
    if v < 0.0:
        v = 0.0
    return sgn * v, sgn * mu


@kernel
def plant_advance(q, fp, fs, st, ring, u):
    """Advance the plant by one tick with valve command ``u`` held (zero-order hold)."""
    u = min(1.0, max(-1.0, u))
    x_old = st[Z_XT]
    f_old = st[Z_FS]
    slf_old = st[Z_SLF]
    n1_old = st[Z_N1]
    n2_old = st[Z_N2]
    nsub = int(q[Q_NSUB])
    h = q[Q_H]
    tau = q[Q_TAUL]
    kh = q[Q_KH]
    g = h * 1e6 / q[Q_MKG]
    ca = q[Q_CA]
    km = q[Q_KM]
    ffs = q[Q_FFS]
    v0 = fp[P_V0]
    vreg = fp[P_VREG]
    steady = q[Q_STEADY] > 0.5
    nr = ring.shape[0]
    rpos = int(st[Z_RPOS])
    delayed = q[Q_DELAY] > 0.5
    v_del = ring[(rpos + 1) % nr]
    n1 = st[Z_N1]
    n2 = st[Z_N2]
    ntot = n1 + n2
    for _ in range(nsub):
        # spool
        xsp = st[Z_XSP]
        stic = q[Q_STIC]
        target = u
        if stic > 0.0:
            e = u - xsp
            if abs(e) <= stic:
                target = xsp
            elif e > 0.0:
                target = u - stic
            else:
                target = u + stic
        xsp_new = target + (xsp - target) * q[Q_AV]
        xbar = 0.5 * (xsp + xsp_new)
        st[Z_XSP] = xsp_new
        fa = st[Z_FA]
        va = st[Z_VA]
        fsp = st[Z_FS]
        r0 = fa * (1.0 - 0.5 * h / tau) - 0.5 * h * kh * va + h * ffs * xbar / tau
        r1 = va * (1.0 - 0.5 * g * ca) + 0.5 * g * (fa - fsp)
        r2 = fsp + 0.5 * h * km * va
        p0 = q[Q_K + 0] * r0 + q[Q_K + 1] * r1 + q[Q_K + 2] * r2
        p1 = q[Q_K + 3] * r0 + q[Q_K + 4] * r1 + q[Q_K + 5] * r2
        p2 = q[Q_K + 6] * r0 + q[Q_K + 7] * r1 + q[Q_K + 8] * r2
        x_i = st[Z_X0] + st[Z_DELTA]
        if steady:
            base, a = friction_law(q, fp, fs, x_i, v_del if delayed else st[Z_VS])
            vs, mu = solve_slip_mass(p2, q[Q_QV + 2], ntot, base, vreg, q[Q_MIH], st[Z_VS])
        else:
            base, a = friction_law(q, fp, fs, x_i, 0.0)
            vs, mu = solve_slip(p2, q[Q_QV + 2], ntot, base, a, v0, vreg)
        va_new = p1 + q[Q_QV + 1] * vs
        st[Z_FA] = p0 + q[Q_QV + 0] * vs
        st[Z_FS] = p2 + q[Q_QV + 2] * vs
        st[Z_XA] += 0.5 * h * (va + va_new)
        st[Z_VA] = va_new
        st[Z_VS] = vs
        st[Z_MU] = mu
        st[Z_DELTA] += vs * h
        advance_state(fp, fs, vs, h)
        st[Z_XT] = st[Z_XA] - st[Z_FS] * q[Q_CTP]
    # end of tick: ring buffer, normal forces, sensor filters
    rpos = (rpos + 1) % nr
    ring[rpos] = st[Z_VS]
    st[Z_RPOS] = rpos
    n1, n2 = normal_forces(q, st[Z_XT])
    st[Z_N1] = n1
    st[Z_N2] = n2
    # first-order analog filters, exact for an input linear over the tick
    st[Z_LVF] = lowpass_tick(st[Z_LVF], x_old, st[Z_XT], q[Q_LV_A], q[Q_LV_G])
    f_in_old = f_old
    f_in = st[Z_FS]
    if q[Q_SL_ON] > 0.5:
        st[Z_SLF] = lowpass_tick(st[Z_SLF], f_old, f_in, q[Q_SL_A], q[Q_SL_G])
        f_in_old = slf_old
        f_in = st[Z_SLF]
    st[Z_FLF] = lowpass_tick(st[Z_FLF], f_in_old, f_in, q[Q_FL_A], q[Q_FL_G])
    st[Z_N1F] = lowpass_tick(st[Z_N1F], n1_old, n1, q[Q_NL_A], q[Q_NL_G])
    st[Z_N2F] = lowpass_tick(st[Z_N2F], n2_old, n2, q[Q_NL_A], q[Q_NL_G])
    st[Z_TICK] += 1.0


@kernel
def plant_sample(q, st, z0, z1, z2, z3):
    """Sensor readings at the current tick given four standard-normal draws.

    In the hardware's order (rig.model.sensors): white noise, held over the tick, enters each
    transducer's first-order analog filter with the signal (by linearity its filtered part is
    kept apart, ``Z_*E``; the reading's noise sigma is the profile's), then the ADC quantizes.
    Returns (position_um, friction_N, normal_1_N, normal_2_N)."""
    st[Z_LVE] = q[Q_LV_A] * st[Z_LVE] + q[Q_LV_SIG] * z0
    st[Z_FLE] = q[Q_FL_A] * st[Z_FLE] + q[Q_FL_SIG] * z1
    st[Z_N1E] = q[Q_NL_A] * st[Z_N1E] + q[Q_NL_SIG] * z2
    st[Z_N2E] = q[Q_NL_A] * st[Z_N2E] + q[Q_NL_SIG] * z3
    x = quantize(st[Z_LVF] + st[Z_LVE], q[Q_LV_Q], q[Q_LV_MIN], q[Q_LV_MAX])
    t = st[Z_TICK] * q[Q_DT]
    f = st[Z_FLF] + st[Z_FLE] + q[Q_DRIFT] * t
    n1 = st[Z_N1F] + st[Z_N1E]
    n2 = st[Z_N2F] + st[Z_N2E]
    return x, f, n1, n2


# rows of the closed-loop output array (order of the block-dict keys)
BLOCK_KEYS = ("t_s", "position_ref_um", "position_um", "friction_N", "normal_1_N", "normal_2_N", "valve_cmd",
              "pid_p", "pid_i", "pid_d", "dither", "true_position_um", "true_velocity_um_s", "true_mu", "spool")
N_OUT = len(BLOCK_KEYS)


@kernel(nogil=True)
def run_closed_loop(q, fp, fs, st, ring, c, cs, xref, ffref, i0, noise, j0, out, k0, count):
    """``count`` closed-loop ticks: sample sensors, controller (rig.control), advance plant.

    Reads ``xref[i0:]``, the feed-forward force ``ffref[i0:]`` (N; an empty array: none) and
    ``noise[j0:]`` (n x 4 standard normals), writes ``out[:, k0:]``
    (rows in the order of BLOCK_KEYS). Returns ``count``."""
    dt = q[Q_DT]
    for k in range(count):
        lv, fr, n1, n2 = plant_sample(q, st, noise[j0 + k, 0], noise[j0 + k, 1], noise[j0 + k, 2],
                                      noise[j0 + k, 3])
        xr = xref[i0 + k]
        ffn = ffref[i0 + k] if ffref.shape[0] > 0 else 0.0
        v, p, i, d, dz = controller_step_v(c, cs, xr, lv, math.nan, ffn)
        o = k0 + k
        out[0, o] = st[Z_TICK] * dt
        out[1, o] = xr
        out[2, o] = lv
        out[3, o] = fr
        out[4, o] = n1
        out[5, o] = n2
        out[6, o] = v
        out[7, o] = p
        out[8, o] = i
        out[9, o] = d
        out[10, o] = dz
        out[11, o] = st[Z_XT]
        out[12, o] = st[Z_VS]
        out[13, o] = st[Z_MU]
        out[14, o] = st[Z_XSP]
        plant_advance(q, fp, fs, st, ring, v)
    return count
