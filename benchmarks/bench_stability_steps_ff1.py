"""Velocity overshoot and rise time at the paper's steps (1->2, 1->5, 1->10 µm/s) on the full
simulated rig, with and without the velocity feed-forward FF1 (rig.control, ff1_N_s_per_um).

Overshoot = (peak - v2)/(v2 - v1) of the true slip velocity (50 ms moving mean) within 5 s
after the step; rise time = from the step's start to 90 % of the step. Reported with the
rig's sensor noise (mean over seeds) and without it (the controller's own response).
Paper: rise within 0.5 s; target: overshoot < 10 %.

Run: python benchmarks/bench_stability_steps_ff1.py [lubricant ...]"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from rig.analysis.simrun import run_sim_trial, step_recipe
from rig.profile import default_profile_path, load_profile

FF1_VALUES = (0.0, 0.02, 0.05, 0.1, 0.15)   # N s/µm; 0.02 = k_h tau_L, the valve's flow gain


def step_metrics(lub: str, prof, seed: int) -> list[dict]:
    st = run_sim_trial(step_recipe(lub), prof.friction_model(lub), profile=prof, seed=seed, keep_raw=True)
    v = st.raw["true_velocity_um_s"]
    vs = np.convolve(v, np.ones(50) / 50, mode="same")
    out = []
    for e in st.trial.events:
        if e["kind"] != "velocity_step":
            continue
        v1, v2 = e["v1_um_s"], e["v2_um_s"]
        i0 = int(round(e["t_s"] * prof.loop.rate_hz))
        y = vs[i0:i0 + 5000]
        t90 = int(np.argmax(y > v1 + 0.9 * (v2 - v1))) / prof.loop.rate_hz
        out.append({"v1": v1, "v2": v2, "overshoot": (y.max() - v2) / (v2 - v1), "t90_s": t90})
    return out


def main():
    lubs = sys.argv[1:] or ["boundary", "dry", "paraffin"]
    prof0 = load_profile(default_profile_path())
    lv = prof0.sensors.lvdt.model_copy(update={"noise_sigma_um": 0.0, "quantization_um": 0.0})
    quiet = prof0.model_copy(update={"sensors": prof0.sensors.model_copy(update={"lvdt": lv})})
    print(f"load average at start: {os.getloadavg()}")
    t0 = time.perf_counter()
    for lub in lubs:
        for label, base, seeds in (("noisy", prof0, (1, 2, 3)), ("noise-free", quiet, (1,))):
            for ff1 in FF1_VALUES:
                prof = base.model_copy(update={"controller": base.controller.model_copy(
                    update={"ff1_N_s_per_um": ff1})})
                ms = [step_metrics(lub, prof, s) for s in seeds]
                cells = []
                for k in range(len(ms[0])):
                    ov = np.mean([m[k]["overshoot"] for m in ms])
                    tr = np.mean([m[k]["t90_s"] for m in ms])
                    cells.append(f"{ms[0][k]['v1']:g}->{ms[0][k]['v2']:g}: overshoot {100 * ov:4.0f} % rise {tr:.2f} s")
                print(f"{lub:9s} {label:10s} FF1 {ff1:5.2f} N s/µm | " + " | ".join(cells), flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s, load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
