"""`rig export --elastic-correction K|fit`: interface_slip_um = position - friction / k, with k
given, from the file's machine_stiffness_kN_per_m, or from the whole-record fit (a synthetic
load-point record of known stiffness)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.cli import app
from rig.data import read_csv
from rig.log import write_trial_data
from rig.model.spec import FrictionModel
from rig.sim.synth import generate, paper_step_protocol


K_TRUE_KN_PER_M = 100.0


@pytest.fixture(scope="module")
def load_point_log(tmp_path_factory):
    fm = FrictionModel(extensions=["finite_stiffness"],
                       params={"mu0": 0.1, "A_mu": 0.0011, "B_mu": 0.004, "L_um": 19.2,
                               "stiffness_kN_per_m": K_TRUE_KN_PER_M})
    rec = generate(fm, paper_step_protocol(highs=(10.0,), pre_um=150.0), seed=3)
    rec.trial.metadata["position_source"] = "load_point"
    d = tmp_path_factory.mktemp("ec")
    write_trial_data(rec.trial, d / "lp.mcap")
    rec.trial.metadata["machine_stiffness_kN_per_m"] = "80"
    write_trial_data(rec.trial, d / "lp-known.mcap")
    rec.trial.metadata["machine_stiffness_kN_per_m"] = "stiff"
    write_trial_data(rec.trial, d / "lp-bad.mcap")
    # the same step with no spring: the position is the interface's, no stiffness to find
    rigid = generate(FrictionModel(params={"mu0": 0.1, "A_mu": 0.0011, "B_mu": 0.004, "L_um": 19.2}),
                     paper_step_protocol(highs=(10.0,), pre_um=150.0), seed=3)
    write_trial_data(rigid.trial, d / "rigid.mcap")
    return d


def _export(path, out, arg):
    res = CliRunner().invoke(app, ["export", str(path), "-o", str(out), "--elastic-correction", arg])
    return res, res.output


def test_fit_recovers_the_stiffness_and_writes_interface_slip(load_point_log):
    res, text = _export(load_point_log / "lp.mcap", load_point_log / "fit.csv", "fit")
    assert res.exit_code == 0, text
    tr = read_csv(load_point_log / "fit.csv")
    k = float(tr.metadata["elastic_correction_kN_per_m"])
    assert k == pytest.approx(K_TRUE_KN_PER_M, rel=0.1)
    assert "whole-record fit" in tr.metadata["elastic_correction_source"]
    slip = tr.extra["interface_slip_um"]
    assert np.allclose(slip, tr.position_um - tr.friction_N / (k * 1e-3), atol=1e-4)
    # the interface lags the load point by the spring's stretch, F / k (about 200 µm here)
    assert np.median(tr.position_um - slip) == pytest.approx(np.median(tr.friction_N) / (k * 1e-3), rel=1e-6)


def test_metadata_stiffness_and_a_given_one_are_used_as_they_are(load_point_log):
    res, text = _export(load_point_log / "lp-known.mcap", load_point_log / "known.csv", "fit")
    assert res.exit_code == 0, text
    tr = read_csv(load_point_log / "known.csv")
    assert tr.metadata["elastic_correction_kN_per_m"] == "80"
    assert tr.metadata["elastic_correction_source"] == "machine_stiffness_kN_per_m metadata"
    res, text = _export(load_point_log / "lp.mcap", load_point_log / "given.csv", "250")
    assert res.exit_code == 0, text
    tr = read_csv(load_point_log / "given.csv")
    assert np.allclose(tr.extra["interface_slip_um"], tr.position_um - tr.friction_N / 0.25, atol=1e-4)


@pytest.mark.parametrize("arg", ["-5", "abc", "nan", "0"])
def test_bad_flag_is_one_error_and_no_file(load_point_log, arg):
    out = load_point_log / f"bad{arg}.csv"
    res, text = _export(load_point_log / "lp.mcap", out, arg)
    assert res.exit_code == 2 and "--elastic-correction" in text and "Traceback" not in text
    assert not out.exists()


def test_a_bad_metadata_stiffness_is_named(load_point_log):
    out = load_point_log / "badmeta.csv"
    res, text = _export(load_point_log / "lp-bad.mcap", out, "fit")
    assert res.exit_code == 2 and "machine_stiffness_kN_per_m metadata 'stiff'" in text and "kN/m" in text
    assert not out.exists()


def test_fit_on_a_record_without_compliance_is_refused_not_a_number_on_a_bound(load_point_log):
    """A position measured at the interface: the fit's stiffness runs off to a bound or to a value
    its s.e. dwarfs; that is no stiffness, so 'fit' is one error saying so, and no file."""
    out = load_point_log / "rigid.csv"
    res, text = _export(load_point_log / "rigid.mcap", out, "fit")
    assert res.exit_code == 2 and "does not determine" in text and "give the stiffness" in text and "Traceback" not in text, text
    assert not out.exists()
