"""Speed of the forward model's sensitivity kernels (what every fit's Jacobian costs).

``rig.model.forward.force_sensitivities`` on a synthetic record of velocity steps with
reversals, for a two-state slip-law model (``mu_series_sens``) and the same with a finite
stiffness (``stiff_series_sens``, the spring balance's safeguarded Newton iteration);
``predict_force`` of the aging law with a spring (``stiff_series``, the same iteration).
Prints the best CPU time of ``--repeat`` calls per kernel (a shared machine disturbs it less than
the wall clock) beside os.getloadavg().

    python benchmarks/bench_model_kernels.py [--samples 200000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from rig.model.forward import force_sensitivities, predict_force
from rig.model.spec import FrictionModel


def record(n: int, rate_hz: float = 25.0):
    """Velocity steps 1 <-> 10 µm/s reversing every 400 samples (t s, x µm, v µm/s, N N)."""
    t = np.arange(n) / rate_hz
    level = np.where((np.arange(n) // 100) % 2 == 0, 1.0, 10.0)
    sign = np.where((np.arange(n) // 400) % 2 == 0, 1.0, -1.0)
    v = level * sign
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate_hz)])
    return t, x, v, np.full(n, 200.0)


MODELS = {
    "two-state slip law (mu_series_sens)": FrictionModel(
        baseline="rate_state", extensions=["second_state_variable"],
        params={"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4e-3, "L_um": 19.2, "B2_mu": 1e-3, "L2_um": 200.0}),
    "slip law + spring (stiff_series_sens)": FrictionModel(
        baseline="rate_state", extensions=["finite_stiffness"],
        params={"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4e-3, "L_um": 19.2, "stiffness_kN_per_m": 500.0}),
    "aging law + spring (stiff_series, force only)": FrictionModel(
        baseline="rate_state", extensions=["aging_law", "finite_stiffness"],
        params={"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4e-3, "L_um": 19.2, "stiffness_kN_per_m": 500.0}),
}


def _call(model, t, x, v, n, names):
    if "aging_law" in model.extensions:
        return predict_force(model, t, x, v, n, 100.0), {}
    return force_sensitivities(model, t, x, v, n, 100.0, names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    t, x, v, n = record(a.samples)
    for name, model in MODELS.items():
        names = list(model.params)
        _call(model, t[:100], x[:100], v[:100], n[:100], names)  # compile
        best = np.inf
        for _ in range(a.repeat):
            t0 = time.process_time()
            F, J = _call(model, t, x, v, n, names)
            best = min(best, time.process_time() - t0)
        print(f"{name}: {a.samples} samples, {len(names)} columns: best {best * 1e3:.1f} ms CPU "
              f"({a.samples / best / 1e6:.2f} M samples/s); checksum {float(np.sum(F)):.12g} "
              f"{sum(float(np.sum(d)) for d in J.values()):.12g}; load {os.getloadavg()}")


if __name__ == "__main__":
    main()
