"""The loading system: the stiffness between where position is measured and the interface.

The interface slips ``delta != x`` when the path from the position sensor (the LVDT at
the test piece, or a load point) to the sliding surfaces is compliant: quasi-statically
(massless interface), ``k (x - delta) = F`` with ``F = mu N`` the friction force.
:func:`stiff_series` integrates that along a kinematic record: per interval the interface
velocity is the root of ``mu(v, state advanced at v) N - (F_prev + k (dx - v dt)) = 0``
(monotone in ``v``: the direct effect A and the spring both grow with ``v``), found by a
safeguarded Newton iteration on ``asinh(v / VS)`` (signed: stops and returns); the state
is integrated in the interface's slip and position-periodic friction is evaluated at the
interface's position.

:func:`stiff_series_sens` is the same balance for a state with the slip law (what the
forward model uses for it), with the Newton derivative in closed form and the exact
derivatives of the force with respect to every parameter (implicit function theorem per
interval): the diagnosis fits' Jacobians. :func:`stiff_series` serves the aging law and
the steady_state baseline; the two agree to the solver's tolerance.

In the simulated rig the same stiffness is the series compliance between the LVDT point and
the interface; :func:`lvdt_to_interface_compliance_um_per_N` says which compliance that is:
a model with ``finite_stiffness`` REPLACES the profile's fixture compliance (the diagnosis
measured all of it), it does not add to it.
"""

from __future__ import annotations

import math

import numpy as np
from rig.jitstart import kernel

from rig.model.friction import (D_PER_COS, D_PER_SIN, D_V_INIT, N_STATE, P_A, P_AMP, P_B, P_B2, P_L, P_L2, P_MU0,
                                P_PHASE, P_STATE_ON, P_V0, P_VREG, P_WAVE, P_WEAR, advance_state, init_state, init_state_sens,
                                mu_of, mu_regularized_grad)


def lvdt_to_interface_compliance_um_per_N(fixture_compliance_um_per_N: float,
                                          stiffness_N_per_um: float | None) -> float:
    """Compliance (µm/N) between the LVDT point and the interface's slip: the model's
    ``finite_stiffness`` (N/µm) when it has one, else the rig's own fixture compliance."""
    if stiffness_N_per_um is None:
        return float(fixture_compliance_um_per_N)
    if not stiffness_N_per_um > 0:
        raise ValueError("finite_stiffness needs stiffness_kN_per_m > 0")
    return 1.0 / float(stiffness_N_per_um)


VS = 1e-3  # µm/s, scale of the signed velocity variable of the stiffness solver


@kernel(inline="always")
def _bracketed_newton(u, g, dg, lo, hi):
    """One step of the spring balance's root finder on an increasing g(u) (the root is unique): the
    bracket (lo, hi) shrunk by the sign of g(u), then the next u, a Newton step inside it, else
    bisection (the slope ``dg`` not positive, or the step leaving the bracket). Returns (u, lo, hi)."""
    if g > 0.0:
        hi = u
    else:
        lo = u
    un = u - g / dg if dg > 0.0 else 0.5 * (lo + hi)
    if not (un > lo and un < hi):
        un = 0.5 * (lo + hi)
    return un, lo, hi


