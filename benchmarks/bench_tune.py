"""Measured frequency response against rig stability's loop model, and autotune's gains against
the analytic advice (docs/tuning.md; issue 22's Must-show).

config/recipes/tune-sweep.yaml on the simulated rig with the shipped profile (sim.substeps 1)
and with 8 plant substeps per tick, and (``--hardware``) through rig run --hardware
config/rigs/emulated.yaml; for each: rig.analysis.tuning.frf (bands of 1/6 octave up to 50 Hz:
max gain and phase difference, within 1 dB and 5 deg asked), then fit_plant and propose_gains
against the same rule on the nominal plant (within 15 % asked). Prints os.getloadavg().

Run: python benchmarks/bench_tune.py [--hardware]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from rig.analysis.tuning import fit_plant, frf, propose_gains
from rig.config.profile import load_profile
from rig.log import read_trial

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um", "ff1_N_s_per_um")


def run(tmp: Path, name: str, profile_text: str | None, hardware: bool) -> Path:
    recipe = (ROOT / "config" / "recipes" / "tune-sweep.yaml").read_text()
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
    print(f"{name}: {rep['segments_used']} segments ({rep['stalls_in_sweep']} stalls, {rep['stale_position_runs']} "
          f"stale stretches left out), {c['n']} coherent bins to 50 Hz: bands max {c['gain_db_max_abs']:.2f} dB, "
          f"{c['phase_deg_max_abs']:.1f} deg -> {'within' if c['within_1db_5deg'] else 'NOT within'} 1 dB / 5 deg")
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
        report("sim, substeps 1", run(tmp, "sub1", None, False), sim)
        (tmp / "sub8p.yaml").write_text(f"extends: {sim}\nsim:\n  substeps: 8\n")
        report("sim, substeps 8", run(tmp, "sub8", f"extends: {sim}\nsim:\n  substeps: 8\n", False), tmp / "sub8.yaml")
        if hardware:
            report("emulated rig", run(tmp, "hw", None, True), ROOT / "config" / "rigs" / "emulated.yaml")
    print(f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
