"""The reported rigid models multiply mu by the measured normal forces where they vary (core.reported_grid),
as identify divides friction by them: friction follows the normal force on every rig, and a model held
to the nominal load read its 0.1 % fall along each slide on the simulated rig as a slower decay (L +5 %,
docs/validation.md "Coverage"). The decisions keep the nominal load (diagnosis.md)."""

import math

import numpy as np

from rig.diagnosis.core import refit_all, reported_grid
from rig.diagnosis.fit import evaluate
from rig.diagnosis.prep import prepare
from rig.model.spec import FrictionModel
from rig.sim import synth

TRUTH = {"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.2}


def _record():
    """The paper's steps, generated; the riders' load (and with it the friction) 1 % up and down
    over 150 s periods, measured by the normal load cells."""
    trial = synth.generate(FrictionModel(params=TRUTH), synth.paper_step_protocol(pre_um=150.0, post_um=200.0,
                                                                                   back_um=150.0), seed=3).trial
    f = 1.0 + 0.01 * np.sin(2.0 * math.pi * trial.time_s / 150.0)
    trial.friction_N = trial.friction_N * f
    trial.normal_1_N = trial.normal_1_N * f
    trial.normal_2_N = trial.normal_2_N * f
    return trial


def _rigid(grid):
    return evaluate(grid, "rate_state", [], dict(TRUTH))


def _errors(grid):
    res = refit_all(grid, _rigid(grid))
    return {k: abs(res.params[k] / TRUTH[k] - 1.0) for k in ("A_mu", "B_mu", "L_um")}


def test_the_reported_fit_follows_the_measured_normals_and_the_nominal_one_does_not():
    grid = prepare(_record())
    rep = reported_grid(grid, _rigid(grid))
    assert rep.normals_in_model and not grid.normals_in_model
    nominal, measured = _errors(grid), _errors(rep)
    assert max(measured.values()) < 0.05, measured
    assert max(nominal.values()) > 2.0 * max(measured.values()), (nominal, measured)


def test_a_record_whose_normals_do_not_vary_or_a_named_cause_keeps_its_grid():
    grid = prepare(_record())
    lag = evaluate(grid, "rate_state", ["sensor_lag"], dict(TRUTH, tau_s=0.5))
    assert reported_grid(grid, lag) is grid
    trial = _record()
    trial.normal_1_N = np.full(len(trial), 100.0)
    trial.normal_2_N = np.full(len(trial), 100.0)
    grid = prepare(trial)
    assert reported_grid(grid, _rigid(grid)) is grid
