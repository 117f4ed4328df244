"""Stability: eq. (8) in the fixture's force units, eq. (13) (Table 2), the A = 0 case,
and the simulated boundary of Fig. 1's system against eq. (8) (reduced, fast version;
the full sweep is benchmarks/bench_identify_stability.py)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.analysis import stability as S
from rig.cli import app
from rig.model.paper import TABLE2
from rig.model.spec import FrictionModel


def test_eq13_reproduces_table2_and_eq8_reduces_to_it():
    for name, row in TABLE2.items():
        a = S.analyse(S.StabilityInputs(row["A_mu"][0], row["B_mu"][0], row["L_um"][0], 100.0, mass_kg=1e-9,
                                        kd_N_s_per_um=0.0), margin=2.0)
        assert a["k_cr_eq13_kN_per_m"] == pytest.approx(row["k_cr_kN_per_m"][0], rel=0.03)  # 15.1 vs 14.8
        if row["A_mu"][0] > 0:
            # quasi-static, kd = 0: eq. (8) = eq. (13) with the fixture's 2 N
            assert a["k_cr_eq8_kN_per_m"] == pytest.approx(2 * a["k_cr_eq13_kN_per_m"], rel=1e-6)
            assert a["kp_min_N_per_um"] == pytest.approx(2 * a["k_cr_eq8_N_per_um"], rel=1e-9)
        else:
            assert a["k_cr_eq8_kN_per_m"] is None  # A + kv V0 = 0: no finite k_cr
            assert "no finite" in a["advice"]


def test_mass_and_damping_terms():
    # kd lowers k_cr (B - A - kv V0); the mass term raises it, through 1 + m V0^2/((A + kv V0) L)
    base = S.k_cr_eq8_N_per_um(1.1e-3, 4e-3, 19.2, 100.0, 10.0, 0.0, 1.0)
    with_kd = S.k_cr_eq8_N_per_um(1.1e-3, 4e-3, 19.2, 100.0, 10.0, 0.1, 1.0)
    heavy = S.k_cr_eq8_N_per_um(1.1e-3, 4e-3, 19.2, 100.0, 1e7, 0.0, 1.0)
    assert with_kd < base < heavy
    qs = 2 * 100 * (4e-3 - 1.1e-3) / 19.2
    assert heavy == pytest.approx(qs * (1 + 1e7 * 1e-12 / (0.22 * 19.2e-6)), rel=1e-9)


def test_paraffin_regularised_law_has_an_effective_A():
    m = FrictionModel.for_lubricant("paraffin", 0.12)
    a_eff = S.effective_A_mu(m, 1.0)
    assert 0 < a_eff < 2e-5  # mu v_reg^2 / V0^2 = 0.12 x 1e-4
    b = FrictionModel.for_lubricant("boundary", 0.12)
    assert S.effective_A_mu(b, 1.0) == pytest.approx(1.1e-3, rel=1e-6)


@pytest.mark.parametrize("name", ["boundary", "paraffin"])
def test_simulated_boundary_matches_eq8(name):
    r = S.check_lubricant(name, iters=7, periods=20.0)
    assert r["k_sim_N_per_um"] is not None
    assert abs(r["rel_diff"]) < 0.05
    # the bracket is real: below it grows, above it decays
    runs = sorted(r["runs"], key=lambda x: x["kp_N_per_um"])
    assert runs[0]["growth_rate_per_s"] > 0 and runs[-1]["growth_rate_per_s"] < 0


def test_cli(tmp_path):
    out, png = tmp_path / "s.json", tmp_path / "s.png"
    res = CliRunner().invoke(app, ["stability", "--lubricant", "boundary", "--margin", "3", "--simulate",
                                   "--json", str(out), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    a = doc["analyses"]["boundary"]
    assert a["kp_min_N_per_um"] == pytest.approx(3 * a["k_cr_eq8_N_per_um"])
    assert abs(doc["checks"][0]["rel_diff"]) < 0.05
    assert png.stat().st_size > 10_000


def test_cli_params_from_identify_json(tmp_path):
    rep = {"schema": "rig.identify/1", "steps": [], "mean": {"A_mu": 1e-3, "B_mu": 5e-3, "L_um": 20.0},
           "sem": {}, "normal_force_N": 100.0}
    p = tmp_path / "id.json"
    p.write_text(json.dumps(rep))
    res = CliRunner().invoke(app, ["stability", "--params", str(p), "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 0, res.output
    a = json.loads((tmp_path / "o.json").read_text())["analyses"]["id"]
    assert a["k_cr_eq13_kN_per_m"] == pytest.approx(20.0)


def test_cli_bad_input(tmp_path):
    res = CliRunner().invoke(app, ["stability", "--lubricant", "honey"])
    assert res.exit_code != 0 and "honey" in res.output
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    res = CliRunner().invoke(app, ["stability", "--params", str(bad)])
    assert res.exit_code != 0 and "bad.json" in res.output


def test_full_rig_boundary_agrees_with_eq8_plus_leakage():
    """The full simulated rig (PD) against eq. (8): the actuator's leakage acts as extra
    derivative gain; with it the boundary agrees within 5 %."""
    from rig.analysis.simrun import SIM_AVAILABLE

    if not SIM_AVAILABLE:
        pytest.skip("simulated rig not available")
    r = S.full_rig_boundary("boundary", iters=6)
    assert r["k_sim_N_per_um"] is not None
    assert abs(r["k_sim_N_per_um"] / r["k_cr_eq8_with_leak_N_per_um"] - 1) < 0.05
    assert abs(r["rel_diff"]) < 0.05
