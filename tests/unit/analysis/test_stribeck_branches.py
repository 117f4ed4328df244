"""Stribeck curve (section 4.1): levels, up/down branches, eq. (7)'s A - B."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.sim import synth
from rig.analysis.stribeck import stribeck
from rig.cli import app
from rig.data import write_csv
from rig.model.spec import FrictionModel


PARAFFIN = FrictionModel(params={"mu0": 0.12, "A_mu": 2e-4, "B_mu": 0.0111, "L_um": 22.4})
A_MINUS_B = 2e-4 - 0.0111
VELS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)


def _pass_with_hysteresis(seed: int, offset_mu: float):
    """A generated pass; friction on the up branch raised by ``offset_mu`` (Fig. 6's loop)."""
    rec = synth.generate(PARAFFIN, synth.stribeck_protocol(VELS), seed=seed, jitter=0.3)
    tr = rec.trial
    ev = rec.truth["events"]
    t = tr.time_s
    top = max(e["t_s"] for e in ev if e["v2_um_s"] == max(VELS))
    up = t < top + 2.0
    tr.friction_N = tr.friction_N + offset_mu * (tr.normal_1_N + tr.normal_2_N) * up
    return tr


def test_branches_and_a_minus_b_from_data():
    trials = [_pass_with_hysteresis(s, 0.002) for s in (1, 2, 3)]
    rep = stribeck(trials, use_events=False)
    assert rep["level_source"] == ["data"]
    up, down = rep["fit_up"], rep["fit_down"]
    # the maximum velocity is one level in the data (no step between its two halves)
    assert len(rep["branches"]["up"]) == 7 and len(rep["branches"]["down"]) == 6
    assert up["mu0"] - down["mu0"] == pytest.approx(0.002, abs=4e-4)
    for f in (up, down):
        assert abs(f["A_minus_B"] - A_MINUS_B) < max(4 * f["A_minus_B_err"], 3e-4)
    # pooled: the loop inflates the residual, so the error grows, the slope stays
    assert rep["fit"]["A_minus_B_err"] > up["A_minus_B_err"]


def test_levels_from_log_events_full_sim(repo_root):
    from rig.config.profile import default_profile_path, load_profile
    from rig.config.recipe import load_recipe
    from rig.session.sim import simulate

    log, _ = simulate(load_recipe(repo_root / "config/recipes/stribeck-pass.yaml"),
                      load_profile(default_profile_path()), PARAFFIN, seed=5)
    rep = stribeck([log.trial_data(25.0)])
    assert rep["level_source"] == ["events"]
    # 7 velocities, up and down; the top one is planned twice in a row (up, then down) and
    # slides on as one stretch: one level, the other listed with its reason
    assert rep["n_levels"] == len(rep["levels"]) == 13
    assert [r["v_um_s"] for r in rep["rejected_levels"]] == [200.0]
    assert "same velocity" in rep["rejected_levels"][0]["reason"]
    assert {lv["direction"] for lv in rep["levels"]} == {"up", "down"}
    # windows are the last 50 µm of each level
    for lv in rep["levels"]:
        # samples at 25 Hz (block means, time-stamped at their centres) span the 50 µm window
        # less at most one sample interval, depending on where the 40 ms grid falls
        span = lv["x_end_um"] - lv["x_start_um"]
        assert 50.0 - lv["v_um_s"] / 25.0 - 3.0 <= span <= 50.0 + 3.0
    f = rep["fit"]
    assert abs(f["A_minus_B"] - A_MINUS_B) < 0.1 * abs(A_MINUS_B)


def test_cli(tmp_path):
    tr = _pass_with_hysteresis(7, 0.0)
    csv = tmp_path / "pass.csv"
    write_csv(tr, csv)
    out, png = tmp_path / "s.json", tmp_path / "s.png"
    res = CliRunner().invoke(app, ["stribeck", str(csv), "--json", str(out), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["schema"] == "rig.stribeck/1"
    assert abs(rep["fit"]["A_minus_B"] - A_MINUS_B) < 5e-4
    assert png.stat().st_size > 10_000
    assert np.all(np.diff([b["v_um_s"] for b in rep["branches"]["up"]]) > 0)
