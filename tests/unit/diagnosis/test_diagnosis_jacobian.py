"""The exact Jacobians the diagnosis fits use (issue 10, Deliver 7: speed).

rig.model.forward.force_sensitivities carries forward-mode sensitivities along the same
integration as predict_force (friction.mu_series_sens; with a spring, loading.stiff_series_sens by
the implicit function theorem). It must give the same force as predict_force and derivatives
that agree with central finite differences of predict_force, for every parameter it claims.
"""

from __future__ import annotations

import numpy as np
import pytest

from rig.model.forward import force_sensitivities, has_sensitivities, predict_force
from rig.model.loading import stiff_series
from rig.model.spec import FrictionModel


def _record(seed: int = 0):
    """Irregular sampling, steps 1 <-> 10 um/s, a stop and a short return: what real records hold."""
    rng = np.random.default_rng(seed)
    n = 6000
    t = np.cumsum(rng.uniform(0.05, 0.2, n))
    v = np.where((t // 120) % 2 == 0, 1.0, 10.0) * (1 + 0.05 * rng.standard_normal(n))
    v[2000:2040] = 0.0
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    N = 200.0 + 0.6 * rng.standard_normal(n)
    return t, x, v, N


CASES = [
    ("rigid, second state, lag, drifts, normals",
     ["second_state_variable", "sensor_lag", "force_offset_drift", "slip_wear_drift", "normal_force_variation"],
     dict(mu0=0.1, A_mu=0.004, B_mu=-0.003, L_um=20.0, B2_mu=0.002, L2_um=300.0, tau_s=0.7, rate_N_per_s=1e-4,
          rate_mu_per_mm=1e-3)),
    ("rigid, periodic, delay", ["position_periodic", "time_delay"],
     dict(mu0=0.1, A_mu=0.004, B_mu=0.006, L_um=20.0, amplitude_mu=1e-3, wavelength_um=150.0, phase_rad=0.4,
          delay_s=0.5)),
    ("spring, second state, lag", ["finite_stiffness", "second_state_variable", "sensor_lag"],
     dict(mu0=0.1, A_mu=0.004, B_mu=0.006, L_um=20.0, B2_mu=0.002, L2_um=300.0, tau_s=0.5,
          stiffness_kN_per_m=300.0)),
    ("spring, periodic, wear", ["finite_stiffness", "position_periodic", "slip_wear_drift"],
     dict(mu0=0.1, A_mu=0.004, B_mu=0.006, L_um=20.0, amplitude_mu=1e-3, wavelength_um=150.0, phase_rad=0.4,
          rate_mu_per_mm=1e-3, stiffness_kN_per_m=150.0)),
]


@pytest.mark.parametrize("label,ext,par", CASES, ids=[c[0] for c in CASES])
def test_sensitivities_match_finite_differences(label, ext, par):
    t, x, v, N = _record()
    model = FrictionModel(extensions=ext, params=par)
    assert has_sensitivities(model.baseline, ext)
    names = list(par) + ["v_init_um_s"]
    F, J = force_sensitivities(model, t, x, v, N, 100.0, names, 2.0)
    np.testing.assert_array_equal(F, predict_force(model, t, x, v, N, 100.0, 2.0))
    # only the delay is left to finite differences
    assert set(names) - set(J) <= {"delay_s"}, set(names) - set(J)
    for nm, col in J.items():
        val = par.get(nm, 2.0)
        h = 1e-6 * max(abs(val), 1e-3)
        if nm == "v_init_um_s":
            up = predict_force(model, t, x, v, N, 100.0, 2.0 + h)
            dn = predict_force(model, t, x, v, N, 100.0, 2.0 - h)
        else:
            up = predict_force(FrictionModel(extensions=ext, params={**par, nm: val + h}), t, x, v, N, 100.0, 2.0)
            dn = predict_force(FrictionModel(extensions=ext, params={**par, nm: val - h}), t, x, v, N, 100.0, 2.0)
        fd = (up - dn) / (2 * h)
        scale = max(float(np.max(np.abs(fd))), 1e-12)
        assert np.max(np.abs(fd - col)) < 1e-4 * scale, (nm, float(np.max(np.abs(fd - col))), scale)


def test_spring_solver_agrees_with_the_finite_difference_newton():
    """predict_force's spring balance (closed-form Newton derivative) agrees with stiff_series (a
    finite-difference Newton derivative) to the solver's tolerance while sliding."""
    t, x, v, N = _record(1)
    model = FrictionModel(extensions=["finite_stiffness", "second_state_variable"],
                          params=dict(mu0=0.1, A_mu=0.004, B_mu=0.006, L_um=20.0, B2_mu=0.002, L2_um=300.0,
                                      stiffness_kN_per_m=300.0))
    F = predict_force(model, t, x, v, N, 100.0, 1.0)
    F_ref = stiff_series(model.to_array(), t, x, v, np.full(t.size, 200.0), 0.3, 1.0)
    assert np.max(np.abs(F - F_ref)) < 1e-8 * np.max(np.abs(F_ref))
