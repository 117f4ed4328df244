"""`rig identify` on the rig's own MCAP log (full simulated rig, planner events)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.cli import app
from rig.model.spec import FrictionModel


def test_identify_mcap_uses_log_events(tmp_path):
    from rig import log
    from rig.analysis.reproduce import step_recipe
    from rig.config.recipe import compile_recipe
    from rig.config.profile import default_profile_path, load_profile
    from rig.sim import SimRig

    prof = load_profile(default_profile_path())
    recipe = step_recipe("boundary", highs=(10.0,))
    plan = compile_recipe(recipe, prof)
    model = FrictionModel.for_lubricant("boundary", 0.10)
    path = tmp_path / "steps.mcap"
    with log.TrialLogWriter(path, loop_rate_hz=plan.loop_rate_hz, decimated_rate_hz=25.0, raw_rate_hz=1000.0,
                            metadata={"normal_force_N": 100, "lubricant": "boundary"}, fsync=False) as w:
        for ev in plan.events:
            w.event(ev["t_s"], ev["kind"], **{k: v for k, v in ev.items() if k not in ("t_s", "kind")})
        for blk in SimRig(prof, model, seed=3).run_blocks(plan.x_ref_um, block_ticks=1000):
            w.write_block(blk)
    out = tmp_path / "id.json"
    res = CliRunner().invoke(app, ["identify", str(path), "--json", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["step_source"] == ["events"]
    assert len(rep["steps"]) == 1
    s = rep["steps"][0]
    assert s["v1_um_s"] == pytest.approx(1.0, rel=0.02) and s["v2_um_s"] == pytest.approx(10.0, rel=0.02)
    assert abs(s["A_mu"] - 1.1e-3) < 0.3e-3
    assert abs(s["B_mu"] - 4.0e-3) < 0.6e-3
    assert abs(s["L_um"] - 19.2) < 3.0
