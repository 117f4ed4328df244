"""The whole-record fit's honest errors (issue 20, Deliver 6): a run's start from rest is not
compared, and the errors are never below the leave-one-run-out jackknife's."""

import math

import numpy as np

from rig.analysis.identify import _exclude_break_away, _jackknife_floor


def _run_from_rest(seed: int, rest_s: float):
    """A run at 1 µm/s (25 Hz, LVDT noise 0.03 µm) whose slider sticks ``rest_s`` before moving."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 60.0, 0.04)
    x = 500.0 + np.maximum(t - rest_s, 0.0) + rng.normal(0.0, 0.03, t.size)
    return t, x


def test_a_run_after_a_rest_is_compared_from_its_break_away_plus_the_settling():
    t, x = _run_from_rest(1, rest_s=1.5)
    sliding = np.ones(t.size, bool)
    _exclude_break_away(t, x, [(10, t.size)], sliding, settle_s=1.0)
    first = t[np.argmax(sliding[10:]) + 10]
    # the slider moves at 1.5 s (3 noise widths later: +0.1 s), then 1 s of settling
    assert 2.4 < first < 2.8
    assert sliding[:10].all()  # before the run: untouched


def test_a_run_from_the_records_first_samples_is_compared_whole():
    t, x = _run_from_rest(2, rest_s=1.5)
    sliding = np.ones(t.size, bool)
    _exclude_break_away(t, x, [(0, t.size)], sliding, settle_s=1.0)
    assert sliding.all()


def _unc(sd_A, sd_L):
    cov = np.diag([sd_A ** 2, sd_L ** 2])
    cov[0, 1] = cov[1, 0] = 0.5 * sd_A * sd_L
    return {"params_sd": {"A_mu": sd_A, "L_um": sd_L},
            "intervals": {"A_mu": [1e-3 - sd_A, 1e-3 + sd_A], "L_um": [20.0 * math.exp(-sd_L / 20), 20.0 * math.exp(sd_L / 20)]},
            "correlation": {"names": ["A_mu", "L_um"]}, "cov": cov}


def test_the_jackknife_widens_only_the_errors_it_exceeds_and_keeps_the_correlation():
    unc = _unc(2e-5, 0.05)
    _jackknife_floor(unc, {"runs": 3, "groups": 3, "sd": {"A_mu": 1e-5, "L_um": 0.2}}, {"A_mu": 1e-3, "L_um": 20.0})
    assert unc["params_sd"]["A_mu"] == 2e-5  # the Jacobian's is larger: kept
    assert unc["params_sd"]["L_um"] == 0.2
    lo, hi = unc["intervals"]["L_um"]
    # widened by 4 in ln L about the value: still skewed, about +-1 % per 0.2 µm
    assert math.isclose(math.log(hi / 20.0), 4 * 0.05 / 20, rel_tol=1e-9)
    assert math.isclose(math.log(20.0 / lo), 4 * 0.05 / 20, rel_tol=1e-9)
    c = unc["cov"]
    assert math.isclose(c[0, 1] / math.sqrt(c[0, 0] * c[1, 1]), 0.5)
    assert math.isclose(math.sqrt(c[1, 1]), 0.2)
    assert unc["jackknife"]["raised"] == ["L_um"]


def test_without_a_jackknife_the_errors_are_the_jacobians():
    unc = _unc(2e-5, 0.05)
    _jackknife_floor(unc, {}, {"A_mu": 1e-3, "L_um": 20.0})
    assert unc["params_sd"] == {"A_mu": 2e-5, "L_um": 0.05} and "jackknife" not in unc


def test_the_errors_are_never_below_the_change_with_the_steps_estimated_velocity():
    from rig.analysis.identify import fit_whole_record
    from rig.model.spec import FrictionModel
    from rig.sim import synth

    # three short steps up and down (about 1 s to generate): the floor needs steps, not their length
    protocol = synth.paper_step_protocol(pre_um=100.0, post_um=120.0, back_um=100.0)
    trial = synth.generate(FrictionModel.for_lubricant("boundary", 0.12), protocol, seed=4, rate_hz=25.0).trial
    w = fit_whole_record(trial, max_points=2000)
    rise = w.reported["uncertainty"]["velocity_rise"]
    assert set(rise["sd"]) == {"A_mu", "B_mu", "L_um"} and rise["window_s"] > 0
    sd = w.reported["params_sd"]
    # the floor is the disagreement of two fits of the same record: never zero, never above the reported error
    assert rise["sd"]["A_mu"] > 0
    for k, s in rise["sd"].items():
        assert sd[k] >= 0.999 * s
    # a starting point (diagnose's prior) pays for no second fit
    quick = fit_whole_record(trial, max_points=2000, jackknife=False)
    assert "velocity_rise" not in quick.reported["uncertainty"]
