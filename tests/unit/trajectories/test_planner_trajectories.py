"""Planner: segment lengths, the stepped pass's geometry, velocity steps, limits, speed, the
run-up before a velocity step (>= 5 L of the friction model in use), and the layering
(trajectories imports nothing from rig)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rig.config.profile import RigProfile, load_profile
from rig.config.recipe import compile_recipe, load_recipe, parse_recipe
from trajectories import MIN_RUN_UP_L, PlanError, PlanSpec, RigLimits, compile_plan
from trajectories import Hold as PlainHold


LIM = RigLimits(loop_rate_hz=1000.0, stroke_min_um=0.0, stroke_max_um=5000.0, max_speed_um_s=1000.0,
                initial_position_um=500.0, source="test")


def recipe(segments: str, extra: str = ""):
    return parse_recipe(f"name: t\nlubricant: boundary\n{extra}segments:\n{segments}")


def test_run_in_lengths_and_bounded_acceleration():
    r = recipe("  - kind: run_in\n", "accel_um_s2: 100\n")
    p = compile_recipe(r, limits=LIM)
    x, v = p.x_ref_um, p.v_ref_um_s
    assert x[0] == pytest.approx(500.0)
    assert x.max() == pytest.approx(4500.0, abs=1e-6)  # pulled 4 mm
    assert x[-1] == pytest.approx(500.0, abs=1e-6)     # pushed back
    assert v.max() == pytest.approx(20.0) and v.min() == pytest.approx(-20.0)
    a = np.diff(v) * p.loop_rate_hz
    assert np.abs(a).max() <= 100.0 * 1.001            # acceleration bound
    # position is the integral of velocity (closed form agrees with trapezoid)
    assert np.allclose(np.diff(x) * 1000.0, 0.5 * (v[1:] + v[:-1]), atol=1e-3)
    # 2 x 4000 µm at 20 µm/s = 400 s plus the ramps
    assert 400.0 < p.duration_s < 401.0
    seg = p.segments[0]
    assert seg["kind"] == "run_in" and seg["x_max_um"] == pytest.approx(4500.0)


def test_stepped_pass_up_then_down_and_geometry():
    r = recipe("  - kind: stepped_pass\n")
    p = compile_recipe(r, limits=LIM)
    levels = p.events_of("level")
    vs = [e["v_um_s"] for e in levels]
    assert vs == [1, 2, 5, 10, 50, 100, 200, 200, 100, 50, 10, 5, 2, 1]
    assert [e["direction"] for e in levels] == ["up"] * 7 + ["down"] * 7
    for i, e in enumerate(levels):
        assert e["x_start_um"] == pytest.approx(500.0 + 250.0 * i, abs=1e-6)
        assert e["x_end_um"] == pytest.approx(500.0 + 250.0 * (i + 1), abs=1e-6)
        assert e["window_x_end_um"] - e["window_x_start_um"] == pytest.approx(50.0)
        assert e["window_x_end_um"] == pytest.approx(e["x_end_um"])
        # window time = 50 µm at the level's velocity
        assert e["window_t_end_s"] - e["window_t_start_s"] == pytest.approx(50.0 / e["v_um_s"], rel=1e-9)
        # the reference velocity is the level's over the whole averaging window
        i0 = int(np.ceil(e["window_t_start_s"] * 1000)) + 1
        i1 = int(np.floor(e["window_t_end_s"] * 1000)) - 1
        assert np.allclose(p.v_ref_um_s[i0:i1], e["v_um_s"], rtol=1e-9)
    # the pass: 3.5 mm tensile, ends (practically) at the minimum velocity, then stops
    seg = p.segments[0]
    assert seg["x_end_um"] - seg["x_start_um"] == pytest.approx(3500.0, abs=0.01)
    assert p.v_ref_um_s[-1] == 0.0


def test_stepped_pass_transition_too_long_is_a_plan_error():
    r = recipe("  - kind: stepped_pass\n", "accel_um_s2: 20\n")
    with pytest.raises(PlanError, match=r"segment 1 \(stepped_pass\).*accel"):
        compile_recipe(r, limits=LIM)


def test_velocity_steps_events_and_slip():
    r = recipe("  - kind: velocity_steps\n    slip_before_um: 100\n    slip_after_um: 300\n"
               "    steps: [{v1_um_s: 1, v2_um_s: 2}, {v1_um_s: 1, v2_um_s: 10, slip_after_um: 340}]\n",
               "accel_um_s2: 20\n")
    p = compile_recipe(r, limits=LIM)
    steps = p.events_of("velocity_step")
    assert [(e["v1_um_s"], e["v2_um_s"]) for e in steps] == [(1, 2), (1, 10)]
    for e, after in zip(steps, (300, 340)):
        k = int(round(e["t_s"] * 1000))
        assert e["x_um"] == pytest.approx(600.0, abs=1e-6)       # 100 µm of slip from the start (500)
        assert p.v_ref_um_s[k - 5] == pytest.approx(1.0)
        k2 = int(np.ceil(e["ramp_end_s"] * 1000)) + 2
        assert p.v_ref_um_s[k2] == pytest.approx(e["v2_um_s"])
        assert e["x_end_um"] - e["x_um"] == pytest.approx(after)
    assert p.x_ref_um[-1] == pytest.approx(500.0)  # returned to the start
    # the events are in time order and bracketed by the segment's start/end
    ts = [e["t_s"] for e in p.events]
    assert ts == sorted(ts)
    assert p.events[0]["kind"] == "segment_start" and p.events[-1]["kind"] == "segment_end"


def test_stroke_violation_names_segment_and_limit():
    r = recipe("  - kind: hold\n    duration_s: 1\n  - kind: move\n    position_um: 5200\n    speed_um_s: 50\n")
    with pytest.raises(PlanError) as ei:
        compile_recipe(r, limits=LIM)
    msg = str(ei.value)
    assert ei.value.segment == 1 and "segment 2 (move)" in msg and "stroke" in msg and "5200" in msg


def test_run_in_beyond_stroke():
    r = recipe("  - kind: move\n    position_um: 1500\n    speed_um_s: 100\n  - kind: run_in\n")
    with pytest.raises(PlanError, match=r"segment 2 \(run_in\).*5500.*stroke"):
        compile_recipe(r, limits=LIM)


def test_speed_limit_from_profile():
    lim = RigLimits(max_speed_um_s=100.0, initial_position_um=500.0)
    r = recipe("  - kind: stepped_pass\n")
    with pytest.raises(PlanError, match=r"segment 1 \(stepped_pass\): speed 200 .*maximum 100"):
        compile_recipe(r, limits=lim)
    # the same limits read from a profile
    prof = RigProfile.model_validate({"stroke": {"min_um": 0, "max_um": 5000, "home_um": 500},
                                      "actuator": {"max_speed_um_s": 100.0}})
    with pytest.raises(PlanError, match="maximum 100"):
        compile_recipe(r, prof)


def test_log_rate_must_divide_loop_rate():
    r = recipe("  - kind: hold\n    duration_s: 1\n", "log: {decimated_rate_hz: 30}\n")
    with pytest.raises(PlanError, match="decimated_rate_hz"):
        compile_recipe(r, limits=LIM)


@pytest.mark.parametrize("lubricant", ["dry", "paraffin", "boundary"])
def test_shipped_recipes_fit_the_sim_profile_for_every_lubricant(repo_root, lubricant):
    prof = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    L_um = prof.lubricants[lubricant].L_um
    for path in sorted((repo_root / "config" / "recipes").glob("*.yaml")):
        r = load_recipe(path)
        r.lubricant = lubricant  # what `rig run --lubricant` does
        p = compile_recipe(r, prof)
        assert p.x_ref_um.min() >= prof.stroke.min_um and p.x_ref_um.max() <= prof.stroke.max_um
        assert p.x_ref_um[0] == pytest.approx(prof.stroke.home_um)
        for e in p.events_of("velocity_step"):
            assert e["run_up_L"] >= MIN_RUN_UP_L
            # the reference is at v1 over the last 5 L before the step
            k0 = int(np.ceil((e["t_s"] - MIN_RUN_UP_L * L_um / e["v1_um_s"]) * 1000))
            k1 = int(np.floor(e["t_s"] * 1000))
            assert np.allclose(p.v_ref_um_s[k0:k1], e["v1_um_s"], rtol=1e-9)


def test_velocity_steps_recipe_windows_fit(repo_root):
    """Enough slip after each step for the windows at 50/100/250 µm plus 200 points at 25 Hz."""
    r = load_recipe(repo_root / "config" / "recipes" / "velocity-steps.yaml")
    p = compile_recipe(r, limits=LIM)
    steps = p.events_of("velocity_step")
    assert [(e["v1_um_s"], e["v2_um_s"]) for e in steps] == [(1, 2), (1, 5), (1, 10)]
    L_um = 19.2  # boundary lubricant, Table 2
    for e in steps:
        assert e["slip_before_um"] >= 5 * L_um
        assert e["slip_after_um"] >= 250 + 200 / 25.0 * e["v2_um_s"]
    assert p.duration_s < 900


def test_one_hour_plan_is_fast():
    r = recipe("  - kind: stepped_pass\n  - kind: hold\n    duration_s: 2700\n")
    t0 = time.perf_counter()
    p = compile_recipe(r, limits=LIM)
    dt = time.perf_counter() - t0
    assert p.duration_s > 3600
    assert p.n_ticks == pytest.approx(p.duration_s * 1000 + 1, abs=2)
    assert dt < 3.0, f"planning 1 h took {dt:.2f} s"


def test_start_position_adds_an_approach():
    r = recipe("  - kind: hold\n    duration_s: 1\n", "start_position_um: 1000\n")
    p = compile_recipe(r, limits=LIM)
    assert p.segments[0]["index"] == -1 and p.segments[0]["kind"] == "move"
    assert p.segments[1]["x_start_um"] == pytest.approx(1000.0)
    assert p.x_ref_um[0] == pytest.approx(500.0)


def test_default_speed_limit_and_hardware_stroke_interlocks():
    prof = RigProfile.model_validate({
        "stroke": {"min_um": 0, "max_um": 5000, "home_um": 500},
        "hardware": {"loadcells": {}, "lvdt": {}, "valve": {}, "interlocks": {"stroke_max_um": 3000}}})
    r = recipe("  - kind: move\n    position_um: 3500\n    speed_um_s: 100\n")
    with pytest.raises(PlanError, match=r"outside the stroke \[0, 3000\]"):
        compile_recipe(r, prof)
    r = recipe("  - kind: move\n    position_um: 3500\n    speed_um_s: 1500\n")
    with pytest.raises(PlanError, match="planner's default"):
        compile_recipe(r, RigProfile())


STEPS = "  - kind: velocity_steps\n    label: vs\n{before}    steps: [{{v1_um_s: 1, v2_um_s: 2}}]\n"


def test_short_run_up_is_refused_naming_the_segment():
    prof = RigProfile()  # dry: L = 64.7 µm
    r = recipe("  - kind: hold\n    duration_s: 1\n" + STEPS.format(before="    slip_before_um: 120\n"),
               "accel_um_s2: 20\n")
    r.lubricant = "dry"
    with pytest.raises(PlanError) as ei:
        compile_recipe(r, prof)
    msg = str(ei.value)
    assert ei.value.segment == 1 and msg.startswith("segment 2 (velocity_steps 'vs'): step 1 (1 -> 2 µm/s)")
    assert "out of steady state" in msg and "1.85 L" in msg and "L = 64.7 µm" in msg and "dry" in msg
    assert "slip_before_um >= 324" in msg
    r.lubricant = "boundary"  # 120 µm = 6.2 L of boundary's 19.2 µm: fine
    assert compile_recipe(r, prof).events_of("velocity_step")[0]["run_up_L"] == pytest.approx(6.25, abs=0.01)


def test_default_run_up_is_six_L_of_the_model_in_use():
    from rig.model.spec import FrictionModel

    prof = RigProfile()
    r = recipe(STEPS.format(before=""), "accel_um_s2: 20\n")
    for lub in ("dry", "paraffin", "boundary"):
        r.lubricant = lub
        e = compile_recipe(r, prof).events_of("velocity_step")[0]
        assert e["run_up_L"] == pytest.approx(6.0)
        assert e["slip_before_um"] == pytest.approx(6 * prof.lubricants[lub].L_um + np.pi / 80, rel=1e-9)
    # a friction model given to the run (rig run --friction-model) sets L
    fm = FrictionModel(params={"mu0": 0.1, "A_mu": 0.001, "B_mu": 0.004, "L_um": 100.0})
    e = compile_recipe(r, prof, friction_model=fm).events_of("velocity_step")[0]
    assert e["slip_before_um"] == pytest.approx(600.0, abs=0.1)
    r = recipe(STEPS.format(before="    slip_before_um: 150\n"), "accel_um_s2: 20\n")  # 7.8 L of boundary
    with pytest.raises(PlanError, match="L = 100 µm .the friction model given"):
        compile_recipe(r, prof, friction_model=fm)


def test_require_steady_state_false_allows_a_short_run_up():
    r = recipe(STEPS.format(before="    slip_before_um: 10\n    require_steady_state: false\n"),
               "accel_um_s2: 20\n")
    e = compile_recipe(r, limits=LIM).events_of("velocity_step")[0]
    assert e["run_up_L"] == pytest.approx((10 - np.pi / 80) / 19.2)
    r = recipe(STEPS.format(before="    slip_before_um: 0.01\n    require_steady_state: false\n"),
               "accel_um_s2: 20\n")
    with pytest.raises(PlanError, match="shorter than the run-up to v1"):
        compile_recipe(r, limits=LIM)


def test_dry_run_up_still_fits_the_stroke(repo_root):
    """velocity-steps.yaml on dry: 388 µm of run-up + 650 µm after the 1 -> 10 step from 500 µm."""
    prof = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    r = load_recipe(repo_root / "config" / "recipes" / "velocity-steps.yaml")
    r.lubricant = "dry"
    p = compile_recipe(r, prof)
    assert p.x_ref_um.max() < 1600.0 < prof.stroke.max_um
    assert 1400 < p.duration_s < 1600


def test_planner_takes_plain_data():
    p = compile_plan(PlanSpec(segments=(PlainHold(duration_s=2.0),)), RigLimits(initial_position_um=100.0))
    assert p.duration_s == pytest.approx(2.0) and np.all(p.x_ref_um == 100.0)


def test_rig_run_refuses_a_step_out_of_steady_state(repo_root, tmp_path):
    """`rig run --plan-only`: the shipped recipe plans for dry; a 120 µm run-up does not (exit 2)."""
    from typer.testing import CliRunner
    from rig.cli import app

    shipped = repo_root / "config" / "recipes" / "velocity-steps.yaml"
    res = CliRunner().invoke(app, ["run", str(shipped), "--sim", "--lubricant", "dry", "--plan-only"])
    assert res.exit_code == 0, res.output
    old = tmp_path / "old.yaml"
    old.write_text(shipped.read_text().replace("    label: boundary steps\n",
                                               "    label: boundary steps\n    slip_before_um: 120\n"))
    res = CliRunner().invoke(app, ["run", str(old), "--sim", "--lubricant", "dry", "--plan-only"])
    assert res.exit_code == 2
    text = " ".join(res.output.split())
    # the recipe's "boundary steps" says the lubricant actually used (--lubricant dry)
    assert "segment 2 (velocity_steps 'dry steps')" in text and "out of steady state" in text
    assert "Traceback" not in text
