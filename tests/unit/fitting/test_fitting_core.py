"""rig.fitting: named parameters with bounds and ln scaling; Jacobian standard errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.fitting import Param, ParamSet, least_squares_fit


def test_line_fit_errors_match_ordinary_least_squares():
    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 10.0, 400)
    y = 0.5 + 0.2 * x + 0.05 * rng.standard_normal(x.size)
    ps = ParamSet([Param("a", "1", -10, 10, scale=0.1), Param("b", "1/s", -10, 10, scale=0.01)])
    out = least_squares_fit(lambda p: p["a"] + p["b"] * x - y, ps, [{"a": 0.0, "b": 0.0}])
    X = np.column_stack([np.ones_like(x), x])
    coef, res, *_ = np.linalg.lstsq(X, y, rcond=None)
    s2 = float(res[0]) / (x.size - 2)
    se = np.sqrt(np.diag(np.linalg.inv(X.T @ X)) * s2)
    assert out.params["a"] == pytest.approx(coef[0], abs=1e-6)
    assert out.params["b"] == pytest.approx(coef[1], abs=1e-6)
    assert out.stderr["a"] == pytest.approx(se[0], rel=1e-3)
    assert out.stderr["b"] == pytest.approx(se[1], rel=1e-3)


def test_log_parameter_stays_positive_and_best_start_wins():
    t = np.linspace(0.0, 50.0, 300)
    y = np.exp(-t / 7.0)
    ps = ParamSet([Param("L_um", "µm", 0.05, 1e5, log=True)])
    # a start far out converges to a poor local fit; several starts find the truth
    out = least_squares_fit(lambda p: np.exp(-t / p["L_um"]) - y, ps, [{"L_um": 1e4}, {"L_um": 5.0}])
    assert out.params["L_um"] == pytest.approx(7.0, rel=1e-6)
    assert out.params["L_um"] > 0 and math.isfinite(out.stderr["L_um"])
    assert Param("k", "N", 1.0, 10.0, log=True).at_bound(10.0)
