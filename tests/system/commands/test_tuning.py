"""Loop tuning: the square and sine_sweep segments, the H1 estimate, `rig tune step|frf|autotune`
on a simulated sweep (measured vs rig stability's loop model, the plant fit, gains within 15 %
of the analytic advice, the overlay profile)."""

from __future__ import annotations

import json

import pytest
import yaml
from typer.testing import CliRunner

from rig.cli import app
from rig.config.profile import load_profile


def test_autotune_from_the_sweep_log_writes_an_overlay_near_the_advice(sweep_log, repo_root):
    out = sweep_log / "gains.yaml"
    prof = repo_root / "config" / "rigs" / "emulated.yaml"
    res = CliRunner().invoke(app, ["tune", "autotune", "--hardware", str(prof), "--from-log",
                                   str(sweep_log / "tune.mcap"), "-o", str(out), "--json", str(sweep_log / "at.json")])
    assert res.exit_code == 0, res.output
    doc = json.loads((sweep_log / "at.json").read_text())
    assert all(abs(v) < 0.15 for v in doc["relative_difference"].values()), doc["relative_difference"]
    assert doc["proposed"]["margin_to_k_cr"] > 2.0
    text = yaml.safe_load(out.read_text())
    assert "extends" in text and set(text["controller"]) == {"kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um",
                                                             "ff1_N_s_per_um"}
    tuned = load_profile(out)
    assert tuned.controller.kp_N_per_um == pytest.approx(doc["proposed"]["kp_N_per_um"], rel=1e-3)
    assert tuned.hardware is not None and tuned.actuator == load_profile(prof).actuator   # the rest inherited
    # never in place; bad input is one error
    r2 = CliRunner().invoke(app, ["tune", "autotune", "--hardware", str(out), "--from-log",
                                  str(sweep_log / "tune.mcap"), "-o", str(out)])
    assert r2.exit_code == 2 and "never in place" in r2.output
    r3 = CliRunner().invoke(app, ["tune", "frf", str(repo_root / "tests" / "data" / "v1-sim-1khz.mcap")])
    assert r3.exit_code == 2 and "Traceback" not in r3.output
