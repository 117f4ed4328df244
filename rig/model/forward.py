"""The one forward model: a kinematic record (t, x measured, v) -> the force the load cell reports.

    friction law (rig.model.friction) -> loading system (rig.model.loading)
        -> sensor chain (rig.model.sensors)

driven by a :class:`~rig.model.spec.FrictionModel`. Identification's whole-record fit,
every diagnosis candidate and the synthetic-record generator call :func:`predict_force`;
the simulated rig's closed-loop kernel (rig.sim.plant) calls the same friction-law and
sensor kernels tick by tick, with the loading system's compliance chosen by
:func:`rig.model.loading.lvdt_to_interface_compliance_um_per_N`.

:func:`force_sensitivities` gives the same force and its exact derivatives with respect to the
parameters (forward-mode sensitivities along the same integration), for the fits' Jacobians.

Without ``finite_stiffness`` the interface slips with the measured position (diagnosis.md);
with it, the interface's slip follows from the spring (:func:`rig.model.loading.stiff_series`)
and position-periodic friction is evaluated at the interface's position.
"""

from __future__ import annotations

import numpy as np
from rig.jitstart import kernel

from rig.model import sensors
from rig.model import friction as fr
from rig.model.friction import N_STATE, P_B2, P_STATE_ON, mu_of, mu_series
from rig.model.loading import D_STIFF, stiff_series, stiff_series_sens
from rig.model.spec import FrictionModel


def slip_increments_um(t_s: np.ndarray, v_um_s: np.ndarray) -> np.ndarray:
    """The slip (µm) of each interval between samples: the trapezoidal integral of the speed |v|
    point by point, so an interval with a reversal adds the distance slid both ways. The one slip
    integral: :func:`cumulative_slip_um`, the forward model's memoryless laws, the diagnosis's
    trends in slip and its state-length limit (the record's total, ``np.sum`` of these) use it."""
    t = np.asarray(t_s, dtype=float)
    speed = np.abs(np.asarray(v_um_s, dtype=float))
    return 0.5 * (speed[1:] + speed[:-1]) * np.diff(t)


def cumulative_slip_um(t_s: np.ndarray, v_um_s: np.ndarray) -> np.ndarray:
    """Accumulated slip distance (µm) at every sample, from 0 (:func:`slip_increments_um`)."""
    out = np.zeros(np.shape(t_s))
    out[1:] = np.cumsum(slip_increments_um(t_s, v_um_s))
    return out


@kernel
def _memoryless_series(p, v, x, slip):
    """mu_ss(v) of a memoryless (steady_state) law with the periodic/wear terms via mu_of."""
    n = v.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    for i in range(n):
        s[2] = slip[i]
        out[i] = mu_of(p, s, v[i], x[i])
    return out


def as_model(baseline: str, extensions: list[str], params: dict[str, float]) -> FrictionModel:
    """The :class:`FrictionModel` of a baseline, extensions and named params (nuisance
    parameters such as ``v_init_um_s`` are not part of the model and are dropped)."""
    return FrictionModel(baseline=baseline, extensions=list(extensions),
                         params={k: float(v) for k, v in params.items() if k != "v_init_um_s"})


def _inputs(model: FrictionModel, t_s, x_um, v_um_s, N_tot_N, N_nom_N: float, v_init_um_s: float | None):
    """What the force and its sensitivities start from: the parameter array, the record as
    contiguous float arrays, the normal-force factor, the (delayed) velocity the friction sees and
    the speed of the starting steady state (default: the median of the first velocities)."""
    ext = model.extensions
    p = model.to_array()
    t = np.ascontiguousarray(t_s, dtype=float)
    x = np.ascontiguousarray(x_um, dtype=float)
    v = np.ascontiguousarray(v_um_s, dtype=float)
    nfac = sensors.normal_factor(t.size, N_tot_N, N_nom_N, "normal_force_variation" in ext)
    v_eff = v
    if "time_delay" in ext:
        v_eff = sensors.delayed(t, v, model.get("delay_s"))
    if v_init_um_s is None:
        v_init_um_s = float(np.median(v_eff[: max(3, min(50, v_eff.size))]))
    return p, t, x, v, nfac, v_eff, v_init_um_s


