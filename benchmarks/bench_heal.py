"""Slide-hold-slide on the simulated rig: each hold's delta_mu_peak against the aging law's
B ln(1 + v t_h / L), and the healing rate of both state laws (docs/identification.md,
section 9; issue 24's Must-show).

config/recipes/slide-hold-slide.yaml (boundary, v = 10 µm/s, holds 1, 3, 10, 30, 100 s) run
on the simulated rig with the aging law (config/models/boundary-aging.yaml) and with the
paper's slip law, for SEEDS seeds, reduced by rig.analysis.healing.heal from the 25 Hz channel
and from every loop sample. Prints the ratio to the prediction per hold (within 20 % asked),
beta_per_decade ± s.e. (aging: against B ln 10; slip: within 2 s.e. of 0 or below
0.2 B ln 10 asked), CPU time and os.getloadavg().

Run: python benchmarks/bench_heal.py [n_seeds]   (3 by default)
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from rig.analysis.healing import aging_prediction, heal
from rig.config.profile import load_profile
from rig.config.recipe import load_recipe
from rig.model.spec import FrictionModel
from rig.session.sim import simulate

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    n_seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    prof = load_profile(ROOT / "config" / "rigs" / "sim.yaml")
    rec = load_recipe(ROOT / "config" / "recipes" / "slide-hold-slide.yaml")
    lp = prof.lubricants[rec.lubricant]
    seg = next(s for s in rec.segments if s.kind == "slide_hold_slide")
    params = {"mu0": lp.mu0, "A_mu": lp.A_mu, "B_mu": lp.B_mu, "L_um": lp.L_um}
    pred = aging_prediction(lp.B_mu, lp.L_um, seg.velocity_um_s, seg.hold_times_s)
    print(f"load average {os.getloadavg()}; holds {seg.hold_times_s} s at {seg.velocity_um_s:g} µm/s; "
          f"B ln 10 = {lp.B_mu * np.log(10):.4g}; prediction {np.round(pred, 5).tolist()}")
    c0 = time.process_time()
    worst = {"aging": 0.0}
    for law, ext in (("aging", ["aging_law"]), ("slip", [])):
        for seed in range(rec.seed, rec.seed + n_seeds):
            log, _ = simulate(rec, prof, FrictionModel(extensions=ext, params=params), seed=seed)
            for rate in (25.0, None):
                r = heal(log.trial_data(rate))
                got = np.array([h["delta_mu_peak"] for h in r["holds"]])
                ratio = got / pred
                if law == "aging":
                    worst["aging"] = max(worst["aging"], float(np.abs(ratio - 1).max()))
                ok = (np.abs(ratio - 1).max() < 0.2) if law == "aging" else \
                    (abs(r["beta_per_decade"]) < 2 * r["beta_per_decade_sd"]
                     or abs(r["beta_per_decade"]) < 0.2 * lp.B_mu * np.log(10))
                print(f"{law:5s} seed {seed} {'25 Hz' if rate else '1 kHz'}: ratio to B ln(1+vt/L) "
                      f"{np.round(ratio, 3).tolist()}  beta {r['beta_per_decade']:.3e} ± {r['beta_per_decade_sd']:.1e}"
                      f"  {'ok' if ok else 'NOT MET'}")
    print(f"largest |ratio - 1| (aging): {worst['aging']:.3f}; CPU {time.process_time() - c0:.1f} s; "
          f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
