"""Velocity estimators on a quantized, noisy LVDT record (rig/kinematics.py)."""

from __future__ import annotations

import numpy as np

from rig.kinematics import velocity_for_steps, velocity_local_poly, velocity_paper


Q_UM = 0.076  # LVDT quantization step (paper, section 3)


def _lvdt(t, x_true, seed=1, sigma_um=0.125):
    rng = np.random.default_rng(seed)
    return np.round((x_true + rng.normal(0, sigma_um, t.size)) / Q_UM) * Q_UM


def test_local_poly_beats_paper_estimator_at_25_hz():
    t = np.arange(0, 200, 0.04)
    v_true = np.where(t < 100, 1.0, 10.0)
    x_true = np.where(t < 100, t, 100 + 10 * (t - 100))
    x = _lvdt(t, x_true)
    vp = velocity_paper(t, x)
    vl = velocity_local_poly(t, x, window_s=2.0)
    steady = (np.abs(t - 100) > 2) & (t > 2) & (t < 198)
    err_p = np.sqrt(np.mean((vp - v_true)[steady] ** 2))
    err_l = np.sqrt(np.mean((vl - v_true)[steady] ** 2))
    assert err_l < 0.5 * err_p
    assert err_l < 0.1  # µm/s


def test_adaptive_window_tracks_both_speeds_and_uneven_sampling():
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.005, 0.06, 8000))
    t = t[(t < 180) | (t > 185)]  # a 5 s gap
    ts = 90.0
    v_true = np.where(t < ts, 1.0, 10.0)
    x_true = np.where(t < ts, t, ts + 10 * (t - ts))
    v = velocity_for_steps(t, _lvdt(t, x_true, seed=2))
    ok = np.abs(t - ts) > 2.5
    rel = np.abs(v - v_true)[ok] / v_true[ok]
    assert np.percentile(rel, 95) < 0.15
    assert np.all(np.isfinite(v))


def test_cumulative_slip_is_the_integral_of_speed():
    from rig.model.forward import cumulative_slip_um
    t = np.linspace(0, 10, 1001)
    v = np.where(t < 5, 2.0, -3.0)
    s = cumulative_slip_um(t, v)
    assert abs(s[-1] - (2 * 5 + 3 * 5)) < 0.1
    assert np.all(np.diff(s) >= 0)
    # point by point across a reversal: +1 then -1 slides 1 µm, where |mean v| would give 0
    assert cumulative_slip_um([0.0, 1.0], [1.0, -1.0])[-1] == 1.0


def test_velocity_changes_finds_each_step_once():
    from rig.kinematics import velocity_changes

    t = np.arange(0.0, 60.0, 0.01)
    v = np.where(t < 20.0, 1.0, np.where(t < 40.0, 10.0, 2.0))
    te = velocity_changes(t, v)
    assert te.size == 2
    assert np.allclose(te, [20.0, 40.0], atol=1.0)
    assert velocity_changes(t, np.full(t.size, 3.0)).size == 0