@kernel
def stiff_series(p, t, x, v, nfac, k, v_init):
    """Friction force with a spring ``k`` (N/µm) between the LVDT position ``x`` and the interface."""
    n = t.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    s2 = np.zeros(N_STATE)
    v0 = v_init if abs(v_init) > 1e-6 else 1e-6
    init_state(p, s, v0)
    # the interface sits where the spring's stretch F / k puts it: x - F / k (the same point
    # the simulated rig evaluates position-periodic friction at)
    F = mu_of(p, s, v0, x[0]) * nfac[0]
    xi = x[0] - F / k
    F = mu_of(p, s, v0, xi) * nfac[0]
    xi = x[0] - F / k
    out[0] = F
    vprev = v0
    for i in range(1, n):
        dt = t[i] - t[i - 1]
        dx = x[i] - x[i - 1]
        # root of g(u) = mu(v) N + k v dt - (F + k dx), v = VS sinh(u) (signed: stops and returns)
        rhs = F + k * dx
        lo = -20.0
        hi = 20.0
        u = math.asinh(vprev / VS)
        g = 0.0
        for it in range(60):
            vv = VS * math.sinh(u)
            for q in range(N_STATE):
                s2[q] = s[q]
            advance_state(p, s2, vv, dt)
            g = mu_of(p, s2, vv, xi + vv * dt) * nfac[i] + k * vv * dt - rhs
            if abs(g) < 1e-12 * (1.0 + abs(rhs)):
                break
            du = 1e-6
            vv2 = VS * math.sinh(u + du)
            for q in range(N_STATE):
                s2[q] = s[q]
            advance_state(p, s2, vv2, dt)
            g2 = mu_of(p, s2, vv2, xi + vv2 * dt) * nfac[i] + k * vv2 * dt - rhs
            dg = (g2 - g) / du
            un, lo, hi = _bracketed_newton(u, g, dg, lo, hi)
            if hi - lo < 1e-13:
                break
            u = un
        vv = VS * math.sinh(u)
        advance_state(p, s, vv, dt)
        xi += vv * dt
        F = mu_of(p, s, vv, xi) * nfac[i]
        out[i] = F
        vprev = vv
    return out


# derivative column of stiff_series_sens for the stiffness k (N/µm), besides friction's P_* / D_*
D_STIFF = D_PER_SIN + 1


@kernel
def _spring_step(p, on, th, th2, slip, xi, vv, dt, nf, k):
    """The interval's spring balance at interface velocity ``vv`` from state (th, th2, slip, xi):
    returns g = mu(vv, state advanced at vv, x_i + vv dt) N + k vv dt, dg/dvv, and the pieces the
    sensitivities reuse (new states, E = exp(-dslip/L), E2, ln(v/V0), d theta'/d vv, d theta2'/d vv,
    d mu/d base, d mu/d A, mu with the periodic and wear terms)."""
    b = p[P_B]
    l_um = p[P_L]
    b2 = p[P_B2]
    l2 = p[P_L2]
    v0 = p[P_V0]
    va = abs(vv)
    sv = 1.0 if vv >= 0.0 else -1.0
    dslip = va * dt
    thn = th
    th2n = th2
    dthv = 0.0
    dth2v = 0.0
    e = 1.0
    e2 = 1.0
    lv = 0.0
    if dslip > 0.0:
        lv = math.log(max(va, 1e-12) / v0)
        dlv = 1.0 / vv if va > 1e-12 else 0.0
        if on:
            e = math.exp(-dslip / l_um)
            if b != 0.0:
                thss = -b * lv
                thn = thss + (th - thss) * math.exp(-dslip / l_um)
                dthv = -b * dlv * (1.0 - e) - (th - thss) * e * sv * dt / l_um
        if b2 != 0.0:
            e2 = math.exp(-dslip / l2)
            thss2 = -b2 * lv
            th2n = thss2 + (th2 - thss2) * math.exp(-dslip / l2)
            dth2v = -b2 * dlv * (1.0 - e2) - (th2 - thss2) * e2 * sv * dt / l2
    xn = xi + vv * dt
    tt = th2n
    if on:
        tt += thn
    mu, gb, ga, gv = mu_regularized_grad(vv, tt, p[P_MU0], p[P_A], v0, p[P_VREG])
    amp = p[P_AMP]
    per = 0.0
    dper = 0.0
    if amp != 0.0:
        arg = 2.0 * math.pi * xn / p[P_WAVE] + p[P_PHASE]
        per = amp * math.sin(arg)
        dper = amp * math.cos(arg) * 2.0 * math.pi / p[P_WAVE] * dt
    wr = 0.0
    if p[P_WEAR] != 0.0:
        wr = p[P_WEAR] * (slip + dslip) * 1e-3
    extra = per + wr
    mut = mu + extra if vv >= 0.0 else mu - extra
    dmudv = gv + gb * (dth2v + dthv) + sv * dper + p[P_WEAR] * 1e-3 * dt
    return (mut * nf + k * vv * dt, dmudv * nf + k * dt, thn, th2n, e, e2, lv, dthv, dth2v, gb, ga, mut)


