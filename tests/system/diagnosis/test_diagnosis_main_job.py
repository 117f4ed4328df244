"""The main job (README: `rig run config/recipes/velocity-steps.yaml --sim`, then `rig export`) diagnosed.

A shorter recipe with the same physics as config/recipes/velocity-steps.yaml (boundary
lubricant, profile A_mu 1.1e-3, B_mu 4.0e-3, L 19.2 µm; steps from 1 µm/s after 6 L of
slip, the return at 100 µm/s and the 2 s rest before each step) runs on the simulated rig;
the trial is exported at the 25 Hz log rate and at the raw 1 kHz loop rate. `rig diagnose`
must give the same causes at both rates, nothing beyond the rig's own compliance (its
fixture, 10 N/µm = 10,000 kN/m, between the LVDT and the interface), and A and B within
30 % of the profile. Measured (full recipe): 25 Hz A 1.02e-3, B 3.99e-3, L 20.3 µm; 1 kHz
A 1.16e-3, B 4.11e-3, L 19.6 µm; no finding at either rate.
"""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.cli import app


RECIPE = """\
name: velocity-steps-short
description: two of the main job's steps (1->5, 1->10 um/s), same physics
lubricant: boundary
normal_force_N: 100
seed: 3
accel_um_s2: 20
log:
  raw_rate_hz: 1000
  decimated_rate_hz: 25
segments:
  - kind: hold
    duration_s: 2
  - kind: velocity_steps
    return_speed_um_s: 100
    hold_s: 2
    steps:
      - {v1_um_s: 1, v2_um_s: 5, slip_after_um: 250}
      - {v1_um_s: 1, v2_um_s: 10, slip_after_um: 400}
"""

PROFILE = {"A_mu": 1.1e-3, "B_mu": 4.0e-3}
RIG_OWN_KN_PER_M = 10_000.0  # config/rigs/sim.yaml fixture_stiffness_N_per_um: 10


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mainjob")
    recipe = tmp / "steps.yaml"
    recipe.write_text(RECIPE)
    run = CliRunner().invoke(app, ["run", str(recipe), "--sim", "--out", str(tmp / "T.mcap"), "-q"])
    assert run.exit_code == 0, run.output
    out = {}
    for rate in ("25", "raw"):
        csv = tmp / f"T-{rate}.csv"
        ex = CliRunner().invoke(app, ["export", str(tmp / "T.mcap"), "--csv", str(csv), "--rate", rate, "--no-extra"])
        assert ex.exit_code == 0, ex.output
        js = tmp / f"d-{rate}.json"
        res = CliRunner().invoke(app, ["diagnose", str(csv), "--json", str(js)])
        assert res.exit_code == 0, res.output
        out[rate] = json.loads(js.read_text())
    return out


def test_same_causes_at_25_hz_and_1_khz(reports):
    causes = {rate: [f["cause"] for f in rep["findings"]] for rate, rep in reports.items()}
    assert causes["25"] == causes["raw"], causes
    # nothing beyond the rig's own compliance
    assert set(causes["25"]) <= {"finite_stiffness"}, causes
    for rep in reports.values():
        assert rep["unexplained"] == []
        for f in rep["findings"]:
            k = f["params"]["stiffness_kN_per_m"]
            assert RIG_OWN_KN_PER_M / 3 < k < RIG_OWN_KN_PER_M * 3, k


@pytest.mark.parametrize("rate", ["25", "raw"])
def test_a_and_b_within_30_pct_of_the_profile(reports, rate):
    p = reports[rate]["model"]["params"]
    for name, truth in PROFILE.items():
        assert abs(p[name] - truth) <= 0.3 * truth, (rate, name, p[name], truth)