def predict_force(model: FrictionModel, t_s: np.ndarray, x_um: np.ndarray, v_um_s: np.ndarray,
                  N_tot_N: np.ndarray | None, N_nom_N: float, v_init_um_s: float | None = None) -> np.ndarray:
    """Measured friction force (N) on a record (t from the file start, x measured, v, N1+N2).

    ``v_init_um_s``: the speed whose steady state the record starts in (default: the median
    of the first velocities)."""
    ext = model.extensions
    p, t, x, v, nfac, v_eff, v_init_um_s = _inputs(model, t_s, x_um, v_um_s, N_tot_N, N_nom_N, v_init_um_s)
    k = model.stiffness_N_per_um
    if k is not None and _slip_law(model.baseline, ext):
        # the same spring balance with its Newton derivative in closed form (1.5x faster)
        F, _ = stiff_series_sens(p, t, x, v_eff, nfac, k, float(v_init_um_s), _NO_COLS)
    elif k is not None:
        F = stiff_series(p, t, x, v_eff, nfac, k, float(v_init_um_s))
    elif p[P_STATE_ON] > 0.5 or p[P_B2] != 0.0:
        F = mu_series(p, t, v_eff, x, float(v_init_um_s)) * nfac
    else:
        slip = cumulative_slip_um(t, v_eff)
        F = _memoryless_series(p, np.maximum(v_eff, 1e-6) if np.all(v_eff > -1e-9) else v_eff, x, slip) * nfac
    if "sensor_lag" in ext:
        F = sensors.lowpass_uneven(t, F, model.get("tau_s"))
    if "force_offset_drift" in ext:
        F = F + sensors.offset_drift(t, model.get("rate_N_per_s"))
    return F


# the parameters whose exact derivatives :func:`force_sensitivities` gives (rigid slip-law path),
# mapped to the friction kernel's columns; ``periodic_cos_mu`` / ``periodic_sin_mu`` are the
# periodic term written c cos(2 pi x / wavelength) + s sin(2 pi x / wavelength)
_SENS_COLS = {"mu0": fr.P_MU0, "A_mu": fr.P_A, "B_mu": fr.P_B, "L_um": fr.P_L, "B2_mu": fr.P_B2, "L2_um": fr.P_L2,
              "rate_mu_per_mm": fr.P_WEAR, "amplitude_mu": fr.P_AMP, "wavelength_um": fr.P_WAVE,
              "phase_rad": fr.P_PHASE, "v_init_um_s": fr.D_V_INIT, "periodic_cos_mu": fr.D_PER_COS,
              "periodic_sin_mu": fr.D_PER_SIN}


_NO_COLS = np.zeros(0, dtype=np.int64)


def _slip_law(baseline: str, extensions: list[str]) -> bool:
    """A state variable with the Ruina slip law (what the sensitivity kernels differentiate)."""
    return (baseline == "rate_state" or "frictional_memory" in extensions) and "aging_law" not in extensions


def has_sensitivities(baseline: str, extensions: list[str]) -> bool:
    """True when :func:`force_sensitivities` applies: a state variable with the slip law, rigid or
    with ``finite_stiffness`` (the aging law and the steady_state baseline are differentiated
    numerically)."""
    return _slip_law(baseline, extensions)


def force_sensitivities(model: FrictionModel, t_s: np.ndarray, x_um: np.ndarray, v_um_s: np.ndarray,
                        N_tot_N: np.ndarray | None, N_nom_N: float, names: list[str],
                        v_init_um_s: float | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`predict_force` (the same numbers) and exact dF/d(name) (N per unit of the parameter)
    for those of ``names`` it can differentiate along the integration
    (:func:`rig.model.friction.mu_series_sens`, with a spring :func:`rig.model.loading.stiff_series_sens`;
    the sensor chain is linear in F, ``tau_s`` by a central difference of the low-pass alone).
    Names it cannot give (``delay_s``) are absent: the caller differentiates them numerically.
    Needs :func:`has_sensitivities`."""
    ext = model.extensions
    if not has_sensitivities(model.baseline, ext):
        raise ValueError("force_sensitivities: the model has no analytic sensitivities (aging law or no state)")
    p, t, x, v, nfac, v_eff, v_init_um_s = _inputs(model, t_s, x_um, v_um_s, N_tot_N, N_nom_N, v_init_um_s)
    law = [nm for nm in names if nm in _SENS_COLS]
    cols = np.array([_SENS_COLS[nm] for nm in law], dtype=np.int64)
    k = model.stiffness_N_per_um
    if k is not None:
        if "stiffness_kN_per_m" in names:
            law.append("stiffness_kN_per_m")
            cols = np.append(cols, D_STIFF)
        F, J = stiff_series_sens(p, t, x, v_eff, nfac, k, float(v_init_um_s), cols)
        if "stiffness_kN_per_m" in names:
            J[:, -1] *= 1e-3  # d/dk (N/µm) -> per kN/m
    else:
        mu, dmu = fr.mu_series_sens(p, t, v_eff, x, float(v_init_um_s), cols)
        F = mu * nfac
        J = dmu * nfac[:, None]
    out = {nm: J[:, j] for j, nm in enumerate(law)}
    if "sensor_lag" in ext:
        tau = model.get("tau_s")
        if "tau_s" in names:
            h = 1e-5 * tau
            out["tau_s"] = (sensors.lowpass_uneven(t, F, tau + h) - sensors.lowpass_uneven(t, F, tau - h)) / (2 * h)
        F = sensors.lowpass_uneven(t, F, tau)
        out.update({nm: sensors.lowpass_uneven(t, out[nm], tau) for nm in law})
    if "force_offset_drift" in ext:
        F = F + sensors.offset_drift(t, model.get("rate_N_per_s"))
        if "rate_N_per_s" in names:
            out["rate_N_per_s"] = t.copy()
    return F, out
