"""The `rig diagnose` command: JSON report to the letter of diagnosis.md, PNG, model YAML, bad input."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
from typer.testing import CliRunner

from rig.cli import app
from rig.data import write_csv
from rig.sim.synth import SynthSpec, make_record, random_effect
from rig.model.spec import FrictionModel


def test_cli_report_plot_model(tmp_path):
    rng = np.random.default_rng(3)
    eff = {"position_periodic": random_effect("position_periodic", rng)}
    trial, truth = make_record(SynthSpec(rate_hz=25.0, effects=eff, seed=3, duration_s=600.0, protocol="varied"))
    csv = write_csv(trial, tmp_path / "trial.csv")
    js, png, yml = tmp_path / "r.json", tmp_path / "r.png", tmp_path / "m.yaml"
    res = CliRunner().invoke(app, ["diagnose", str(csv), "--json", str(js), "--plot", str(png),
                                   "--model-out", str(yml)])
    assert res.exit_code == 0, res.output
    assert "position_periodic" in res.output
    rep = json.loads(js.read_text())
    assert set(rep) - {"warnings"} == {"schema", "data", "baseline", "findings", "unexplained", "model", "holdout_rms_N"}
    assert rep["schema"] == "rig.diagnosis/1"
    # the spec's keys, and only its optional additive ones (plus the A-B-L correlation of issue 20)
    optional = {"params_sd", "intervals", "correlation"}
    assert {"model", "params", "holdout_rms_N"} <= set(rep["baseline"]) <= {"model", "params", "holdout_rms_N"} | optional
    assert set(rep["baseline"]["params_sd"]) == set(rep["baseline"]["params"])
    assert rep["baseline"]["intervals"]["L_um"][0] < rep["baseline"]["params"]["L_um"] < rep["baseline"]["intervals"]["L_um"][1]
    assert all(-1.0 <= c <= 1.0 for c in rep["baseline"]["correlation"].values())
    f = rep["findings"][0]
    required = {"cause", "params", "evidence", "holdout_rms_N_before", "holdout_rms_N_after", "gain_pct", "delta_bic"}
    assert required <= set(f) <= required | optional | {"stability", "alternatives"}
    assert 0.5 < f["stability"] <= 1.0
    # a finding's parameters are the final model's
    assert all(rep["model"]["params"][k] == v for k, v in f["params"].items())
    assert "final model: rate_state + position_periodic" in res.output
    assert set(f["params"]) == {"amplitude_mu", "wavelength_um"}
    assert abs(f["gain_pct"] - 100 * (f["holdout_rms_N_before"] - f["holdout_rms_N_after"])
               / f["holdout_rms_N_before"]) < 0.05
    assert {"baseline", "extensions", "params"} <= set(rep["model"]) <= {"baseline", "extensions", "params"} | optional
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fm = FrictionModel.from_yaml(yml)
    assert fm.extensions == rep["model"]["extensions"]
    # it says what it wrote; the model is readable as open() makes a file (0666 less the umask)
    assert all(f"wrote {p}" in res.output for p in (js, png, yml))
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(yml.stat().st_mode) == 0o666 & ~umask
    assert abs(fm.params["wavelength_um"] - truth["params"]["wavelength_um"]) < 0.25 * truth["params"]["wavelength_um"]


def test_cli_bad_input(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("# rig-trial-csv: 1\ntime_s,friction_N\n0,1\n")
    js = tmp_path / "out.json"
    res = CliRunner().invoke(app, ["diagnose", str(bad), "--json", str(js)])
    assert res.exit_code != 0
    assert "position_um" in res.output
    assert not js.exists()


def test_cli_bad_mcap(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file\n")
    res = CliRunner().invoke(app, ["diagnose", str(bad), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 2  # bad input (rig.commands.common's exit-code table)
    assert "bad.mcap" in res.output
    assert not (tmp_path / "o.json").exists()


def test_cli_bad_machine_stiffness(tmp_path):
    """A stated machine stiffness that is no positive number: one error naming the key, exit 2,
    nothing written (measured-data.md: machine_stiffness_kN_per_m)."""
    t = np.arange(0.0, 30.0, 0.1)
    rows = "\n".join(f"{a:.2f},{a * 2:.3f},{60 + 0.01 * a:.4f}" for a in t)
    bad = tmp_path / "k.csv"
    bad.write_text("# rig-trial-csv: 1\n# normal_force_N: 100\n# position_source: load_point\n"
                   "# machine_stiffness_kN_per_m: -300\ntime_s,position_um,friction_N\n" + rows + "\n")
    js = tmp_path / "o.json"
    res = CliRunner().invoke(app, ["diagnose", str(bad), "--json", str(js)])
    assert res.exit_code == 2, res.output
    assert "machine_stiffness_kN_per_m" in res.output and "k.csv" in res.output
    assert "Traceback" not in res.output
    assert not js.exists()
