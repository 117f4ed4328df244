"""Stribeck finds the same levels in one trial whatever its form: the MCAP log (level events)
and its 25 Hz CSV (steps detected in the data) through the CLI, and its 1 kHz raw channel
without events; and says how many it found and why a planned level is not counted (were 14
from the MCAP, 13 from the 25 Hz CSV, 11 from the 1 kHz record: the top velocity is planned


twice in a row, which the data show as one level, and the 1 kHz detection missed the short
fast levels that the 25 Hz block means show)."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from typer.testing import CliRunner

from rig.analysis.stribeck import stribeck
from rig.cli import app
from rig.log.reader import read_trial


@pytest.fixture(scope="module")
def pass_files(tmp_path_factory, repo_root):
    d = tmp_path_factory.mktemp("stribeck")
    r = CliRunner()
    mcap = d / "pass.mcap"
    res = r.invoke(app, ["run", str(repo_root / "config/recipes/stribeck-pass.yaml"), "--sim", "--out", str(mcap)])
    assert res.exit_code == 0, res.output
    res = r.invoke(app, ["export", str(mcap), "--rate", "25", "-o", str(d / "pass25.csv")])
    assert res.exit_code == 0, res.output
    return {"mcap": mcap, "csv25": d / "pass25.csv"}


def _stribeck(path):
    res = CliRunner().invoke(app, ["stribeck", str(path), "--json", "-"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout), res.stderr


def _vel(rep):
    # the same velocities in the same order (detected levels carry measured speeds, within 1 %)
    return [round(10 * math.log10(lv["v_um_s"])) for lv in rep["levels"]]


def test_same_levels_from_mcap_and_csv(pass_files):
    (mc, text), (cv, _) = _stribeck(pass_files["mcap"]), _stribeck(pass_files["csv25"])
    assert mc["n_levels"] == cv["n_levels"] == 13
    assert mc["level_source"] == ["events"] and cv["level_source"] == ["data"]
    assert _vel(mc) == _vel(cv)
    assert [lv["direction"] for lv in mc["levels"]] == [lv["direction"] for lv in cv["levels"]]
    # eq. (7)'s slope agrees between the two forms to within its error
    assert abs(mc["fit"]["A_minus_B"] - cv["fit"]["A_minus_B"]) < 5 * mc["fit"]["A_minus_B_err"] + 1e-4
    # the count and the reason for the one planned level not counted are printed
    assert "13 level(s) found" in text and "same velocity as the level before" in text
    assert [r["v_um_s"] for r in mc["rejected_levels"]] == [200.0]


def test_same_levels_from_the_1khz_record(pass_files):
    raw = read_trial(pass_files["mcap"], channel="raw")
    raw = dataclasses.replace(raw, events=[])  # as a 1 kHz CSV: no events
    rep = stribeck([raw])
    assert rep["level_source"] == ["data"] and rep["n_levels"] == 13
    assert _vel(rep) == _vel(_stribeck(pass_files["mcap"])[0])
