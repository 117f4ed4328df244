"""Feed-forward at the paper's velocity steps (docs/paper.md row 8): the recipe's switches
(controller.ff1, controller.friction_ff) reach the simulated loop; the friction feed-forward
predicts the paper's Fig. 9 transient; with it the steps 1->2, 1->5, 1->10 µm/s overshoot
< 10 % and rise (10-90 %) within the paper's 0.5 s, measured as the paper's Fig. 8 shows a
step (LVDT at 25 Hz, 10-point moving average + central difference). Noise-free here (the
controller's own response); the noisy figures, over seeds, are benchmarks/bench_overshoot.py's."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

import rig
from rig.analysis.reproduce import step_recipe
from rig.analysis.stability import step_response_metrics, step_velocity_traces
from rig.config.profile import default_profile_path, load_profile
from rig.config.recipe import ControllerSwitches, RecipeError, compile_recipe, load_recipe, parse_recipe
from rig.model.spec import FrictionModel
from rig.session.memory import MemoryLog
from rig.session.sim import simulate
from rig.sim import SimRig
from rig.model.feedforward import friction_feedforward_N


RECIPE = Path(rig.__file__).resolve().parents[1] / "config" / "recipes" / "velocity-steps.yaml"
MOVE = textwrap.dedent("""\
    name: ff
    lubricant: boundary
    accel_um_s2: 100
    {controller}
    segments:
      - kind: hold
        duration_s: 0.5
      - kind: move
        position_um: 520
        speed_um_s: 5
    """)


@pytest.fixture(scope="module")
def profile():
    return load_profile(default_profile_path())


def test_recipe_switches_parse_on_off_and_refuse_anything_else():
    r = parse_recipe(MOVE.format(controller="controller: {ff1: off, friction_ff: on}"))
    assert (r.controller.ff1, r.controller.friction_ff) == (False, True)
    d = parse_recipe(MOVE.format(controller=""))
    assert (d.controller.ff1, d.controller.friction_ff) == (True, False)  # the defaults: FF1 on, friction off
    with pytest.raises(RecipeError, match=r"controller\.ff1"):
        parse_recipe(MOVE.format(controller="controller: {ff1: maybe}"), "r.yaml")
    with pytest.raises(RecipeError, match=r"controller\.ff2"):
        parse_recipe(MOVE.format(controller="controller: {ff2: on}"), "r.yaml")


@pytest.mark.parametrize("ff1, fff", [(True, False), (False, False), (True, True), (False, True)])
def test_recipe_switch_reaches_the_loop(profile, ff1, fff):
    """The feed-forward in the valve command (command x full scale - P - I - D - dither)
    is FF1 x v_ref with ff1 on, 0 with it off, plus the model's friction with friction_ff."""
    rec = parse_recipe(MOVE.format(controller=f"controller: {{ff1: {'on' if ff1 else 'off'}, "
                                              f"friction_ff: {'on' if fff else 'off'}}}"))
    assert compile_recipe(rec, profile).controller == {"ff1": ff1, "friction_ff": fff}
    log, _ = simulate(rec, profile, seed=2)
    c = log.columns()
    ff = (c["valve_cmd"] * profile.actuator.full_scale_force_N - c["pid_p"] - c["pid_i"] - c["pid_d"]
          - c["dither"])
    v_ref = np.diff(c["position_ref_um"], prepend=c["position_ref_um"][0]) * profile.loop.rate_hz
    moving = slice(1000, 4000)                        # at 5 µm/s, after the 0.5 s hold and the ramp
    assert np.allclose(v_ref[moving], 5.0, atol=1e-6)
    expect = (profile.controller.ff1_N_s_per_um if ff1 else 0.0) * 5.0
    if fff:
        m = profile.friction_model("boundary")
        # the model's prediction along the same reference, from the state of a run that starts
        # with a hold (rig.sim: steady state at the profile's initial creep)
        pred = friction_feedforward_N(c["position_ref_um"], 1e-3, m, 2 * rec.normal_force_N,
                                      profile.sim.initial_creep_um_s)
        expect = expect + pred[moving]
        # the rate-and-state part at 5 µm/s, on its way from the creep state: 2N (A ln 5 + theta)
        assert np.all(np.abs(pred[moving]) > 0.3)
    assert np.allclose(ff[moving], expect, atol=1e-6)


