"""Identification (eqs. 10-14) on generated records with known parameters."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.sim import synth
from rig.analysis.identify import SCHEMA, identify_trials, k_cr_table2
from rig.kinematics import detect_steps
from rig.cli import app
from rig.data import write_csv
from rig.model.paper import TABLE2
from rig.model.spec import FrictionModel


BOUNDARY = FrictionModel.for_lubricant("boundary", 0.12)
DRY = FrictionModel.for_lubricant("dry", 0.15)


@pytest.fixture(scope="module")
def boundary_25hz():
    return [synth.generate(BOUNDARY, synth.paper_step_protocol(), seed=s, rate_hz=25.0) for s in (11, 12, 13)]


def test_recovery_25hz_boundary(boundary_25hz):
    idn = identify_trials([r.trial for r in boundary_25hz], directions="up")
    rep = idn.report()
    assert rep["n_steps"] == 9 and rep["sem_over"] == "trials"
    m, e = rep["mean"], rep["sem"]
    # within the paper's standard errors (Table 2) of the true values
    assert abs(m["A_mu"] - 1.1e-3) < 0.1e-3
    assert abs(m["B_mu"] - 4.0e-3) < 0.4e-3
    assert abs(m["L_um"] - 19.2) < 1.4
    assert all(e[k] > 0 for k in ("A_mu", "B_mu", "L_um"))
    # the whole-record fit: within 4 of its own (autocorrelation-corrected) errors
    for w in rep["whole_record"]:
        for k, true in (("A_mu", 1.1e-3), ("B_mu", 4.0e-3), ("L_um", 19.2)):
            assert abs(w["params"][k] - true) < 4 * w["err_corr"][k] + 0.02 * true, (k, w["params"][k])


def test_recovery_25hz_dry_uneven_sampling():
    rec = synth.generate(DRY, synth.paper_step_protocol(pre_um=400, back_um=400), seed=21, rate_hz=25.0,
                         jitter=0.6, gaps=6)
    idn = identify_trials([rec.trial], use_events=False)
    rep = idn.report()
    assert rep["n_steps"] == 6  # three up, three down
    assert abs(rep["mean"]["A_mu"] - 2.8e-3) < 0.5e-3
    assert abs(rep["mean"]["B_mu"] - 9.4e-3) < 1.1e-3
    assert abs(rep["mean"]["L_um"] - 64.7) < 14.3
    w = rep["whole_record"]
    assert abs(w["params"]["L_um"] - 64.7) < 0.1 * 64.7


def test_recovery_1khz():
    rec = synth.generate(BOUNDARY, synth.paper_step_protocol(highs=(5.0, 10.0), pre_um=150, back_um=150),
                         seed=31, rate_hz=1000.0)
    assert len(rec.trial) > 500_000
    idn = identify_trials([rec.trial], directions="up")
    rep = idn.report()
    assert rep["n_steps"] == 2
    assert abs(rep["mean"]["A_mu"] - 1.1e-3) < 0.15e-3
    assert abs(rep["mean"]["B_mu"] - 4.0e-3) < 0.4e-3
    assert abs(rep["mean"]["L_um"] - 19.2) < 1.4
    w = rep["whole_record"]
    assert abs(w["params"]["B_mu"] - 4.0e-3) < 0.2e-3
    assert w["decimation"] > 1


@pytest.mark.parametrize("use_events", [True, False])
def test_step_detection_with_and_without_events(use_events):
    rec = synth.generate(BOUNDARY, synth.stribeck_protocol(velocities=(1, 2, 5, 10, 20, 50, 100)), seed=3,
                         jitter=0.5, gaps=4)
    steps = detect_steps(rec.trial, use_events=use_events)
    truth = rec.truth["events"]
    assert len(steps) == len(truth) == 12
    for s, e in zip(steps, truth):
        assert abs(s.t_s - e["t_s"]) < 0.3
        assert s.v1_um_s == pytest.approx(e["v1_um_s"], rel=0.05)
        assert s.v2_um_s == pytest.approx(e["v2_um_s"], rel=0.05)
        assert s.source == ("events" if use_events else "data")
    assert {s.direction for s in steps} == {"up", "down"}


def test_no_false_steps_in_constant_velocity():
    rec = synth.generate(BOUNDARY, [synth.Segment(2.0, 600.0)], seed=4)
    assert detect_steps(rec.trial, use_events=False) == []


def test_k_cr_reproduces_table2():
    for name, row in TABLE2.items():
        k, sk = k_cr_table2(row["A_mu"][0], row["A_mu"][1], row["B_mu"][0], row["B_mu"][1], row["L_um"][0],
                            row["L_um"][1], 100.0)
        assert k == pytest.approx(row["k_cr_kN_per_m"][0], rel=0.05), name
        assert sk == pytest.approx(row["k_cr_kN_per_m"][1], rel=0.05), name


def test_cli_json_keys_exactly_per_spec(tmp_path, boundary_25hz):
    csv = tmp_path / "trial.csv"
    write_csv(boundary_25hz[0].trial, csv)
    out = tmp_path / "id.json"
    png = tmp_path / "id.png"
    res = CliRunner().invoke(app, ["identify", str(csv), "--json", str(out), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["schema"] == SCHEMA == "rig.identify/1"
    for key in ("schema", "steps", "mean", "sem"):
        assert key in rep
    for s in rep["steps"]:
        for key in ("t_s", "v1_um_s", "v2_um_s", "A_mu", "B_mu", "L_um", "r2", "window_um"):
            assert key in s
        assert s["window_um"] in (50, 100, 250)
    for part in ("mean", "sem"):
        assert set(("A_mu", "B_mu", "L_um", "k_cr_kN_per_m")) <= set(rep[part])
    m = rep["mean"]
    assert m["k_cr_kN_per_m"] == pytest.approx((m["B_mu"] - m["A_mu"]) * 100 / m["L_um"] * 1e3, rel=1e-4)
    assert png.stat().st_size > 10_000
    assert "whole_record" in rep


def test_cli_bad_input(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("# rig-trial-csv: 1\ntime_s,position_um\n0,0\n")
    out = tmp_path / "x.json"
    res = CliRunner().invoke(app, ["identify", str(bad), "--json", str(out)])
    assert res.exit_code != 0
    assert "friction_N" in res.output and "bad.csv" in res.output
    assert not out.exists()


def test_cli_no_steps(tmp_path):
    rec = synth.generate(BOUNDARY, [synth.Segment(2.0, 200.0)], seed=4)
    csv = tmp_path / "flat.csv"
    write_csv(rec.trial, csv)
    out = tmp_path / "x.json"
    res = CliRunner().invoke(app, ["identify", str(csv), "--json", str(out)])
    assert res.exit_code == 2  # a record with no velocity step is input identify cannot use (rig.commands.common)
    assert "no velocity steps" in res.output
    assert not out.exists()


def test_several_files_mean_over_trials(tmp_path, boundary_25hz):
    paths = []
    for k, r in enumerate(boundary_25hz):
        p = tmp_path / f"t{k}.csv"
        write_csv(r.trial, p)
        paths.append(str(p))
    out = tmp_path / "all.json"
    res = CliRunner().invoke(app, ["identify", *paths, "--json", str(out), "--no-whole", "--direction", "up"])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["sem_over"] == "trials" and rep["n_trials"] == 3 and len(rep["per_trial"]) == 3
    assert {s["trial"] for s in rep["steps"]} == {0, 1, 2}
    assert math.isclose(rep["mean"]["A_mu"], float(np.mean([t["A_mu"] for t in rep["per_trial"]])), rel_tol=1e-4)


def test_measured_normals_are_used():
    rec = synth.generate(BOUNDARY, synth.paper_step_protocol(highs=(10.0,)), seed=5, rate_hz=25.0)
    tr = rec.trial
    # normals 10 % low on one rider: mu must follow the measured normals
    tr.normal_1_N = tr.normal_1_N * 0.9
    tr.friction_N = tr.friction_N * (tr.normal_1_N + tr.normal_2_N) / (tr.normal_1_N / 0.9 + tr.normal_2_N)
    rep = identify_trials([tr], whole_record=False, directions="up").report()
    assert abs(rep["mean"]["B_mu"] - 4.0e-3) < 0.6e-3
