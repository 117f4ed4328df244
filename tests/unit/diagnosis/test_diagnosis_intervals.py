"""Honest intervals for a final model the record does not determine (rig.diagnosis.intervals; issue 20,
items 2 and 7): the hull of every value the profile holds within one error, and the whole searched
domain, said in one sentence, where no profile is computed."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rig.commands.diagnose import summary
from rig.diagnosis import intervals
from rig.diagnosis.fit import param


def _grid(n_bins: int = 10):
    return SimpleNamespace(t=np.arange(n_bins, dtype=float), known={"mu0": 0.5}, stiffness_floor_kN_per_m=50.0,
                           max_state_um=1000.0)


def test_a_second_valley_within_one_error_belongs_to_the_interval():
    vs = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    rise = np.array([0.5, 3.0, 0.0, 2.0, 0.4, 9.0])  # lowest at 3; a second valley at 5 past a rise at 4
    up = intervals._edge(vs, rise, 1.0, [2, 3, 4, 5])
    down = intervals._edge(vs, rise, 1.0, [2, 1, 0])
    assert 5.0 < up < 6.0  # past the second valley, to where it rises through the threshold
    assert down == 1.0     # never rises that far again below: open to the last point held


def test_a_single_valley_crosses_where_the_profile_rises_one_error():
    vs = np.array([1.0, 2.0, 3.0])
    rise = np.array([4.0, 0.0, 4.0])
    assert np.isclose(intervals._edge(vs, rise, 1.0, [1, 2]), 2.5)  # sqrt(rise) linear: half way
    assert np.isclose(intervals._edge(vs, rise, 1.0, [1, 0]), 1.5)


def test_over_the_bin_limit_every_parameter_gets_its_whole_domain_without_a_fit():
    g = _grid(50)
    res = SimpleNamespace(params={"mu0": 0.5, "A_mu": 0.004, "B_mu": 0.003, "L_um": 20.0, "stiffness_kN_per_m": 300.0})
    ivs, whole = intervals.undetermined_intervals(g, res, ["mu0", "A_mu", "B_mu", "L_um", "stiffness_kN_per_m"], 0.2,
                                                  max_bins=10)
    assert "mu0" not in ivs  # the file states it: never an interval
    assert sorted(whole) == sorted(ivs) == ["A_mu", "B_mu", "L_um", "stiffness_kN_per_m"]
    assert ivs["A_mu"] == (param("A_mu", g, spring=True).lo, 0.2)  # the spring's floor of A, the coefficient cap
    assert ivs["B_mu"] == (-0.2, 0.2)
    assert ivs["stiffness_kN_per_m"][0] == 50.0  # the record's stiffness floor
    assert ivs["L_um"][1] == 1000.0              # the longest state the record tells from a drift


def _rep(**extra):
    params = {"mu0": 0.48, "A_mu": 0.0118, "B_mu": -0.0056, "L_um": 834.0, "stiffness_kN_per_m": 483.0}
    iv = {"A_mu": [0.0113, 0.0124], "B_mu": [-0.0065, -0.0048], "L_um": [601.0, 1234.0],
          "stiffness_kN_per_m": [50.0, 1e5]}
    return {"data": "x.csv", "baseline": {"model": "rate_state", "params": params, "holdout_rms_N": 1.3},
            "findings": [], "unexplained": [], "holdout_rms_N": 1.3, "warnings": [],
            "model": {"baseline": "rate_state", "extensions": ["finite_stiffness"], "params": params,
                      "params_sd": {k: (b - a) / 2 for k, (a, b) in iv.items()}, "intervals": iv}, **extra}


def test_the_summary_says_the_errors_are_profiles_and_which_are_the_whole_domain():
    text = summary(_rep(_profiled=["A_mu", "B_mu", "L_um", "stiffness_kN_per_m"],
                        _domain_whole={"stiffness_kN_per_m": "the record has no velocity step"}))
    prof = [ln for ln in text.splitlines() if "profile-likelihood intervals" in ln]
    whole = [ln for ln in text.splitlines() if "whole searched domain" in ln]
    assert len(prof) == 1 and len(whole) == 1
    assert "A_mu, B_mu, L_um are" in prof[0] and "stiffness" not in prof[0]
    assert "stiffness_kN_per_m" in whole[0] and "[50, 1e+05]" in whole[0] and "A_mu" not in whole[0]
    assert "no velocity step" in whole[0]


def test_a_determined_model_says_neither():
    text = summary(_rep())
    assert "profile-likelihood" not in text and "whole searched domain" not in text


def test_a_profile_that_cannot_be_set_up_gives_the_whole_domain(monkeypatch):
    def broken(*a, **k):
        raise KeyError("phase_rad")

    monkeypatch.setattr(intervals, "domain_interval", broken)
    g = _grid(5)
    res = SimpleNamespace(params={"A_mu": 0.004})
    ivs, whole = intervals.undetermined_intervals(g, res, ["A_mu"], 0.2)
    assert whole == ["A_mu"] and ivs["A_mu"] == intervals.whole_domain(g, "A_mu", 0.2)
