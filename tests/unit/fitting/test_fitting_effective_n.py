"""Statistics that weigh time, not rows (issue 20 Deliver 3): the effective sample size of white
and AR(1) residuals, and an information-criterion difference that does not change when part of a
record is logged ten times faster."""

from __future__ import annotations

import numpy as np
import pytest

from rig.diagnosis.prep import time_weights
from rig.fitting.stats import comparison_n_eff, effective_n, effective_n_time, information_criterion, score_inflation


def _ar1(n: int, rho: float, rng: np.random.Generator) -> np.ndarray:
    e = rng.standard_normal(n)
    out = np.empty(n)
    out[0] = e[0]
    for i in range(1, n):
        out[i] = rho * out[i - 1] + np.sqrt(1.0 - rho * rho) * e[i]
    return out


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_effective_n_of_white_and_ar1_residuals(rho):
    # AR(1): the variance of the mean is (1 + rho) / (1 - rho) times white noise's
    rng = np.random.default_rng(7)
    n = 20000
    r = _ar1(n, rho, rng)
    want = n * (1.0 - rho) / (1.0 + rho)
    assert effective_n(r) == pytest.approx(want, rel=0.2)
    # the same in time: rows at 10 Hz in cells of 1 s (ten rows a cell), each row one raw sample
    t = np.arange(n) * 0.1
    assert effective_n_time(t, r, np.ones(n), 1.0) == pytest.approx(want, rel=0.2)


def test_effective_n_counts_a_slow_misfit_once_per_correlation_time():
    # a misfit that wanders over ~5 s under white noise: far fewer independent pieces than rows
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 600.0, 0.04)
    r = 0.1 * rng.standard_normal(t.size) + np.interp(t, np.arange(0.0, 605.0, 5.0),
                                                      rng.standard_normal(121))
    ne = effective_n_time(t, r, np.ones(t.size), 1.0)
    assert ne < 0.05 * t.size
    assert 20 < ne < 600   # of the order of the 120 wanders of 5 s


def _record(second_half_hz: float, rng: np.random.Generator):
    """A step at 60 s: model B is the truth (residual: noise correlated over ~0.5 s, as a sensor
    chain's), model A misses a transient of 8 s after the step. Logged at 10 Hz, after the step at
    ``second_half_hz``. Returns (t, time weights, residual of A, residual of B)."""
    t = np.concatenate([np.arange(0.0, 60.0, 0.1), np.arange(60.0, 120.0, 1.0 / second_half_hz)])
    # the noise is a property of time: drawn on a 1 kHz clock, low-passed, then sampled
    tf = np.arange(0.0, 120.0, 1e-3)
    noise = np.interp(t, tf, 0.05 * _smooth(rng.standard_normal(tf.size), 500))
    misfit = np.where(t > 60.0, 0.3 * np.exp(-(t - 60.0) / 8.0), 0.0)
    return t, time_weights(t), noise + misfit, noise


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    c = np.cumsum(np.concatenate([[0.0], x]))
    y = (c[k:] - c[:-k]) / np.sqrt(k)
    return np.concatenate([y, np.full(k - 1, y[-1])])


def _delta_ic(t, w, rA, rB, n_eff=None) -> float:
    """A's criterion minus B's (B has one parameter more) on the comparison's effective sample size."""
    n = float(w.sum())
    ssr_a, ssr_b = float(np.sum(w * rA * rA)), float(np.sum(w * rB * rB))
    ne = comparison_n_eff(t, w, rA, rB, 1.0) if n_eff is None else n_eff
    return information_criterion(ssr_a, n, ne, 3) - information_criterion(ssr_b, n, ne, 4)


def test_information_criterion_difference_does_not_grow_with_a_faster_second_half():
    rng_u, rng_m = np.random.default_rng(11), np.random.default_rng(11)
    uniform = _record(10.0, rng_u)
    mixed = _record(100.0, rng_m)
    d_u, d_m = _delta_ic(*uniform), _delta_ic(*mixed)
    assert d_u > 10.0                      # the transient is clearly there
    assert d_m == pytest.approx(d_u, rel=0.25)
    # counting rows instead would weigh the fast half ten times: the difference several times larger
    rows_m = _delta_ic(*mixed, n_eff=float(mixed[0].size))
    rows_u = _delta_ic(*uniform, n_eff=float(uniform[0].size))
    assert rows_m > 3.0 * rows_u


def test_score_inflation_sees_correlation_only_where_a_parameter_has_information():
    # a slow wander over the first half only: the level of the first half inflates, the level of the
    # second half keeps white-noise errors
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 400.0, 0.1)
    r = 0.1 * rng.standard_normal(t.size)
    r[t < 200.0] += np.interp(t[t < 200.0], np.arange(0.0, 205.0, 10.0), rng.standard_normal(21))
    J = np.column_stack([(t < 200.0).astype(float), (t >= 200.0).astype(float)])
    tau = score_inflation(t, J, r, 1.0)
    assert tau[0] > 20.0
    assert tau[1] == pytest.approx(1.0, abs=0.6)