@kernel
def _dmu_dq(p, cols, on, gb, ga, sg, xn, slip_tot, dth, dth2, dxn, dsl, out):
    """d mu / d p[cols[j]] at the interface position ``xn`` given the states' sensitivities (dth,
    dth2), the position's (dxn) and the accumulated slip's (dsl), into ``out``."""
    amp = p[P_AMP]
    wave = p[P_WAVE]
    wear = p[P_WEAR]
    sa = 0.0
    ca = 0.0
    if amp != 0.0 or cols.shape[0] > 0:
        if wave > 0.0:
            arg = 2.0 * math.pi * xn / wave + p[P_PHASE]
            sa = math.sin(arg)
            ca = math.cos(arg)
    for j in range(cols.shape[0]):
        c = cols[j]
        d = gb * (dth2[j] + dth[j]) if on else gb * dth2[j]
        if c == P_MU0:
            d += gb
        elif c == P_A:
            d += ga
        if amp != 0.0:
            d += sg * amp * ca * 2.0 * math.pi / wave * dxn[j]
        if wear != 0.0:
            d += sg * wear * 1e-3 * dsl[j]
        if c == P_WEAR:
            d += sg * slip_tot * 1e-3
        elif c == P_AMP:
            d += sg * sa
        elif c == P_PHASE:
            d += sg * amp * ca
        elif c == P_WAVE:
            d += -sg * amp * ca * 2.0 * math.pi * xn / (wave * wave)
        elif c == D_PER_COS:
            d += sg * math.cos(2.0 * math.pi * xn / wave)
        elif c == D_PER_SIN:
            d += sg * math.sin(2.0 * math.pi * xn / wave)
        out[j] = d