def test_friction_feedforward_is_the_papers_step_response():
    """On a velocity step v1 -> v2 the feed-forward is Fig. 9: a jump 2N A ln(v2/v1), then
    the decay over L (slip) to the new steady state 2N (A - B) ln(v2/v1)."""
    A, B, L, N = 0.0011, 0.004, 19.2, 100.0
    m = FrictionModel(params={"mu0": 0.1, "A_mu": A, "B_mu": B, "L_um": L})
    dt, v1, v2 = 1e-3, 1.0, 5.0
    v = np.r_[np.full(200_000, v1), np.full(40_000, v2)]          # 200 µm at v1, then 200 µm at v2
    x = 500.0 + np.cumsum(v) * dt
    f = friction_feedforward_N(x, dt, m, 2 * N, v1)
    i = 200_000
    assert f[i - 1] == pytest.approx(0.0, abs=1e-9)          # steady at V0: mu0 left to the I term
    assert f[i] - f[i - 1] == pytest.approx(2 * N * A * math.log(v2 / v1), rel=2e-3)  # the jump
    assert f[-1] - f[i - 1] == pytest.approx(2 * N * (A - B) * math.log(v2 / v1), rel=1e-3)
    k = i + int(L / v2 / dt)                                       # one L after the step
    frac = (f[k] - f[-1]) / (f[i] - f[-1])
    assert frac == pytest.approx(math.exp(-1.0), abs=0.01)


def _noise_free(profile):
    lv = profile.sensors.lvdt.model_copy(update={"noise_sigma_um": 0.0, "quantization_um": 0.0})
    return profile.model_copy(update={"sensors": profile.sensors.model_copy(update={"lvdt": lv})})


def _steps(profile, friction_ff: bool, ff_model=None) -> dict:
    prof = _noise_free(profile)
    accel = load_recipe(RECIPE).accel_um_s2                        # the shipped recipe's ramp
    rec = step_recipe("boundary", accel_um_s2=accel).model_copy(
        update={"controller": ControllerSwitches(friction_ff=friction_ff)})
    plan = compile_recipe(rec, prof)
    rig = SimRig(prof, "boundary", seed=1)
    rig.ff_model = ff_model
    log = MemoryLog(rate_hz=plan.loop_rate_hz)
    log.schedule_events(plan.events)
    for b in rig.run_blocks(plan.x_ref_um, block_ticks=20000, controller=plan.controller):
        log.write_block(b)
    t, vp, _, steps = step_velocity_traces(log)
    return {e["v2_um_s"]: step_response_metrics(t, vp, e["t_s"], e["v1_um_s"], e["v2_um_s"]) for e in steps}


def test_steps_with_friction_feedforward_overshoot_under_10_percent_and_rise_within_half_a_second(profile):
    without = _steps(profile, False)
    assert without[2.0]["overshoot"] > 0.3          # FF1 alone: the friction transient comes through
    with_ff = _steps(profile, True)
    for v2, m in with_ff.items():
        assert m["overshoot"] < 0.10, (v2, m)
        assert m["rise_s"] <= 0.5, (v2, m)        # paper: 10-90 % in less than 0.5 s
        assert m["overshoot"] < 0.5 * without[v2]["overshoot"]


def test_a_wrong_feedforward_model_still_keeps_the_steps_under_10_percent(profile):
    """The feed-forward's model off by 30 % in A and L, -20 % in B, +0.005 in mu0 (a poor
    identification): the PID absorbs the difference."""
    m = profile.friction_model("boundary")
    p = dict(m.params)
    p.update(A_mu=1.3 * p["A_mu"], B_mu=0.8 * p["B_mu"], L_um=1.3 * p["L_um"], mu0=p["mu0"] + 0.005)
    for v2, r in _steps(profile, True, m.model_copy(update={"params": p})).items():
        assert r["overshoot"] < 0.10, (v2, r)
