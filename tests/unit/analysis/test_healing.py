"""Slide-hold-slide: the planner's segment (run-up >= 5 L, stroke, events), `rig heal`'s
reduction, and the physics: the aging law heals about B ln(1 + v t_h / L) per hold at the
simulated rig's stiff loading, the slip law does not heal at rest."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.analysis.healing import aging_prediction, heal, healing_rate
from rig.cli import app
from rig.config.profile import load_profile
from rig.config.recipe import compile_recipe, parse_recipe
from rig.data import write_csv
from rig.model.spec import FrictionModel
from rig.session.sim import simulate
from trajectories import PlanError, RigLimits


LIM = RigLimits(loop_rate_hz=1000.0, stroke_min_um=0.0, stroke_max_um=5000.0, max_speed_um_s=1000.0,
                initial_position_um=500.0, source="test")
HOLDS = (1.0, 3.0, 10.0, 30.0, 100.0)
V_UM_S = 10.0
SHS = f"""name: shs
lubricant: boundary
seed: 11
accel_um_s2: 500
controller: {{ff1: on, friction_ff: on}}
segments:
  - kind: hold
    duration_s: 1
  - kind: slide_hold_slide
    velocity_um_s: {V_UM_S:g}
    run_up_um: 400
    hold_times_s: [{', '.join(f'{h:g}' for h in HOLDS)}]
