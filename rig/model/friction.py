"""Rate-and-state friction laws as small composable numba pieces (Dupont & Dunlap 1995, section 2.1).

Written with the friction coefficient of one interface of the double-shear fixture:

    mu = mu0 + A ln(v/V0) + theta                                   (eq. 5)
    dtheta/ddelta = -(theta + B ln(v/V0)) / L     (Ruina slip law, eq. 6)   :func:`slip_law`
    dtheta/dt = B (V0/L) exp(-theta/B) - B v / L  (Dieterich aging law)     :func:`aging_law`
    mu_ss(v) = mu0 + (A - B) ln(v/V0)                                (eq. 7)

with ``v`` in µm/s, slip ``delta`` in µm, ``L`` in µm, ``V0 = 1 µm/s``. A second state
variable (B2, L2) follows the slip law; :func:`periodic_term` (position-periodic friction,
at the interface's position) and :func:`wear_term` (slip wear drift) add to mu.

Sticking and ``v -> 0`` are handled by the regularised (arcsinh) form

    mu = A asinh( v / (2 V0) * exp((mu0 + theta) / A) )

which equals eq. (5) to within exp(-2 (mu0+theta)/A) while sliding, is odd in ``v`` and
finite at ``v = 0``, so stick-slip can be simulated with a solver implicit in ``v``. With
``A = 0`` (paraffin oil in Table 2) a smooth sign function of width ``v_reg_um_s`` takes
its place.

The kernels take the packed parameter vector ``p`` (indices ``P_*``, built by
:meth:`rig.model.spec.FrictionModel.to_array`) and the state vector ``s`` (``S_*``): the
packing stays inside this kernel boundary; everything outside uses the named params of
:class:`~rig.model.spec.FrictionModel`.
"""

from __future__ import annotations

import math

import numpy as np
from rig.jitstart import kernel

V0_UM_S = 1.0  # reference velocity V0 (µm/s), diagnosis.md and Table 2

# ---------------------------------------------------------------------------
# Packed parameter vector for the numba kernels
# ---------------------------------------------------------------------------
P_MU0 = 0        # mu0 (1)
P_A = 1          # A_mu (1): direct effect; for steady_state baseline, the slope c
P_B = 2          # B_mu (1); 0 for the steady_state baseline
P_L = 3          # L_um (µm)
P_V0 = 4         # V0 (µm/s)
P_B2 = 5         # B2_mu (1), second state variable (0 = absent)
P_L2 = 6         # L2_um (µm)
P_AGING = 7      # 1.0: Dieterich aging law in place of the Ruina slip law
P_AMP = 8        # amplitude_mu (1), position-periodic friction
P_WAVE = 9       # wavelength_um (µm)
P_PHASE = 10     # phase_rad (rad)
P_WEAR = 11      # rate_mu_per_mm (1/mm), slip wear drift
P_VREG = 12      # v_reg_um_s (µm/s), regularisation width when A = 0
P_STATE_ON = 13  # 1.0: a state variable exists (rate_state); 0.0: steady_state (mu = mu0 + c ln v/V0)
N_PARAMS = 14

# state vector: theta, theta2, accumulated slip (µm, always >= 0)
S_THETA = 0
S_THETA2 = 1
S_SLIP = 2
N_STATE = 3


@kernel
def mu_regularized(v_um_s, theta_total, mu0, a, v0, v_reg):
    """Friction coefficient for velocity ``v`` and total state, arcsinh form of eq. (5).

    Odd in ``v``; equals ``mu0 + theta + a ln(v/v0)`` while sliding.
    """
    base = mu0 + theta_total
    av = abs(v_um_s)
    sgn = 1.0 if v_um_s >= 0.0 else -1.0
    if a > 0.0:
        if av == 0.0:
            return 0.0
        lnz = math.log(av / (2.0 * v0)) + base / a
        if lnz > 30.0:
            return sgn * (base + a * math.log(av / v0))
        return sgn * a * math.asinh(math.exp(lnz))
    # A = 0: friction independent of speed; smooth sign over v_reg
    return base * v_um_s / math.sqrt(v_um_s * v_um_s + v_reg * v_reg)


@kernel
def dmu_dv(v_um_s, theta_total, mu0, a, v0, v_reg):
    """d mu / d v (s/µm) of :func:`mu_regularized`, for implicit solvers."""
    base = mu0 + theta_total
    av = abs(v_um_s)
    if a > 0.0:
        lnz = math.log(max(av, 1e-300) / (2.0 * v0)) + base / a
        if lnz > 30.0:
            return a / max(av, 1e-300)
        z = math.exp(lnz)
        # d/dv a asinh(k v) = a k / sqrt(1 + k^2 v^2), k = z / v
        k = math.exp(base / a) / (2.0 * v0)
        return a * k / math.sqrt(1.0 + z * z)
    return base * v_reg * v_reg / (v_um_s * v_um_s + v_reg * v_reg) ** 1.5


