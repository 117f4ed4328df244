"""Forward models of the measured friction force for a baseline plus catalogue extensions.

Everything that acts on the friction law itself comes from the shared kernels
of :mod:`rig.friction` (``mu_series``, ``advance_state``, ``mu_of`` on the
packed vector of :meth:`FrictionModel.to_array`): the rate-and-state law
(eqs. 5-6), the second state variable, the aging law, slip wear drift and
position-periodic friction. The sensor- and fixture-side extensions are
applied here, as diagnosis.md says, when ``mu`` is turned into a measured force:

* ``time_delay`` (Hess & Soom): ``mu(t) = mu_ss(v(t - delay_s))``;
* ``finite_stiffness``: the interface slips ``delta != x`` with
  ``k (x - delta) = F`` (quasi-static). Per interval the interface velocity is
  the root of ``mu(v, state advanced at v) * N - (F_prev + k (dx - v dt)) = 0``
  (monotone in ``v``: the direct effect A and the spring both grow with
  ``v``), found by a safeguarded Newton iteration on ``ln v``; the state is
  integrated in the interface's slip;
* ``normal_force_variation``: ``F = mu (N1 + N2)`` instead of ``mu 2 N_nom``;
* ``sensor_lag``: first-order low-pass, ``tau dF_meas/dt = F - F_meas``
  (:func:`rig.friction.lowpass_uneven`);
* ``force_offset_drift``: ``F_meas = F + d t``, ``t`` from the file's start.

Parameter names and units are the catalogue's; ``mu0``, ``A_mu``, ``B_mu``,
``L_um`` (rate_state) or ``mu0``, ``c_mu`` (steady_state), and ``phase_rad``
for the periodic term.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rig.friction import (
    N_STATE,
    P_A,
    P_B,
    P_MU0,
    P_STATE_ON,
    P_V0,
    FrictionModel,
    advance_state,
    init_state,
    lowpass_uneven,
    mu_of,
    mu_series,
)

CATALOGUE = (
    "frictional_memory", "time_delay", "second_state_variable", "aging_law", "sensor_lag",
    "normal_force_variation", "slip_wear_drift", "force_offset_drift", "position_periodic",
    "finite_stiffness",
)

# the parameters each extension adds (catalogue names/units); frictional_memory replaces c_mu
EXT_PARAMS = {
    "frictional_memory": ("A_mu", "B_mu", "L_um"),
    "time_delay": ("delay_s",),
    "second_state_variable": ("B2_mu", "L2_um"),
    "aging_law": ("L_um",),
    "sensor_lag": ("tau_s",),
    "normal_force_variation": (),
    "slip_wear_drift": ("rate_mu_per_mm",),
    "force_offset_drift": ("rate_N_per_s",),
    "position_periodic": ("amplitude_mu", "wavelength_um"),
    "finite_stiffness": ("stiffness_kN_per_m",),
}

BASE_PARAMS = {"rate_state": ("mu0", "A_mu", "B_mu", "L_um"), "steady_state": ("mu0", "c_mu")}


def model_params(baseline: str, extensions: list[str]) -> list[str]:
    """Every fitted parameter name of a model (order: baseline, then extensions)."""
    names: list[str] = []
    if baseline == "steady_state" and "frictional_memory" in extensions:
        names += ["mu0", "A_mu", "B_mu", "L_um"]
    else:
        names += list(BASE_PARAMS[baseline])
    for e in extensions:
        for p in EXT_PARAMS[e]:
            if p not in names:
                names.append(p)
        if e == "position_periodic":
            names.append("phase_rad")
    return names


@njit(cache=True)
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


VS = 1e-3  # µm/s, scale of the signed velocity variable of the stiffness solver


@njit(cache=True)
def _stiff_series(p, t, x, v, nfac, k, v_init):
    """Friction force with a spring ``k`` (N/µm) between the LVDT position ``x`` and the interface."""
    n = t.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    s2 = np.zeros(N_STATE)
    v0 = v_init if abs(v_init) > 1e-6 else 1e-6
    init_state(p, s, v0)
    xi = x[0]
    F = mu_of(p, s, v0, xi) * nfac[0]
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


@njit(cache=True)
def _steady_delayed(p, v, x, slip):
    """mu_ss(v) for the steady_state baseline (state off) with periodic/wear terms via mu_of."""
    n = v.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    for i in range(n):
        s[2] = slip[i]
        out[i] = mu_of(p, s, v[i], x[i])
    return out


def to_friction_model(baseline: str, extensions: list[str], params: dict[str, float]) -> FrictionModel:
    """The shared :class:`FrictionModel` for a diagnosed model (what ``--model-out`` writes)."""
    return FrictionModel(baseline=baseline, extensions=list(extensions),
                         params={k: float(v) for k, v in params.items()})


def predict_force(baseline: str, extensions: list[str], params: dict[str, float], t: np.ndarray,
                  x: np.ndarray, v: np.ndarray, N_tot: np.ndarray, N_nom: float,
                  v_init: float | None = None) -> np.ndarray:
    """Predicted measured friction force (N) on a grid of (t from the file start, x, v, N1+N2)."""
    fm = to_friction_model(baseline, extensions, params)
    p = fm.to_array()
    t = np.ascontiguousarray(t, dtype=float)
    x = np.ascontiguousarray(x, dtype=float)
    v = np.ascontiguousarray(v, dtype=float)
    if "normal_force_variation" in extensions:
        nfac = np.ascontiguousarray(N_tot, dtype=float)
    else:
        nfac = np.full(t.shape, 2.0 * N_nom)
    v_eff = v
    if "time_delay" in extensions:
        d = float(params.get("delay_s", 0.0))
        if d > 0:
            v_eff = _interp_delay(t, v, d)
    if v_init is None and "v_init_um_s" in params:
        v_init = float(params["v_init_um_s"])
    if v_init is None:
        v_init = float(np.median(v_eff[: max(3, min(50, v_eff.size))]))
    if "finite_stiffness" in extensions:
        k = float(params["stiffness_kN_per_m"]) * 1e-3  # N/µm
        F = _stiff_series(p, t, x, v_eff, nfac, k, v_init)
    elif p[P_STATE_ON] > 0.5 or p[5] != 0.0:
        mu = mu_series(p, t, v_eff, x, v_init)
        F = mu * nfac
    else:
        slip = np.zeros_like(t)
        slip[1:] = np.cumsum(0.5 * np.abs(v_eff[1:] + v_eff[:-1]) * np.diff(t))
        F = _steady_delayed(p, np.maximum(v_eff, 1e-6) if np.all(v_eff > -1e-9) else v_eff, x, slip) * nfac
    if "sensor_lag" in extensions:
        F = lowpass_uneven(t, F, float(params["tau_s"]))
    if "force_offset_drift" in extensions:
        F = F + float(params["rate_N_per_s"]) * t
    return F


__all__ = ["CATALOGUE", "EXT_PARAMS", "model_params", "predict_force", "to_friction_model", "P_A", "P_B",
           "P_MU0", "P_V0"]