@kernel
def stiff_series_sens(p, t, x, v, nfac, k, v_init, cols):
    """:func:`stiff_series` for the slip law with a state (no aging law), and the exact derivatives
    dF_i / d p[cols[j]] (friction's P_* and D_* columns, D_STIFF for k in N/µm).

    The same spring balance per interval, solved by the same safeguarded Newton iteration with
    its derivative in closed form (the result agrees with :func:`stiff_series` to the solver's
    tolerance, 1e-12 relative). Sensitivities by the implicit function theorem: g(v; q) = 0 gives
    dv/dq = -(dg/dq) / (dg/dv), with the states, the interface position, the accumulated slip and
    the force carried forward; F_i = F_{i-1} + k (dx - v dt) makes dF_i/dq = dF_{i-1}/dq
    - k dt dv/dq (+ dx - v dt for k). Returns (F, jac)."""
    n = t.shape[0]
    m = cols.shape[0]
    out = np.empty(n)
    jac = np.zeros((n, m))
    on = p[P_STATE_ON] > 0.5
    b = p[P_B]
    b2 = p[P_B2]
    v0p = p[P_V0]
    dth = np.zeros(m)
    dth2 = np.zeros(m)
    dxi = np.zeros(m)
    dsl = np.zeros(m)
    dF = np.zeros(m)
    dmu = np.zeros(m)
    dthq = np.zeros(m)
    dth2q = np.zeros(m)
    v0 = v_init if abs(v_init) > 1e-6 else 1e-6
    dv0 = 1.0 if abs(v_init) > 1e-6 else 0.0
    th, th2 = init_state_sens(p, v0, dv0, cols, dth, dth2)
    # the interface sits where the spring's stretch F / k puts it (two passes, as stiff_series)
    xi = x[0]
    F = 0.0
    for rep in range(2):
        tt = th2 + th if on else th2
        mu, gb, ga, gv = mu_regularized_grad(v0, tt, p[P_MU0], p[P_A], v0p, p[P_VREG])
        extra = 0.0
        if p[P_AMP] != 0.0:
            extra = p[P_AMP] * math.sin(2.0 * math.pi * xi / p[P_WAVE] + p[P_PHASE])
        F = (mu + extra if v0 >= 0.0 else mu - extra) * nfac[0]
        sg = 1.0 if v0 >= 0.0 else -1.0
        _dmu_dq(p, cols, on, gb, ga, sg, xi, 0.0, dth, dth2, dxi, dsl, dmu)
        for j in range(m):
            dF[j] = dmu[j] * nfac[0]
            if cols[j] == D_V_INIT:
                dF[j] += gv * dv0 * nfac[0]
            dxi[j] = -dF[j] / k + (F / (k * k) if cols[j] == D_STIFF else 0.0)
        xi = x[0] - F / k
    out[0] = F
    for j in range(m):
        jac[0, j] = dF[j]
    vprev = v0
    slip = 0.0
    for i in range(1, n):
        dt = t[i] - t[i - 1]
        dx = x[i] - x[i - 1]
        nf = nfac[i]
        rhs = F + k * dx
        lo = -20.0
        hi = 20.0
        u = math.asinh(vprev / VS)
        vv = VS * math.sinh(u)
        r = _spring_step(p, on, th, th2, slip, xi, vv, dt, nf, k)
        for it in range(60):
            g = r[0] - rhs
            if abs(g) < 1e-12 * (1.0 + abs(rhs)):
                break
            dg = r[1] * VS * math.cosh(u)
            un, lo, hi = _bracketed_newton(u, g, dg, lo, hi)
            if hi - lo < 1e-13:
                break
            u = un
            vv = VS * math.sinh(u)
            r = _spring_step(p, on, th, th2, slip, xi, vv, dt, nf, k)
        # r is the balance at the final u (the last evaluation): no recomputation
        dgdv = r[1]
        thn, th2n, e, e2, lv, dthv, dth2v, gb, ga, mut = r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11]
        dslip = abs(vv) * dt
        xn = xi + vv * dt
        if m > 0:
            sv = 1.0 if vv >= 0.0 else -1.0
            thss = -b * lv
            thss2 = -b2 * lv
            l_um = p[P_L]
            l2 = p[P_L2]
            for j in range(m):
                c = cols[j]
                d1 = dth[j] * e
                if c == P_B:
                    d1 += -lv * (1.0 - e)
                elif c == P_L:
                    d1 += (th - thss) * e * dslip / (l_um * l_um)
                dthq[j] = d1 if on else 0.0
                d2 = dth2[j]
                if b2 != 0.0:
                    d2 = d2 * e2
                    if c == P_B2:
                        d2 += -lv * (1.0 - e2)
                    elif c == P_L2:
                        d2 += (th2 - thss2) * e2 * dslip / (l2 * l2)
                dth2q[j] = d2
            _dmu_dq(p, cols, on, gb, ga, sv, xn, slip + dslip, dthq, dth2q, dxi, dsl, dmu)
            for j in range(m):
                isk = cols[j] == D_STIFF
                G = dmu[j] * nf - dF[j] + ((vv * dt - dx) if isk else 0.0)
                dvv = -G / dgdv if dgdv != 0.0 else 0.0
                dth[j] = dthq[j] + dthv * dvv
                dth2[j] = dth2q[j] + dth2v * dvv
                dxi[j] = dxi[j] + dt * dvv
                dsl[j] = dsl[j] + sv * dt * dvv
                dF[j] = dF[j] - k * dt * dvv + ((dx - vv * dt) if isk else 0.0)
                jac[i, j] = dF[j]
        th = thn
        th2 = th2n
        slip += dslip
        xi = xn
        F = mut * nf
        out[i] = F
        vprev = vv
    return out, jac