@kernel
def slip_law(theta, v_abs, dslip, b, l_um, v0):
    """Exact Ruina slip-law update of a state over slip ``dslip`` at constant speed (eq. 6)."""
    if b == 0.0 or dslip <= 0.0:
        return theta
    vv = max(v_abs, 1e-12)
    th_ss = -b * math.log(vv / v0)
    return th_ss + (theta - th_ss) * math.exp(-dslip / l_um)


@kernel
def aging_law(theta, v_abs, dt_s, b, l_um, v0):
    """Exact Dieterich aging-law update over ``dt`` at constant speed.

    dtheta/dt = B (V0/L) exp(-theta/B) - B v / L  (diagnosis.md, aging_law).
    With phi = exp(theta/B): dphi/dt = V0/L - v phi / L, linear in phi.
    """
    if b == 0.0 or dt_s <= 0.0:
        return theta
    phi = math.exp(theta / b)
    if v_abs * dt_s / l_um < 1e-9:
        phi = phi + v0 / l_um * dt_s
    else:
        phi_ss = v0 / v_abs
        phi = phi_ss + (phi - phi_ss) * math.exp(-v_abs * dt_s / l_um)
    return b * math.log(phi)


@kernel
def periodic_term(p, x_um):
    """Position-periodic friction (diagnosis.md ``position_periodic``), evaluated at the
    interface's position along the test piece ``x_um`` (the slip, not the LVDT reading, when
    the loading system is compliant): amplitude_mu sin(2 pi x / wavelength_um + phase_rad)."""
    if p[P_AMP] == 0.0:
        return 0.0
    return p[P_AMP] * math.sin(2.0 * math.pi * x_um / p[P_WAVE] + p[P_PHASE])


@kernel
def wear_term(p, s):
    """Slip wear drift (``slip_wear_drift``): rate_mu_per_mm times the accumulated slip (mm)."""
    if p[P_WEAR] == 0.0:
        return 0.0
    return p[P_WEAR] * s[S_SLIP] * 1e-3


@kernel
def theta_steady(p, v_um_s):
    """Steady-state theta (first state) at speed v: -B ln(v/V0)."""
    return -p[P_B] * math.log(max(abs(v_um_s), 1e-12) / p[P_V0])


@kernel
def init_state(p, s, v_um_s):
    """Put the state at steady state for sliding at ``v`` (slip accumulator untouched)."""
    vv = max(abs(v_um_s), 1e-12)
    s[S_THETA] = -p[P_B] * math.log(vv / p[P_V0]) if p[P_STATE_ON] > 0.5 else 0.0
    s[S_THETA2] = -p[P_B2] * math.log(vv / p[P_V0])


@kernel
def advance_state(p, s, v_um_s, dt_s):
    """Advance the state over ``dt`` at constant velocity ``v`` (exact for constant v)."""
    v_abs = abs(v_um_s)
    dslip = v_abs * dt_s
    if p[P_STATE_ON] > 0.5:
        if p[P_AGING] > 0.5:
            s[S_THETA] = aging_law(s[S_THETA], v_abs, dt_s, p[P_B], p[P_L], p[P_V0])
        else:
            s[S_THETA] = slip_law(s[S_THETA], v_abs, dslip, p[P_B], p[P_L], p[P_V0])
    if p[P_B2] != 0.0:
        s[S_THETA2] = slip_law(s[S_THETA2], v_abs, dslip, p[P_B2], p[P_L2], p[P_V0])
    s[S_SLIP] += dslip


@kernel
def mu_of(p, s, v_um_s, x_um):
    """Friction coefficient for the current state, velocity and position."""
    theta_total = s[S_THETA2]
    if p[P_STATE_ON] > 0.5:
        theta_total += s[S_THETA]
    if p[P_STATE_ON] < 0.5 and p[P_A] < 0.0:
        # steady_state baseline with a negative slope c (P_A): mu = mu0 + c ln(v/V0) (+ theta2),
        # the log argument held at v_reg near v = 0 and a smooth sign as in the A = 0 case
        av = max(abs(v_um_s), p[P_VREG])
        base = p[P_MU0] + theta_total + p[P_A] * math.log(av / p[P_V0])
        mu = base * v_um_s / math.sqrt(v_um_s * v_um_s + p[P_VREG] * p[P_VREG])
    else:
        mu = mu_regularized(v_um_s, theta_total, p[P_MU0], p[P_A], p[P_V0], p[P_VREG])
    extra = periodic_term(p, x_um) + wear_term(p, s)
    if v_um_s >= 0.0:
        return mu + extra
    return mu - extra


