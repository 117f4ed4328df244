"""Run the full simulated rig (:class:`rig.sim.SimRig`) on a planned reference and turn
the closed-loop blocks into a 25 Hz :class:`rig.data.TrialData` with the plan's events,
as the rig's MCAP log would (every ``loop_rate / rate_hz``-th tick, like the log's
``/log25`` channel)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.data import TrialData
from rig.model.spec import FrictionModel

SIM_AVAILABLE = True
try:  # the simulated rig and the planner belong to other helpers; tolerate their absence
    from rig.config.profile import load_profile
    from rig.sim import SimRig
    from rig.config.recipe import Recipe
    from rig.config.recipe import compile_recipe
except Exception:  # noqa: BLE001
    SIM_AVAILABLE = False


def step_recipe(lubricant: str, *, v1=1.0, highs=(2.0, 5.0, 10.0), slip_before_um: float | None = None,
                normal_force_N: float = 100.0, accel_um_s2: float = 20.0, seed: int = 0) -> "Recipe":
    """The paper's protocol (section 4.2): steps 1->2, 1->5, 1->10 µm/s from steady sliding.

    ``slip_before_um`` defaults to 6 L of the lubricant's Table-2 L (at least 120 µm), so
    the state is at steady state before each step; after each step the slide covers the
    paper's last f2 window (250 µm + 200 points at 25 Hz) with a 10 % margin."""
    from rig.model.paper import TABLE2

    L = TABLE2[lubricant]["L_um"][0]
    before = slip_before_um if slip_before_um is not None else max(120.0, 6.0 * L)
    steps = [{"v1_um_s": v1, "v2_um_s": vh, "slip_after_um": round(1.1 * (250.0 + 8.0 * vh), 1)} for vh in highs]
    return Recipe.model_validate({
        "name": f"steps-{lubricant}", "lubricant": lubricant, "normal_force_N": normal_force_N, "seed": seed,
        "accel_um_s2": accel_um_s2, "log": {"raw_rate_hz": 1000, "decimated_rate_hz": 25},
        "segments": [{"kind": "hold", "duration_s": 1.0},
                     {"kind": "velocity_steps", "slip_before_um": before, "return_speed_um_s": 100.0,
                      "hold_s": 1.0, "steps": steps}],
    })


@dataclass
class SimTrial:
    trial: TrialData
    raw: dict | None


def run_sim_trial(recipe, model: FrictionModel, *, profile=None, seed: int = 0, rate_hz: float = 25.0,
                  keep_raw: bool = False) -> SimTrial:
    """Plan ``recipe`` for ``profile``, run the closed loop with ``model``, decimate to
    ``rate_hz``. The plan's events are attached (times on the same clock)."""
    if not SIM_AVAILABLE:
        raise RuntimeError("the simulated rig (rig.sim, trajectories) is not available")
    if profile is None or isinstance(profile, str):
        from rig.config.profile import default_profile_path

        profile = load_profile(profile or default_profile_path())
    plan = compile_recipe(recipe, profile, friction_model=model)
    rig = SimRig(profile, model, normal_force_N=recipe.normal_force_N, seed=seed)
    every = max(1, int(round(plan.loop_rate_hz / rate_hz)))
    keys = ("t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd",
            "true_velocity_um_s", "true_mu")
    parts = {k: [] for k in keys}
    raw_parts = {} if keep_raw else None
    g = 0
    for blk in rig.run_blocks(plan.x_ref_um, block_ticks=20000):
        n = blk["t_s"].size
        sel = np.arange((-g) % every, n, every)
        for k in keys:
            parts[k].append(blk[k][sel])
        if keep_raw:
            for k, v in blk.items():
                raw_parts.setdefault(k, []).append(v)
        g += n
    cols = {k: np.concatenate(v) for k, v in parts.items()}
    trial = TrialData(
        time_s=cols["t_s"], position_um=cols["position_um"], friction_N=cols["friction_N"],
        normal_1_N=cols["normal_1_N"], normal_2_N=cols["normal_2_N"], position_ref_um=cols["position_ref_um"],
        valve_cmd=cols["valve_cmd"], extra={"true_velocity_um_s": cols["true_velocity_um_s"],
                                            "true_mu": cols["true_mu"]},
        metadata={"normal_force_N": f"{recipe.normal_force_N:g}", "lubricant": recipe.lubricant,
                  "generator": "rig.sim.SimRig"},
        events=[dict(e) for e in plan.events], source=f"sim:{recipe.name}:seed{seed}")
    raw = {k: np.concatenate(v) for k, v in raw_parts.items()} if keep_raw else None
    return SimTrial(trial, raw)
