"""Errors that hold what a copy of the record with no other physics does (core.copies_sd), and a final
model whose refit on all rows runs to a bound reported with intervals, not bare values
(core._undetermined_floor): diagnosis.md, "The answer depends on the physics only"."""

from __future__ import annotations

import numpy as np
import pytest

from rig.diagnosis import diagnose
from rig.diagnosis.core import _copies, step_timing_s
from rig.diagnosis.fit import covariance
from rig.diagnosis.transforms import differences, switch_rate
from rig.log import load_trial
from rig.sim.synth import SynthSpec, make_record


def _steps_record():
    trial, truth = make_record(SynthSpec(rate_hz=25.0, duration_s=300.0, seed=11, protocol="varied"))
    return trial, truth


def test_copies_are_the_crops_and_the_half_interval_lags():
    trial, _ = _steps_record()
    t = np.asarray(trial.time_s)

    class Step:
        t_s = float(t[100]) + 0.01

    trial.position_um = 3.0 * (t - t[0])  # sliding at 3 um/s throughout
    cs = _copies(trial, [Step()])
    assert len(cs) == 4
    span = t[-1] - t[0]
    assert cs[0].time_s[0] >= t[0] + 0.03 * span - 1e-9 and cs[0].time_s[-1] == t[-1]
    assert cs[1].time_s[0] == t[0] and cs[1].time_s[-1] <= t[-1] - 0.03 * span + 1e-9
    # the positions moved by half the 40 ms between the rows about the step, later and earlier
    assert step_timing_s(t, [Step()]) == pytest.approx(0.04)
    assert np.allclose(np.asarray(cs[2].position_um)[1:] - np.asarray(trial.position_um)[1:], -0.06)
    assert np.allclose(np.asarray(cs[3].position_um)[:-1] - np.asarray(trial.position_um)[:-1], 0.06)
    assert np.array_equal(cs[2].friction_N, trial.friction_N)
    assert step_timing_s(t, []) == 0.0 and len(_copies(trial, [])) == 2


def test_a_clean_load_point_record_s_copies_move_its_values_less_than_its_noise():
    """A generated load-point step through a spring: the copies move A, B and L by less than the
    Jacobian's own error (the floor adds nothing where the kinematics are clean), and a rigid
    final model has no copies' floor (its kinematics floor is identify's disagreement)."""
    trial, _ = make_record(SynthSpec(protocol=[(30.0, 1.0), (30.0, 10.0)], duration_s=60.0, rate_hz=100.0,
                                     effects={"finite_stiffness": {"stiffness_kN_per_m": 300.0}}, with_ref=False,
                                     seed=7))
    trial.metadata["position_source"] = "load_point"
    d = diagnose(trial, resplits=False)
    moves = d.final_fit.extra["copies_sd"]
    names, _, cov = covariance(d.grid, d.final_fit)
    for k in ("A_mu", "B_mu", "L_um"):
        assert moves[k] < np.sqrt(cov[names.index(k), names.index(k)]), (k, moves[k])
    rigid, _ = _steps_record()
    assert "copies_sd" not in diagnose(rigid, resplits=False).final_fit.extra


def test_leeman_cropped_at_its_start_agrees_with_the_original(real_data_dir):
    """Leeman's step, 3 % cropped at the start (its step stays, 1.1 s after the copy's first row):
    the copy's A (0.0024) and the original's (0.0077) are each within the other's reported errors,
    because the original's errors now hold what that crop does to it."""
    trial = load_trial(real_data_dir / "leeman-p4309-step2.csv")
    t = np.asarray(trial.time_s)
    copy = trial.select(t >= t[0] + 0.03 * (t[-1] - t[0]))
    ref, got = diagnose(trial).report(), diagnose(copy).report()
    assert abs(got["model"]["params"]["A_mu"] - ref["model"]["params"]["A_mu"]) > 0.25 * ref["model"]["params"]["A_mu"]
    assert differences(ref, got, "trim5") == []
    assert ref["model"]["params_sd"]["A_mu"] > 0.003  # the Jacobian alone: 0.0005


def test_a_final_model_whose_refit_runs_to_a_bound_has_intervals(repo_root):
    """Basalt velstep7 logged at 20 Hz about its step (200 Hz from 70 % of the record): the refit on
    every row runs k to its bound; the split fit is reported, as not determined, with every core
    parameter's profile interval holding its value (before: values with no errors at all)."""
    trial = switch_rate(load_trial(repo_root / "tests" / "data" / "giacomel-basalt-velstep7.csv"), 20.0, 200.0, 0.7)
    m = diagnose(trial).report()["model"]
    for k in ("A_mu", "B_mu", "L_um", "stiffness_kN_per_m"):
        lo, hi = m["intervals"][k]
        assert lo <= m["params"][k] <= hi and hi > lo, (k, m["intervals"][k])
        assert m["params_sd"][k] > 0