@kernel
def mu_step(p, s, v_um_s, dt_s, x_um):
    """Advance the state by ``dt`` at ``v`` and return mu at the end of the step."""
    advance_state(p, s, v_um_s, dt_s)
    return mu_of(p, s, v_um_s, x_um)


@kernel
def mu_series(p, t_s, v_um_s, x_um, v_init_um_s):
    """Friction coefficient along a whole record of kinematics (analysis forward model).

    The state starts at steady state for ``v_init`` and is integrated in slip
    between samples with the velocity of the interval's midpoint (exact
    per interval for piecewise-constant velocity, so uneven sampling and gaps
    are handled). Returns mu at every sample.
    """
    n = t_s.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    init_state(p, s, v_init_um_s)
    out[0] = mu_of(p, s, v_um_s[0], x_um[0])
    for i in range(1, n):
        dt = t_s[i] - t_s[i - 1]
        vm = 0.5 * (v_um_s[i] + v_um_s[i - 1])
        advance_state(p, s, vm, dt)
        out[i] = mu_of(p, s, v_um_s[i], x_um[i])
    return out


# ---------------------------------------------------------------------------
# Forward-mode sensitivities of mu_series (exact Jacobians for the fits)
# ---------------------------------------------------------------------------
# derivative columns of :func:`mu_series_sens` besides the P_* indices
D_V_INIT = N_PARAMS       # d/d v_init_um_s, the speed whose steady state the record starts in
D_PER_COS = N_PARAMS + 1  # d/d c of the periodic term written c cos(2 pi x / wavelength) + s sin(...)
D_PER_SIN = N_PARAMS + 2  # d/d s of the same (c = amplitude sin(phase), s = amplitude cos(phase))


@kernel
def mu_regularized_grad(v_um_s, theta_total, mu0, a, v0, v_reg):
    """(mu, d mu/d base, d mu/d a, d mu/d v) of :func:`mu_regularized`, base = mu0 + theta_total."""
    base = mu0 + theta_total
    av = abs(v_um_s)
    sgn = 1.0 if v_um_s >= 0.0 else -1.0
    if a > 0.0:
        if av == 0.0:
            return 0.0, 0.0, 0.0, a * math.exp(min(base / a, 700.0)) / (2.0 * v0)
        lnz = math.log(av / (2.0 * v0)) + base / a
        if lnz > 30.0:
            lv = math.log(av / v0)
            return sgn * (base + a * lv), sgn, sgn * lv, a / av
        z = math.exp(lnz)
        q = z / math.sqrt(1.0 + z * z)   # d asinh(z) / d ln z
        ash = math.asinh(z)
        return sgn * a * ash, sgn * q, sgn * (ash - base / a * q), a * q / av
    den = v_um_s * v_um_s + v_reg * v_reg
    r = v_um_s / math.sqrt(den)
    return base * r, r, 0.0, base * v_reg * v_reg / den ** 1.5


@kernel
def init_state_sens(p, v_init_um_s, dv_init, cols, dth, dth2):
    """The states' steady state at ``v_init_um_s`` (:func:`init_state`: theta = -B ln(v/V0), eq. 6)
    and their derivatives, written into ``dth`` and ``dth2`` (per column of ``cols``; D_V_INIT with
    ``dv_init`` the derivative of the starting speed itself). Returns (theta, theta2)."""
    on = p[P_STATE_ON] > 0.5
    b = p[P_B]
    b2 = p[P_B2]
    vi = max(abs(v_init_um_s), 1e-12)
    lvi = math.log(vi / p[P_V0])
    th = -b * lvi if on else 0.0
    th2 = -b2 * lvi
    dlvi = dv_init / v_init_um_s if abs(v_init_um_s) > 1e-12 else 0.0
    for j in range(cols.shape[0]):
        c = cols[j]
        if c == P_B and on:
            dth[j] = -lvi
        elif c == P_B2:
            dth2[j] = -lvi
        elif c == D_V_INIT:
            if on:
                dth[j] = -b * dlvi
            dth2[j] = -b2 * dlvi
    return th, th2


@kernel(inline="always")
def _slip_law_sens(dth, cols, e, lv, th, thss, dslip, l_um, col_b, col_l):
    """One interval of a slip-law state's sensitivities, in place: theta' = th_ss + (theta - th_ss) E
    (eq. 6, E = exp(-dslip / L), th_ss = -B ln(v/V0) = -B ``lv``) gives dtheta'/dq = E dtheta/dq
    + (1 - E) dth_ss/dq [q = B: ``col_b``] + (theta - th_ss) E dslip / L^2 [q = L: ``col_l``]."""
    for j in range(cols.shape[0]):
        c = cols[j]
        d = dth[j] * e
        if c == col_b:
            d += -lv * (1.0 - e)
        elif c == col_l:
            d += (th - thss) * e * dslip / (l_um * l_um)
        dth[j] = d


