"""Stability: eq. (8) in the fixture's force units, eq. (13) (Table 2), the A = 0 case, the
rig's discrete PID loop (1 kHz, ZOH), and the full simulated rig on either side of the
loop's k_cr (short; the dense scan is benchmarks/bench_stability.py)."""

from __future__ import annotations

import json

import numpy as np
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


def _prof():
    from rig.config.profile import default_profile_path, load_profile

    return load_profile(default_profile_path())


def test_loop_analysis_reduces_to_eq8_for_fig1_pd():
    """Fig. 1's system with a PD: continuous-time roots give eq. (8) exactly; the rig's
    1 kHz sampling (ZOH, backward-difference D) changes it by < 0.1 %."""
    for name in ("dry", "boundary"):
        row = TABLE2[name]
        A, B, L = row["A_mu"][0], row["B_mu"][0], row["L_um"][0]
        k8 = S.k_cr_eq8_N_per_um(A, B, L, 100.0, 10.0, 0.003, 1.0)
        for dt, tol in ((0.0, 1e-3), (1e-3, 1e-3)):
            lm = S.LoopModel(A_N=200 * A, B_N=200 * B, L_um=L, mass_kg=10.0, kd_N_s_per_um=0.003, dt_s=dt)
            assert S.k_cr_loop(lm) == pytest.approx(k8, rel=tol), (name, dt)


def test_characteristic_polynomial_of_the_discrete_pid_loop():
    lm = S.LoopModel(A_N=0.22, B_N=0.8, L_um=19.2, ki_N_per_um_s=5.0, dt_s=1e-3)
    M = S.closed_loop_matrix(lm, 0.05)
    c = S.characteristic_polynomial(lm, 0.05)
    assert c.size == M.shape[0] + 1 == 3 + 1 + 1 + 1  # plant (x, v, theta), e_{n-1}, integral sum
    assert np.allclose(np.sort_complex(np.roots(c)), np.sort_complex(np.linalg.eigvals(M)), atol=1e-6)


def test_integral_term_raises_k_cr():
    """Finding 2: with the paper's Fig. 1 plant the I term raises k_cr (boundary 30 -> ~47 kN/m);
    on the rig's plant it raises boundary's and paraffin's, and removes dry's (stable at
    every kp: the compliance of the test piece damps the I-friction mode)."""
    lm_pd = S.LoopModel(A_N=0.22, B_N=0.8, L_um=19.2, dt_s=1e-3)
    lm_pid = S.LoopModel(A_N=0.22, B_N=0.8, L_um=19.2, ki_N_per_um_s=5.0, dt_s=1e-3)
    assert S.k_cr_loop(lm_pid) > 1.4 * S.k_cr_loop(lm_pd)
    prof = _prof()
    k = {n: S.k_cr_loop(S.LoopModel.from_profile(prof, prof.friction_model(n))) for n in TABLE2}
    assert k["dry"] == 0.0
    assert 0.055 < k["boundary"] < 0.065 and 0.16 < k["paraffin"] < 0.20


def test_fixture_statement_doubles_table2():
    s = S.fixture_statement(1.1e-3, 4.0e-3, 19.2)
    assert "30.21 kN/m" in s and "15.1 kN/m" in s
    # eq. (13) of these values, not "the paper's" (Table 2 prints 14.8 for boundary's means)
    assert "paper's" not in s and "N = 100 N" in s


@pytest.mark.parametrize("ki, lub", [(5.0, "boundary"), (0.0, "paraffin")])
def test_simulated_rig_stick_slips_below_and_slides_above_the_loop_k_cr(ki, lub):
    """The full simulated rig at 0.8 and 1.25 x the loop analysis' k_cr (criterion of
    stability.sliding_run). The dense scan is benchmarks/bench_stability.py."""
    prof = _prof()
    lm = S.LoopModel.from_profile(prof, prof.friction_model(lub), ki_N_per_um_s=ki)
    k = S.k_cr_loop(lm)
    dur = S.scan_duration_s(lm, k)
    below = S.sliding_run(None, lub, 0.8 * k, ki, prof.controller.kd_N_s_per_um, dur)
    above = S.sliding_run(None, lub, 1.25 * k, ki, prof.controller.kd_N_s_per_um, dur)
    assert below["stick_slip"] and below["spread"] > 2 * S.SPREAD_MAX
    assert not above["stick_slip"] and above["stuck_fraction"] == 0.0


def test_cli(tmp_path):
    out = tmp_path / "s.json"
    res = CliRunner().invoke(app, ["stability", "--lubricant", "boundary", "--margin", "3", "--json", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    a = doc["analyses"]["boundary"]
    assert a["k_cr_loop_PID_kN_per_m"] == pytest.approx(59.4, rel=0.02)
    assert a["kp_min_N_per_um"] == pytest.approx(3 * a["k_cr_loop_PID_kN_per_m"] * 1e-3)
    assert "moving test piece" in a["statement"] and "moving test piece" in res.output
    res = CliRunner().invoke(app, ["stability", "--lubricant", "boundary", "--plot", str(tmp_path / "m.png")])
    assert res.exit_code != 0 and "--simulate" in res.output


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


def test_the_simulated_boundary_is_reported_as_its_bracket_not_a_point():
    """A scan resolves the boundary only to [the highest kp that stick-slips, the next that slides]: the
    result is that bracket against the analysis, whatever the true boundary inside it (no "+0.0 %")."""
    true_k = {}

    def run(ppath, lub, kp, ki, kd, dur, v0, seed, bump, noise):
        return {"kp_N_per_um": kp, "stick_slip": kp < true_k["k"], "spread": 1.0 if kp < true_k["k"] else 0.01}

    lm = S.LoopModel.from_profile(*_profile_and_model("boundary"), V0_um_s=1.0)
    k_lin = S.k_cr_loop(lm)
    for true in (0.97 * k_lin, 1.03 * k_lin):  # either side of the analysis: the same bracket
        true_k["k"] = true
        r = S.scan_boundary("boundary", run=run, factors=(0.8, 0.9, 0.95, 1.05, 1.1, 1.25), duration_s=1.0)
        assert "k_sim_N_per_um" not in r
        assert r["bracket_N_per_um"] == pytest.approx([0.95 * k_lin, 1.05 * k_lin])
        assert r["rel_bracket"] == pytest.approx([-0.05, 0.05]) and r["analysis_in_bracket"] is True


def _profile_and_model(lub):
    from rig.config.profile import default_profile_path, load_profile

    prof = load_profile(default_profile_path())
    return prof, prof.friction_model(lub)
