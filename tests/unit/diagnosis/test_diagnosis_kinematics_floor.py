"""The summary says which of the final model's errors are the kinematics floor's (issue 20, Deliver 6):
a disagreement with identify's whole-record fit, not the fit's own."""

from rig.commands.diagnose import summary


def _rep(**extra):
    params = {"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 20.1}
    return {"data": "x.mcap", "baseline": {"model": "rate_state", "params": params, "holdout_rms_N": 0.04},
            "findings": [], "unexplained": [], "holdout_rms_N": 0.04, "warnings": [],
            "model": {"baseline": "rate_state", "extensions": [], "params": params,
                      "params_sd": {"mu0": 2e-5, "A_mu": 8e-5, "B_mu": 3e-5, "L_um": 1.0}}, **extra}


def test_the_summary_names_the_errors_the_kinematics_floor_set():
    text = summary(_rep(_kinematics=["A_mu", "L_um"]))
    line = [ln for ln in text.splitlines() if "identify's whole-record fit" in ln]
    assert len(line) == 1 and "A_mu, L_um" in line[0]


def test_without_the_floor_the_summary_says_nothing_of_it():
    assert "identify's whole-record fit" not in summary(_rep(_kinematics=[]))
    assert "identify's whole-record fit" not in summary(_rep())