@kernel
def mu_series_sens(p, t_s, v_um_s, x_um, v_init_um_s, cols):
    """:func:`mu_series` (the same numbers) and its exact derivatives d mu / d p[cols[j]].

    Forward-mode sensitivities carried along the same integration: per interval the exact slip-law
    update theta' = th_ss + (theta - th_ss) E, E = exp(-dslip / L), th_ss = -B ln(v/V0) (eq. 6)
    gives dtheta'/dq = E dtheta/dq + (1 - E) dth_ss/dq + (theta - th_ss) E dslip / L^2 [q = L],
    and mu (eq. 5, arcsinh form, plus the periodic and wear terms) is differentiated at every
    sample. One call costs little more than one evaluation of the model, instead of one per
    parameter for finite differences. Slip law only (no aging law), state on (rate_state).

    ``cols``: P_MU0, P_A, P_B, P_L, P_B2, P_L2, P_WEAR, P_AMP, P_WAVE, P_PHASE, D_V_INIT,
    D_PER_COS, D_PER_SIN. Returns (mu, jac) with jac[i, j] = d mu_i / d p[cols[j]].
    """
    n = t_s.shape[0]
    m = cols.shape[0]
    out = np.empty(n)
    jac = np.zeros((n, m))
    on = p[P_STATE_ON] > 0.5
    b = p[P_B]
    l_um = p[P_L]
    b2 = p[P_B2]
    l2 = p[P_L2]
    v0 = p[P_V0]
    amp = p[P_AMP]
    wave = p[P_WAVE]
    phase = p[P_PHASE]
    wear = p[P_WEAR]
    # initial steady state (init_state)
    dth = np.zeros(m)
    dth2 = np.zeros(m)
    th, th2 = init_state_sens(p, v_init_um_s, 1.0, cols, dth, dth2)
    slip = 0.0
    for i in range(n):
        if i > 0:
            dt = t_s[i] - t_s[i - 1]
            vm = 0.5 * (v_um_s[i] + v_um_s[i - 1])
            va = abs(vm)
            dslip = va * dt
            if dslip > 0.0:
                lv = math.log(max(va, 1e-12) / v0)
                if on:
                    e = math.exp(-dslip / l_um)
                    thss = -b * lv
                    _slip_law_sens(dth, cols, e, lv, th, thss, dslip, l_um, P_B, P_L)
                    if b != 0.0:
                        th = thss + (th - thss) * math.exp(-dslip / l_um)
                if b2 != 0.0:
                    e2 = math.exp(-dslip / l2)
                    thss2 = -b2 * lv
                    _slip_law_sens(dth2, cols, e2, lv, th2, thss2, dslip, l2, P_B2, P_L2)
                    th2 = thss2 + (th2 - thss2) * math.exp(-dslip / l2)
            slip += dslip
        v = v_um_s[i]
        x = x_um[i]
        tt = th2
        if on:
            tt += th
        mu, gb, ga, _ = mu_regularized_grad(v, tt, p[P_MU0], p[P_A], v0, p[P_VREG])
        sg = 1.0 if v >= 0.0 else -1.0
        per = 0.0
        arg = 0.0
        if amp != 0.0:
            arg = 2.0 * math.pi * x / wave + phase
            per = amp * math.sin(arg)
        wr = 0.0
        if wear != 0.0:
            wr = wear * slip * 1e-3
        extra = per + wr
        out[i] = mu + extra if v >= 0.0 else mu - extra
        for j in range(m):
            c = cols[j]
            d = gb * (dth2[j] + dth[j]) if on else gb * dth2[j]
            if c == P_MU0:
                d += gb
            elif c == P_A:
                d += ga
            elif c == P_WEAR:
                d += sg * slip * 1e-3
            elif c == P_AMP:
                d += sg * math.sin(2.0 * math.pi * x / wave + phase)
            elif c == P_PHASE:
                d += sg * amp * math.cos(2.0 * math.pi * x / wave + phase)
            elif c == P_WAVE:
                d += -sg * amp * math.cos(2.0 * math.pi * x / wave + phase) * 2.0 * math.pi * x / (wave * wave)
            elif c == D_PER_COS:
                d += sg * math.cos(2.0 * math.pi * x / wave)
            elif c == D_PER_SIN:
                d += sg * math.sin(2.0 * math.pi * x / wave)
            jac[i, j] = d
    return out, jac
