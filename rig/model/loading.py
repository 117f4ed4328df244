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

In the simulated rig the same stiffness is the series compliance between the LVDT point and
the interface; :func:`lvdt_to_interface_compliance_um_per_N` says which compliance that is:
a model with ``finite_stiffness`` REPLACES the profile's fixture compliance (the diagnosis
measured all of it), it does not add to it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rig.model.friction import N_STATE, advance_state, init_state, mu_of


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


@njit(cache=True)
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
            if g > 0.0:
                hi = u
            else:
                lo = u
            du = 1e-6
            vv2 = VS * math.sinh(u + du)
            for q in range(N_STATE):
                s2[q] = s[q]
            advance_state(p, s2, vv2, dt)
            g2 = mu_of(p, s2, vv2, xi + vv2 * dt) * nfac[i] + k * vv2 * dt - rhs
            dg = (g2 - g) / du
            un = u - g / dg if dg > 0.0 else 0.5 * (lo + hi)
            if not (un > lo and un < hi):
                un = 0.5 * (lo + hi)
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