"""


def shs(extra: str = ""):
    return parse_recipe(f"name: t\nlubricant: boundary\naccel_um_s2: 500\nsegments:\n  - kind: slide_hold_slide\n{extra}")


def test_planner_holds_at_rest_for_the_hold_times_and_reslides():
    p = compile_recipe(shs("    velocity_um_s: 10\n    hold_times_s: [1, 3, 10]\n"), limits=LIM)
    holds = p.events_of("hold")
    assert [e["hold_s"] for e in holds] == [1, 3, 10]
    L = 19.2  # boundary lubricant of the default profile: the ramp + 6 L by default
    ramp = np.pi * 10.0 ** 2 / (4 * 500.0)
    for e in holds:
        i0, i1 = int(np.ceil(e["t_s"] * 1000)), int(np.floor(e["t_end_s"] * 1000))
        assert np.ptp(p.x_ref_um[i0:i1 + 1]) < 1e-9                     # at rest for the whole hold
        assert e["t_end_s"] - e["t_s"] == pytest.approx(e["hold_s"])
        assert e["reslide_um"] == pytest.approx(ramp + 6 * L)
        k = int(round(0.5 * (e["t_end_s"] + e["t_reslide_end_s"]) * 1000))
        assert p.v_ref_um_s[k] == pytest.approx(10.0)                    # re-slides at v
    # the run-up (ramp + 6 L) and the stop's own ramp before each rest
    assert holds[0]["x_um"] == pytest.approx(500.0 + 2 * ramp + 6 * L, abs=0.01)
    assert holds[1]["x_um"] - holds[0]["x_um"] == pytest.approx(2 * ramp + 6 * L, abs=0.01)


def test_planner_refuses_a_short_reslide_and_the_stroke():
    with pytest.raises(PlanError, match=r"segment 1 \(slide_hold_slide\): the re-slide .*out of steady state"):
        compile_recipe(shs("    reslide_um: 50\n"), limits=LIM)
    with pytest.raises(PlanError, match=r"the run-up would start out of steady state.*run_up_um >= "):
        compile_recipe(shs("    run_up_um: 60\n"), limits=LIM)
    with pytest.raises(PlanError, match="outside the stroke"):
        compile_recipe(shs("    reslide_um: 1000\n    hold_times_s: [1, 2, 3, 4, 5]\n"), limits=LIM)
    with pytest.raises(PlanError, match=r"speed 2000 .*maximum 1000"):
        compile_recipe(shs("    velocity_um_s: 2000\n"), limits=LIM)


def test_healing_rate_is_the_log_slope_with_its_standard_error():
    th = np.array([1.0, 3.0, 10.0, 30.0, 100.0])
    rng = np.random.default_rng(4)
    beta, sd = healing_rate(th, 0.002 + 0.005 * np.log10(th) + rng.normal(0, 1e-4, th.size))
    assert beta == pytest.approx(0.005, abs=3 * sd) and 0 < sd < 2e-4
    assert healing_rate([2.0, 2.0], [0.1, 0.2]) == (None, None)


@pytest.fixture(scope="module")
def runs(repo_root):
    prof = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    rec = parse_recipe(SHS)
    lp = prof.lubricants["boundary"]
    params = {"mu0": lp.mu0, "A_mu": lp.A_mu, "B_mu": lp.B_mu, "L_um": lp.L_um}
    out = {}
    for law, ext in (("aging", ["aging_law"]), ("slip", [])):
        log, res = simulate(rec, prof, FrictionModel(extensions=ext, params=params))
        assert res.status == "completed"
        out[law] = log.trial_data(25.0, source=f"shs-{law}")
    return out, lp


def test_aging_law_heals_as_predicted_at_a_stiff_loading(runs):
    (trials, lp) = runs
    rep = heal(trials["aging"])
    assert [round(h["hold_s_planned"]) for h in rep["holds"]] == list(HOLDS)
    pred = aging_prediction(lp.B_mu, lp.L_um, V_UM_S, HOLDS)
    got = np.array([h["delta_mu_peak"] for h in rep["holds"]])
    assert np.all(np.abs(got / pred - 1) < 0.2), got / pred
    assert np.all(np.diff(got) > 0)  # grows with log hold time
    # beta: the slope of the prediction over these holds (L/v = 1.9 s: not yet B ln 10)
    beta_pred, _ = healing_rate(HOLDS, pred)
    assert rep["beta_per_decade"] == pytest.approx(beta_pred, abs=max(3 * rep["beta_per_decade_sd"],
                                                                     0.1 * beta_pred))
    assert 0.6 * lp.B_mu * np.log(10) < rep["beta_per_decade"] < 1.05 * lp.B_mu * np.log(10)
    assert all(h["reference"] == "before" and not h["reversal"] for h in rep["holds"])
    # another lab's record: no reference, no events; the holds from the measured position alone
    tr = trials["aging"]
    bare = type(tr)(time_s=tr.time_s, position_um=tr.position_um, friction_N=tr.friction_N,
                    normal_1_N=tr.normal_1_N, normal_2_N=tr.normal_2_N)
    rep2 = heal(bare)
    assert rep2["rests_from"] == "position_um" and rep2["n_holds"] == len(HOLDS)
    got2 = np.array([h["delta_mu_peak"] for h in rep2["holds"]])
    assert np.all(np.abs(got2 / pred - 1) < 0.2), got2 / pred


def test_slow_noisy_sliding_is_not_a_hold(repo_root):
    """The sepiolite record slides at 0.2 µm/s with 0.2 µm of displacement noise: its short
    stretches without a significant local slope are not holds."""
    from rig.data import read_csv

    with pytest.raises(ValueError, match="no hold"):
        heal(read_csv(repo_root / "tests" / "data" / "giacomel-sepiolite-velstep2.csv"))


def test_slip_law_does_not_heal_at_rest(runs):
    (trials, lp) = runs
    rep = heal(trials["slip"])
    beta, sd = rep["beta_per_decade"], rep["beta_per_decade_sd"]
    assert abs(beta) < 2 * sd or abs(beta) < 0.2 * lp.B_mu * np.log(10)
    assert max(h["delta_mu_peak"] for h in rep["holds"]) < 0.2 * lp.B_mu * np.log(1 + V_UM_S * 100 / lp.L_um)


def test_velocity_steps_rests_are_holds(repo_root):
    prof = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    rec = parse_recipe("name: vs\nlubricant: boundary\nseed: 2\naccel_um_s2: 200\nsegments:\n"
                       "  - kind: velocity_steps\n    hold_s: 2\n    return_speed_um_s: 100\n"
                       "    steps: [{v1_um_s: 10, v2_um_s: 20, slip_after_um: 150},\n"
                       "            {v1_um_s: 10, v2_um_s: 30, slip_after_um: 150}]\n")
    log, _ = simulate(rec, prof)
    rep = heal(log.trial_data(25.0))
    # the rests after each step and after the first return (the last rest ends the record)
    assert rep["n_holds"] == 3
    assert [h["reversal"] for h in rep["holds"]] == [True] * 3
    assert [h["reference"] for h in rep["holds"]] == ["after"] * 3
    assert [round(h["v_before_um_s"]) for h in rep["holds"]] == [20, -100, 30]
    assert all(abs(h["hold_s"] - 2.0) < 0.2 for h in rep["holds"])
    assert rep["beta_per_decade"] is None and rep["notes"]


def test_heal_command_json_plot_and_bad_input(runs, tmp_path):
    (trials, _) = runs
    csv = write_csv(trials["aging"], tmp_path / "aging.csv")
    runner = CliRunner()
    res = runner.invoke(app, ["heal", str(csv), "--json", str(tmp_path / "h.json"), "--plot", str(tmp_path / "h.png")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "h.json").read_text())
    assert doc["schema"] == "rig.heal/1" and len(doc["holds"]) == len(HOLDS)
    assert {"delta_mu_peak", "delta_mu_relax"} <= set(doc["holds"][0]) and doc["beta_per_decade_sd"] > 0
    assert (tmp_path / "h.png").stat().st_size > 10_000
    flat = tmp_path / "flat.csv"
    flat.write_text("# rig-trial-csv: 1\n# normal_force_N: 100\ntime_s,position_um,friction_N\n"
                    + "".join(f"{k * 0.04:.2f},{k * 0.4:.2f},20\n" for k in range(100)))
    res = runner.invoke(app, ["heal", str(flat), "--json", str(tmp_path / "no.json")])
    assert res.exit_code == 2 and "no hold" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "no.json").exists()
