"""rig diagnose on the real laboratory records of ../shared/data/real/ (what it says, and whether it is sensible).

- leeman-p4309-step2 (Penn State biaxial, 12 -> 1.2 µm/s): the diagnosis names
  finite_stiffness first, with k of a few hundred kN/m; the published xlook fit
  needs k = 560 kN/m at this file's 100 N per rider, and with the stiffness the
  fitted A, B, L come close to the published a = 0.0077, b = 0.0071,
  Dc = 25 µm. The residual left is an oscillation of ~0.5 s period, reported as
  `unexplained` following frequency: the small sawtooth after the step that the
  README mentions. Physically sensible: the load-point displacement is not the
  interface slip, and the sawtooth is not a catalogue cause. Measured: k = 448 kN/m,
  A = 0.00745, B = 0.00681, L = 26.2 µm, hold-out gain 21 %; sawtooth period 0.50 s.
- giacomel-sepiolite-tr2 (0.2 -> 2 µm/s): one state fits the long transient badly
  (b < 0). A second state gains ~31 % on the hold-out blocks but only with
  |B2| = 0.08 > 0.05 (a cancelling pair): not named. The stiffness fit on the fit
  blocks of this single step predicts the hold-out blocks worse (-5 %): no finding
  (before issue 10 it named finite_stiffness; docs/validation.md).
- giacomel-basalt-brava (3 -> 10 µm/s): one state fits with b < 0 at the L bound; a
  slower second state (7.5 % gain) is the only cause that passes.
- Leeman measured now: k = 448 kN/m on the fit blocks, 593 kN/m refitted on all data;
  final A = 0.00779, B = 0.00721, L = 25.6 µm (published 0.007722, 0.007067, 25.46).
"""

from __future__ import annotations

import json

from typer.testing import CliRunner

from rig.cli import app
from rig.log import load_trial
from rig.diagnosis import diagnose


def test_leeman_finite_stiffness_and_sawtooth(real_data_dir, tmp_path):
    out = tmp_path / "leeman.json"
    res = CliRunner().invoke(app, ["diagnose", str(real_data_dir / "leeman-p4309-step2.csv"), "--json", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["findings"][0]["cause"] == "finite_stiffness"
    k = rep["findings"][0]["params"]["stiffness_kN_per_m"]
    assert 250.0 < k < 1200.0  # published: 560 kN/m
    assert rep["findings"][0]["gain_pct"] > 10
    mp = rep["model"]["params"]
    # with the stiffness, the friction parameters come back close to the published xlook fit
    assert abs(mp["A_mu"] - 0.007722) < 0.15 * 0.007722
    assert abs(mp["B_mu"] - 0.007067) < 0.15 * 0.007067
    assert abs(mp["L_um"] - 25.46) < 0.15 * 25.46
    assert [u["follows"] for u in rep["unexplained"]] == ["frequency"]
    assert 0.3 < rep["unexplained"][0]["period_s"] < 1.0


def test_sepiolite_one_state_fits_badly_and_nothing_negligible_is_named(real_data_dir):
    """Sepiolite (0.2 -> 2 um/s, one step): one state fits with b < 0 (README). A second state
    gains on the hold-out blocks but only with |B2| > 0.05 (a cancelling pair, implausible), so
    it is not named. Known limitation (docs/diagnosis.md): the stiffness fit on the fit blocks of
    this single-step record lands in a minimum that predicts the held-out blocks worse; hold-out
    windows aligned to the step (issue 10, item 4) are not done yet."""
    d = diagnose(load_trial(real_data_dir / "giacomel-sepiolite-tr2.csv"))
    rep = d.report()
    assert rep["baseline"]["params"]["B_mu"] < 0  # one state fits badly (README)
    cands = {c.cause: c for c in d.tried[0]}
    assert cands["second_state_variable"].gain_pct > 5 and not cands["second_state_variable"].accepted
    for f in rep["findings"]:
        assert f["gain_pct"] >= 1.0


def test_basalt_second_state_at_most(real_data_dir):
    """Basalt (3 -> 10 um/s): one state fits with b < 0. The only cause that passes, if any, is a
    slower second state (reported with L2 > L, the spec's convention); its parameters stay
    inside the physical bounds."""
    res = CliRunner().invoke(app, ["diagnose", str(real_data_dir / "giacomel-basalt-brava.csv")])
    assert res.exit_code == 0
    rep = diagnose(load_trial(real_data_dir / "giacomel-basalt-brava.csv")).report()
    assert rep["baseline"]["params"]["B_mu"] < 0
    assert [f["cause"] for f in rep["findings"]] in ([], ["second_state_variable"])
    for f in rep["findings"]:
        p = rep["model"]["params"]
        assert p["L2_um"] > p["L_um"]
        assert abs(p["B2_mu"]) < 0.05
