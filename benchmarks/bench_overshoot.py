"""Velocity overshoot and rise time at the paper's steps (1->2, 1->5, 1->10 µm/s), measured as
the paper's Fig. 8 shows a step: velocity from the LVDT's 25 Hz log by the paper's estimator
(10-point moving average + central difference, rig.kinematics.velocity_paper). docs/paper.md
row 8.

For each lubricant and controller variant:
* noise-free (LVDT noise and quantisation off, spool band and dither on): overshoot
  (paper's estimator; in brackets the true slip velocity through the same 0.4 s average),
  rise 10-90 % and t90 from the ramp's start (the planner's 20 µm/s² ramp takes
  (v2 - v1)/20 s of it);
* with the profile's sensor noise, N_SEEDS trials (the paper averaged >= 8 per lubricant):
  overshoot of the trials' mean trace and its noise floor (the same statistic on the 5 s of
  steady sliding at v1 before the step); then the single trial's overshoot, mean ± sd over
  seeds, with its own floor (what one trial's plot shows).
Overshoot and floor are fractions of the step size v2 - v1.

Variants (kp 0.5 N/µm, ki 5, kd 0.003 of config/rigs/sim.yaml in all):
* "FF1 0.1": velocity feed-forward 0.1 N s/µm alone (the previous default);
* "FF1 0.02": the natural FF1 alone, the actuator's leakage slope k_h tau_L = 0.02 N s/µm;
* "FF1 0.02 + friction FF": plus the friction the model predicts along the reference
  (rig.model.feedforward.friction_feedforward_N; the default of recipes: controller.friction_ff);
* "... model off": the same with the feed-forward's model wrong by A x1.3, B x0.8, L x1.3
  and mu0 + 0.005 (a poorly identified model; the simulated interface keeps the true one).

The ramp: the shipped recipe's acceleration (config/recipes/velocity-steps.yaml, 40 µm/s²;
ACCEL=20 for the previous 20 µm/s²).

Run: python benchmarks/bench_overshoot.py [lubricant ...]   (N_SEEDS=8 by default; the paper
averaged >= 8 trials)"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from rig.analysis.reproduce import step_recipe
from rig.analysis.stability import step_response_metrics, step_velocity_traces
from rig.config.profile import default_profile_path, load_profile
from rig.config.recipe import ControllerSwitches
from rig.model.spec import FrictionModel
from rig.config.recipe import compile_recipe, load_recipe
from rig.session.memory import MemoryLog
from rig.sim import SimRig

RECIPE = Path(__file__).resolve().parent.parent / "config" / "recipes" / "velocity-steps.yaml"

# (label, FF1 N s/µm, friction feed-forward, feed-forward model wrong)
VARIANTS = (("FF1 0.1", 0.1, False, False),
            ("FF1 0.02", 0.02, False, False),
            ("FF1 0.02 + friction FF", 0.02, True, False),
            ("FF1 0.02 + friction FF, model off", 0.02, True, True))


def wrong_model(model: FrictionModel) -> FrictionModel:
    p = dict(model.params)
    p.update(A_mu=1.3 * p["A_mu"], B_mu=0.8 * p["B_mu"], L_um=1.3 * p["L_um"], mu0=p["mu0"] + 0.005)
    return model.model_copy(update={"params": p})


def profile_variant(prof0, ff1: float, noise: bool):
    upd = {"controller": prof0.controller.model_copy(update={"ff1_N_s_per_um": ff1})}
    if not noise:
        lv = prof0.sensors.lvdt.model_copy(update={"noise_sigma_um": 0.0, "quantization_um": 0.0})
        upd["sensors"] = prof0.sensors.model_copy(update={"lvdt": lv})
    return prof0.model_copy(update=upd)


def run(lub: str, prof, friction_ff: bool, model_off: bool, seed: int, accel_um_s2: float):
    """One trial of the paper's steps on the simulated rig (the session's plan, events and
    25 Hz log); with ``model_off`` the feed-forward's model is :func:`wrong_model`."""
    rec = step_recipe(lub, accel_um_s2=accel_um_s2).model_copy(
        update={"controller": ControllerSwitches(friction_ff=friction_ff)})
    plan = compile_recipe(rec, prof)
    model = prof.friction_model(lub)
    rig = SimRig(prof, model, seed=seed)
    rig.ff_model = wrong_model(model) if model_off else None
    log = MemoryLog(rate_hz=plan.loop_rate_hz)
    log.schedule_events(plan.events)
    for block in rig.run_blocks(plan.x_ref_um, block_ticks=20000, controller=plan.controller):
        log.write_block(block)
    return step_velocity_traces(log)


def main():
    lubs = sys.argv[1:] or ["boundary", "dry", "paraffin"]
    n_seeds = int(os.environ.get("N_SEEDS", "8"))
    prof0 = load_profile(default_profile_path())
    # the shipped recipe's ramp (config/recipes/velocity-steps.yaml); ACCEL=20 for the old one
    accel = float(os.environ.get("ACCEL", load_recipe(RECIPE).accel_um_s2))
    print(f"load average at start: {os.getloadavg()}  (timings on a shared machine: noisy)")
    print(f"steps 1->2, 1->5, 1->10 µm/s, ramp {accel:g} µm/s², {n_seeds} noise seeds")
    t0 = time.perf_counter()
    for lub in lubs:
        for label, ff1, fff, off in VARIANTS:
            t, vp, vt, steps = run(lub, profile_variant(prof0, ff1, False), fff, off, 1, accel)
            clean = []
            for e in steps:
                mp = step_response_metrics(t, vp, e["t_s"], e["v1_um_s"], e["v2_um_s"])
                mt = step_response_metrics(t, vt, e["t_s"], e["v1_um_s"], e["v2_um_s"])
                clean.append(f"{e['v1_um_s']:g}->{e['v2_um_s']:g} {100 * mp['overshoot']:4.1f} % "
                             f"({100 * mt['overshoot']:4.1f}) rise {mp['rise_s']:.2f} t90 {mp['t90_s']:.2f} s")
            print(f"{lub:9s} {label:34s} noise-free   | " + " | ".join(clean), flush=True)
            runs = [run(lub, profile_variant(prof0, ff1, True), fff, off, s, accel) for s in range(1, n_seeds + 1)]
            t = runs[0][0]
            n = min(r[1].size for r in runs)
            vmean = np.mean([r[1][:n] for r in runs], axis=0)
            noisy = []
            for e in runs[0][3]:
                a = (t[:n], e["t_s"], e["v1_um_s"], e["v2_um_s"])
                mm = step_response_metrics(a[0], vmean, *a[1:])
                single = [step_response_metrics(a[0], r[1][:n], *a[1:]) for r in runs]
                ov = np.array([m["overshoot"] for m in single])
                fl = np.array([m["floor"] for m in single])
                noisy.append(f"{e['v1_um_s']:g}->{e['v2_um_s']:g} mean {100 * mm['overshoot']:4.1f} % "
                             f"(floor {100 * mm['floor']:4.1f}) rise {mm['rise_s']:.2f}; one trial "
                             f"{100 * ov.mean():3.0f} ± {100 * ov.std(ddof=1):2.0f} % (floor {100 * fl.mean():3.0f})")
            print(f"{lub:9s} {label:34s} {n_seeds} seeds noisy | " + " | ".join(noisy), flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s, load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
