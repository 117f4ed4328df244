"""diagnose's velocity is zero where the measured position rests (prep._at_rest): a line fitted over
a window reaching into the motion on either side of a hold smeared it into sliding, and the state
integrated through it lengthened L (the simulated rig's main job: L +7.8/+10.0 % on trials 0-1,
docs/validation.md "Coverage")."""

import numpy as np

from rig.diagnosis.prep import _at_rest


def _slide_hold_slide(v_um_s: float, seed: int = 0):
    """25 Hz: 20 s sliding at v, a 10 s hold, 20 s sliding; the LVDT's noise and quantization."""
    t = np.arange(0.0, 50.0, 0.04)
    x = v_um_s * (np.minimum(t, 20.0) + np.maximum(t - 30.0, 0.0))
    rng = np.random.default_rng(seed)
    xm = np.round((x + rng.normal(0.0, 0.25, t.size)) / 0.076) * 0.076
    return t, xm, np.full(t.size, v_um_s)


def test_a_hold_is_at_rest_and_the_sliding_around_it_is_not():
    t, x, v = _slide_hold_slide(1.0)
    rest = _at_rest(t, x, v)
    inner = (t > 21.5) & (t < 28.5)
    assert rest[inner].mean() > 0.95
    assert not rest[(t < 18.5) | (t > 31.5)].any()


def test_sliding_too_slow_for_the_noise_to_tell_rest_from_slip_is_never_at_rest():
    t, x, v = _slide_hold_slide(0.05)
    assert not _at_rest(t, x, v).any()


def test_only_a_rigid_final_models_reported_grid_rests():
    """core.reported_grid: the rest grid for the rigid final model's refits; a named cause keeps the
    decisions' grid (and the rest grid is not even built)."""
    from rig.data import TrialData
    from rig.diagnosis.core import reported_grid
    from rig.diagnosis.fit import evaluate
    from rig.diagnosis.prep import prepare

    t, x, _ = _slide_hold_slide(1.0)
    rng = np.random.default_rng(1)
    trial = TrialData(time_s=t, position_um=x, friction_N=20.0 + 0.05 * rng.standard_normal(t.size),
                      normal_1_N=np.full(t.size, 100.0), normal_2_N=np.full(t.size, 100.0))
    grid = prepare(trial)
    p = {"mu0": 0.1, "A_mu": 1e-3, "B_mu": 4e-3, "L_um": 10.0}
    rested = reported_grid(grid, evaluate(grid, "rate_state", [], p), lambda: prepare(trial, rest=True))
    hold = (rested.t > 21.5) & (rested.t < 28.5)
    assert np.all(rested.v[hold] == 0.0) and np.abs(grid.v[(grid.t > 21.5) & (grid.t < 28.5)]).max() > 0.0

    def never():
        raise AssertionError("the rest grid was built for a named cause")

    lag = evaluate(grid, "rate_state", ["sensor_lag"], dict(p, tau_s=0.5))
    assert reported_grid(grid, lag, never) is grid
