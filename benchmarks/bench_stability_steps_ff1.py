"""Velocity overshoot and rise time at the paper's steps (1->2, 1->5, 1->10 µm/s) on the full
simulated rig, with and without the velocity feed-forward FF1 (rig.control, ff1_N_s_per_um),
for the profile's gains (kp 0.5 N/µm, ki 5) and a stiffer tuning (kp 3 N/µm, ki 2).

The step response is the true slip velocity (50 ms moving mean) averaged over seeds (the
mean step response: the loop's noise averages out, the controller's response stays), and
once with the sensors' noise off. Overshoot = (peak - v2)/(v2 - v1) within 5 s after the
step; rise = 10 -> 90 % of the step, and t90 from the step's start (the planner's ramp at
20 µm/s^2 itself takes 0.45 s for 1 -> 10). Paper: 0.5 s; target: overshoot < 10 %.

Run: python benchmarks/bench_stability_steps_ff1.py [lubricant ...]"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from rig.analysis.reproduce import step_recipe
from rig.config.profile import default_profile_path, load_profile
from rig.session.sim import simulate

# (label, kp N/µm, ki N/(µm s), FF1 N s/µm)
VARIANTS = (("profile gains, no FF1", 0.5, 5.0, 0.0),
            ("profile gains, FF1 0.02 (k_h tau_L)", 0.5, 5.0, 0.02),
            ("profile gains, FF1 0.10", 0.5, 5.0, 0.10),
            ("kp 3 ki 2, no FF1", 3.0, 2.0, 0.0),
            ("kp 3 ki 2, FF1 0.02", 3.0, 2.0, 0.02),
            ("kp 3 ki 2, FF1 0.05", 3.0, 2.0, 0.05))
SEEDS = (1, 2, 3, 4)


def step_traces(lub: str, prof, seed: int):
    log, _ = simulate(step_recipe(lub), prof, prof.friction_model(lub), seed=seed)
    v = np.convolve(log.column("true_velocity_um_s"), np.ones(50) / 50, mode="same")
    out = []
    for e in log.events:
        if e["kind"] == "velocity_step":
            i0 = int(round(e["t_s"] * prof.loop.rate_hz))
            out.append((e["v1_um_s"], e["v2_um_s"], v[i0:i0 + 5000]))
    return out


def metrics(v1, v2, y, rate):
    t10 = int(np.argmax(y > v1 + 0.1 * (v2 - v1)))
    t90 = int(np.argmax(y > v1 + 0.9 * (v2 - v1)))
    return (y.max() - v2) / (v2 - v1), (t90 - t10) / rate, t90 / rate


def main():
    lubs = sys.argv[1:] or ["boundary", "dry", "paraffin"]
    prof0 = load_profile(default_profile_path())
    lv = prof0.sensors.lvdt.model_copy(update={"noise_sigma_um": 0.0, "quantization_um": 0.0})
    quiet = prof0.model_copy(update={"sensors": prof0.sensors.model_copy(update={"lvdt": lv})})
    rate = prof0.loop.rate_hz
    print(f"load average at start: {os.getloadavg()}")
    t0 = time.perf_counter()
    for lub in lubs:
        for label, kp, ki, ff1 in VARIANTS:
            for noise, base, seeds in (("noisy, mean of 4 seeds", prof0, SEEDS), ("noise-free", quiet, (1,))):
                prof = base.model_copy(update={"controller": base.controller.model_copy(
                    update={"kp_N_per_um": kp, "ki_N_per_um_s": ki, "ff1_N_s_per_um": ff1})})
                runs = [step_traces(lub, prof, s) for s in seeds]
                cells = []
                for k in range(len(runs[0])):
                    v1, v2 = runs[0][k][0], runs[0][k][1]
                    y = np.mean([r[k][2] for r in runs], axis=0)
                    ov, rise, t90 = metrics(v1, v2, y, rate)
                    cells.append(f"{v1:g}->{v2:g}: {100 * ov:4.0f} % rise {rise:.2f} s t90 {t90:.2f} s")
                print(f"{lub:9s} {label:36s} {noise:22s} | " + " | ".join(cells), flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s, load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
