"""Measured frequency response against rig stability's loop model, and autotune's gains against
the analytic advice (docs/tuning.md; issue 22's Must-show).

config/recipes/tune-sweep.yaml on the simulated rig with the shipped profile (sim.substeps 1)
for seeds 9, 11, 13, 14, 15 and with 8 plant substeps per tick (seeds 11, 12), and
(``--hardware``) through rig run --hardware config/rigs/emulated.yaml; for each:
rig.analysis.tuning.frf (bands of 1/6 octave: max gain and phase difference up to 43 Hz and in
the top band 46-50 Hz; within 1 dB and 5 deg up to 50 Hz asked), then fit_plant and
propose_gains against the same rule on the nominal plant (within 15 % asked). Prints
os.getloadavg().

Run: python benchmarks/bench_tune.py [--hardware]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from rig.analysis.tuning import fit_plant, frf, propose_gains
from rig.config.profile import load_profile
from rig.log import read_trial

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um", "ff1_N_s_per_um")


def run(tmp: Path, name: str, profile_text: str | None, hardware: bool, seed: int = 9) -> Path:
    recipe = (ROOT / "config" / "recipes" / "tune-sweep.yaml").read_text().replace("seed: 9", f"seed: {seed}", 1)
    if profile_text is not None:
        (tmp / f"{name}.yaml").write_text(profile_text)
        recipe = recipe.replace("lubricant: boundary", f"lubricant: boundary\nprofile: {tmp / (name + '.yaml')}", 1)
    (tmp / f"{name}-recipe.yaml").write_text(recipe)
    out = tmp / f"{name}.mcap"
    cmd = [sys.executable, "-m", "rig.cli", "run", str(tmp / f"{name}-recipe.yaml"), "--out", str(out)]
    cmd += ["--hardware", str(ROOT / "config" / "rigs" / "emulated.yaml")] if hardware else ["--sim"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out


def report(name: str, log: Path, prof_path: Path) -> None:
    prof = load_profile(prof_path)
    model = prof.friction_model("boundary")
    rep = frf(read_trial(log, channel="raw"), prof, model, {"ff1": True, "friction_ff": True})
    c = rep["compare"]
    hz, g, p = (np.asarray(c[k]) for k in ("band_hz", "band_gain_db", "band_phase_deg"))
    lo = hz <= 44.0
    print(f"{name}: {rep['segments_used']} segments ({rep['stalls_in_sweep']} stalls, {rep['stale_position_runs']} "
          f"stale stretches left out), {c['n']} coherent bins to 50 Hz; bands to 43 Hz max {np.abs(g[lo]).max():.2f} dB, "
          f"{np.abs(p[lo]).max():.1f} deg; top band {np.round(np.abs(g[~lo]), 2).tolist()} dB, "
          f"{np.round(np.abs(p[~lo]), 1).tolist()} deg -> {'within' if c['within_1db_5deg'] else 'NOT within'} "
          "1 dB / 5 deg")
    plant = fit_plant(rep, prof, model)
    tuned = propose_gains(prof, model, plant, V_um_s=rep["slide_um_s"])
    advice = propose_gains(prof, model, None, V_um_s=rep["slide_um_s"])
    diffs = {k: 100 * (tuned[k] / advice[k] - 1) for k in KEYS}
    print(f"   tau_L {1e3 * plant['params']['tau_leak_s']:.3f} ms ± {100 * plant['rel_err']['tau_leak_s']:.1f} %, "
          f"delay {1e3 * plant['params']['delay_s']:.3f} ms; gains vs advice: "
          + ", ".join(f"{k} {v:+.1f} %" for k, v in diffs.items())
          + f"; margin to k_cr {tuned['margin_to_k_cr']:.2f} x")


def main() -> int:
    hardware = "--hardware" in sys.argv
    print(f"load average {os.getloadavg()}")
    sim = ROOT / "config" / "rigs" / "sim.yaml"
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for seed in (9, 11, 13, 14, 15):
            report(f"sim, seed {seed}", run(tmp, f"sub1-{seed}", None, False, seed), sim)
        for seed in (11, 12):
            report(f"sim, 8 substeps, seed {seed}",
                   run(tmp, f"sub8-{seed}", f"extends: {sim}\nsim:\n  substeps: 8\n", False, seed),
                   tmp / f"sub8-{seed}.yaml")
        if hardware:
            report("emulated rig", run(tmp, "hw", None, True), ROOT / "config" / "rigs" / "emulated.yaml")
    print(f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
