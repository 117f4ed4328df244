"""Table 2 reproduced on the full simulated rig: 8 trials per lubricant."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.analysis.identify import k_cr_table2
from rig.analysis.reproduce import reproduce
from rig.cli import app


@pytest.fixture(scope="module")
def rep():
    return reproduce(8, seed=0)


@pytest.mark.parametrize("lub", ["dry", "paraffin", "boundary"])
def test_recovered_within_paper_sem_of_truth(rep, lub):
    r = rep["lubricants"][lub]
    # no draw is rejected: a draw the rig cannot slide steadily (flagged: fixture k_cr above
    # half of kp) may stick-slip and not be identified; every other trial is
    unflagged = [t for t in r["trials"] if not t["k_cr_over_half_kp"]]
    assert all(t["n_steps"] > 0 for t in unflagged)
    assert r["n_trials_identified"] >= len(unflagged) >= 6
    for k, c in r["checks"].items():
        assert c["ok"], (lub, k, c)


@pytest.mark.parametrize("lub", ["dry", "paraffin", "boundary"])
def test_k_cr_column_is_eq13(rep, lub):
    m, e = rep["lubricants"][lub]["recovered"]["mean"], rep["lubricants"][lub]["recovered"]["sem"]
    k, sk = k_cr_table2(m["A_mu"], e["A_mu"], m["B_mu"], e["B_mu"], m["L_um"], e["L_um"], 100.0)
    assert m["k_cr_kN_per_m"] == pytest.approx((m["B_mu"] - m["A_mu"]) * 100.0 / m["L_um"] * 1e3, rel=1e-4)
    assert e["k_cr_kN_per_m"] == pytest.approx(sk, rel=1e-3)


def test_trial_spread_matches_table2(rep):
    # the drawn values scatter like Table 2's trials: sem of the truth of the order of the paper's
    for lub in ("dry", "boundary"):
        r = rep["lubricants"][lub]
        for k in ("B_mu", "L_um"):
            assert 0.3 < r["truth"]["sem"][k] / r["paper"][k]["sem"] < 2.0, (lub, k)


def test_cli_synth_engine(tmp_path):
    out = tmp_path / "r.json"
    res = CliRunner().invoke(app, ["reproduce", "--trials", "2", "--lubricant", "boundary", "--engine", "synth",
                                   "--json", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["schema"] == "rig.reproduce/1"
    assert "Table 2" in res.output and "boundary" in res.output


def test_draws_keep_table2_means_without_rejection():
    import math

    import numpy as np

    from rig.analysis.reproduce import PAPER_MIN_TRIALS, draw_trial_params
    from rig.model.paper import TABLE2

    rng = np.random.default_rng(7)
    for lub in ("dry", "boundary"):
        d = draw_trial_params(lub, 20000, rng, kp_max_N_per_um=0.5)
        assert len(d) == 20000
        for k in ("A_mu", "B_mu", "L_um"):
            x = np.array([t[k] for t in d])
            mean, sem = TABLE2[lub][k]
            assert np.all(x > 0)
            assert x.mean() == pytest.approx(mean, rel=0.01), (lub, k)
            assert x.std() == pytest.approx(sem * math.sqrt(PAPER_MIN_TRIALS), rel=0.05), (lub, k)


@pytest.mark.parametrize("lub", ["dry", "paraffin", "boundary"])
def test_identification_bias_is_reported(rep, lub):
    b = rep["lubricants"][lub]["bias"]
    for k in ("A_mu", "B_mu", "L_um"):
        assert set(b[k]) >= {"recovered_vs_true_rel", "recovered_vs_true_rel_sem", "vs_paper_z"}
    # B and L are recovered within 5 % of the trials' own values (dry L: the last window
    # still holds 2 % of the decay, docs/paper.md row 5), except paraffin's B: measured
    # -5.6 +- 0.9 % (8 trials, seed 0; -5.3 +- 0.2 % over 8 noise seeds at Table 2's means).
    # Of that, -1.6 % is the method's own (all sensor noise off) and about -3.7 % is physical:
    # the LVDT noise, fed back by the PID, shakes the interface (true slip-velocity sd 0.57
    # um/s at 1 um/s, 0.11 without LVDT noise); a rate-state interface shaken that way has a
    # lower mean friction than mu_ss(V), more at low V (-15e-4 in mu at 1 um/s, -6.5e-4 at
    # 10 um/s net of the noise-free offset), so the steady-state difference across a step
    # shrinks and B - A comes out low. Paraffin (A = 2e-4: almost no direct-effect damping) is
    # shaken most. docs/paper.md row 5. Tolerance: the measured bias + 2 s.e.
    tol_B = 0.08 if lub == "paraffin" else 0.05
    assert abs(b["B_mu"]["recovered_vs_true_rel"]) < tol_B
    assert abs(b["L_um"]["recovered_vs_true_rel"]) < 0.06
