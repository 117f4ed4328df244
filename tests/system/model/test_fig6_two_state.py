"""Fig. 6 of the paper: the stepped-velocity pass (config/recipes/stribeck-pass.yaml) on
paraffin with a second, long state variable (config/models/paraffin-two-state.yaml, L2 =
750 µm, three 250 µm levels) shows the up/down loop -- friction after increases in
velocity exceeds friction after decreases -- which the single-state law cannot show; `rig
diagnose` on that pass names the second state variable (docs/paper.md row 9)."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from rig.cli import app


def _branches(path):
    rep = json.loads(path.read_text())
    up = {lv["v_um_s"]: lv["mu"] for lv in rep["levels"] if lv["direction"] == "up"}
    down = {lv["v_um_s"]: lv["mu"] for lv in rep["levels"] if lv["direction"] == "down"}
    # the top velocity is one level (up, then on at the same speed: no velocity change), on the up branch
    both = sorted(v for v in up if v in down)
    return np.array([up[v] - down[v] for v in both]), both


def test_two_state_pass_shows_the_loop_and_diagnose_names_it(tmp_path, repo_root):
    recipe = str(repo_root / "config/recipes/stribeck-pass.yaml")
    model = str(repo_root / "config/models/paraffin-two-state.yaml")
    r = CliRunner()
    for name, extra in (("two", ["--friction-model", model]), ("one", [])):
        res = r.invoke(app, ["run", recipe, "--sim", "-o", str(tmp_path / f"{name}.mcap"), *extra])
        assert res.exit_code == 0, res.output
        res = r.invoke(app, ["stribeck", str(tmp_path / f"{name}.mcap"), "--json", str(tmp_path / f"{name}.json"),
                             *(["--plot", str(tmp_path / "fig6.png")] if name == "two" else [])])
        assert res.exit_code == 0, res.output
    loop, v = _branches(tmp_path / "two.json")
    flat, _ = _branches(tmp_path / "one.json")
    # two states: up above down at every level between the ends (measured 0.004-0.010 in mu
    # at 2-100 µm/s, 10-20 % of the friction); single state: within 3e-4 at every level
    mid = [i for i, x in enumerate(v) if 2.0 <= x <= 100.0]
    assert np.all(loop[mid] > 3e-3), loop
    assert np.all(np.abs(flat) < 1e-3), flat
    assert (tmp_path / "fig6.png").stat().st_size > 10_000
    res = r.invoke(app, ["diagnose", str(tmp_path / "two.mcap"), "--json", str(tmp_path / "d.json")])
    assert res.exit_code == 0, res.output
    causes = [f["cause"] for f in json.loads((tmp_path / "d.json").read_text())["findings"]]
    assert "second_state_variable" in causes, causes
