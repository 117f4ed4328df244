"""Live view (`rig run --live`, rig.log.live): a real WebSocket client speaking the Foxglove protocol
receives the running trial's samples, events and loop statistics, the same as the MCAP holds;
--pace paces the simulated rig without changing its data; a slow client never holds up the log."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rig.config.profile import load_profile
from rig.config.recipe import compile_recipe, load_recipe
from rig.session.sim import SimBackend


def test_sim_pace_waits_and_keeps_the_data(repo_root):
    """--pace 4: the trial takes at least duration / 4 of wall time; the samples are those of an unpaced run."""
    profile = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    recipe = load_recipe(repo_root / "config" / "recipes" / "smoke.yaml")
    plan = compile_recipe(recipe, profile)
    fm = profile.friction_model(recipe.lubricant)

    def run(pace):
        b = SimBackend(profile, fm, recipe.normal_force_N, 7, block_ticks=1000, pace=pace)
        b.start(plan)
        t0 = time.monotonic()
        blocks = []
        while (blk := b.receive()) is not None:
            blocks.append(blk.data["position_um"].copy())
        return time.monotonic() - t0, blocks

    wall_fast, fast = run(0.0)
    wall_paced, paced = run(4.0)
    assert wall_paced >= plan.duration_s / 4 * 0.95
    assert max(b.size for b in paced) == 400  # blocks of 0.1 s of wall time: 0.4 s of trial at 4x
    np.testing.assert_array_equal(np.concatenate(fast), np.concatenate(paced))
    with pytest.raises(ValueError, match="pace"):
        SimBackend(profile, fm, 100.0, 7, pace=-1)
