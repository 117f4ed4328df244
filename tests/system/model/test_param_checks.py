"""Honest results: parameters on a fit bound or outside their physical range are flagged, once
(rig.model.checks, bounds declared in rig.model.spec), in identify's and diagnose's tables and
JSON; rejected steps say why in the table. Real records: Leeman (A > B: a negative k_cr),
sepiolite (its step rejected, B < 0 in the whole-record fit), basalt (diagnose's baseline at its
bounds: A ~ 1e-5, L = 1e5 µm, B < 0)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.cli import app
from rig.model import checks
from rig.model.paper import TABLE2
from rig.model.spec import PARAMS, PLAUSIBLE


def test_checks_flag_bounds_and_unphysical_values():
    w = checks.check_param("L_um", PARAMS["L_um"].hi)
    assert w["kind"] == "at_bound" and "upper bound" in w["message"]
    assert checks.check_param("A_mu", 9.2e-6)["kind"] == "at_bound"  # the fit's lower bound is 0
    w = checks.check_param("B_mu", -0.166)
    assert w["kind"] == "not_physical" and "B < 0" in w["message"]
    assert checks.check_param("A_mu", 0.08)["kind"] == "not_physical"
    w = checks.check_k_cr(-2.63)
    assert w["kind"] == "not_physical" and "A > B" in w["message"]
    assert checks.check_k_cr(15.1) is None
    w = checks.check_param("L_um", 20.0, err=25.0)
    assert w["kind"] == "undetermined"
    # the paper's own values raise nothing
    for row in TABLE2.values():
        vals = {k: row[k][0] for k in ("B_mu", "L_um", "k_cr_kN_per_m")}
        if row["A_mu"][0] > 0:
            vals["A_mu"] = row["A_mu"][0]
        assert checks.check_params(vals) == [], row
    # plausible ranges lie inside the fit bounds (a fit can reach them)
    for name, p in PLAUSIBLE.items():
        assert PARAMS[name].lo <= p.lo < p.hi <= PARAMS[name].hi or name in ("tau_s", "delay_s")


def _identify(path):
    res = CliRunner().invoke(app, ["identify", str(path), "--json", "-"], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout), res.stderr


def test_identify_negative_k_cr_warns(real_data_dir):
    rep, text = _identify(real_data_dir / "leeman-p4309-step2.csv")
    ws = [w for w in rep["warnings"] if w["param"] == "k_cr_kN_per_m"]
    assert {w["where"] for w in ws} == {"mean over steps", "whole-record fit"}
    assert rep["mean"]["k_cr_kN_per_m"] < 0
    assert "warning (!): mean over steps: k_cr (eq. 13)" in text and "kN/m (!)" in text


def test_identify_rejected_step_says_why_in_table(real_data_dir):
    rep, text = _identify(real_data_dir / "giacomel-sepiolite-tr2.csv")
    assert rep["n_steps"] == 0
    reason = rep["rejected_steps"][0]["reason"]
    assert "accepted" in text and "no: " + reason[:20] in text
    assert any(w["param"] == "B_mu" and w["where"] == "whole-record fit" for w in rep["warnings"])


def test_diagnose_baseline_not_physical_warns(real_data_dir):
    """The sepiolite record's slow, non-exponential evolution after its step is fitted by one
    state with B < 0 (docs/validation.md): the baseline is flagged in the JSON and on stderr."""
    res = CliRunner().invoke(app, ["diagnose", str(real_data_dir / "giacomel-sepiolite-tr2.csv"), "--json", "-"])
    assert res.exit_code == 0, res.output
    rep = json.loads(res.stdout)
    base = {w["param"]: w["kind"] for w in rep["warnings"] if w["where"].startswith("baseline")}
    p = rep["baseline"]["params"]
    for name, spec in PARAMS.items():  # whatever sits on its bound is flagged as such
        if name in p and spec.hi is not None and p[name] >= 0.999 * spec.hi:
            assert base.get(name) == "at_bound", (name, p[name])
    if p["B_mu"] < 0:
        assert base.get("B_mu") == "not_physical", rep["warnings"]
    assert base, "the sepiolite baseline (one state for a slower second transient) is flagged"
    assert "warning (!): baseline" in res.stderr
