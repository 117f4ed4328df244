"""Benchmarks of rig diagnose: speed on one-hour records, accuracy and false-finding rate over seeds.

    python benchmarks/bench_diagnose.py speed        # 25 Hz and 1 kHz one-hour records
    python benchmarks/bench_diagnose.py real         # the 75,220-row real record (velstep2), read + diagnosed
    python benchmarks/bench_diagnose.py clean N      # false-finding rate over N clean records
    python benchmarks/bench_diagnose.py accuracy N   # per cause: named and within 25 %, over N seeds
                                                     # (BENCH_EFFECTS=a,b: only those causes)
    python benchmarks/bench_diagnose.py coverage N   # the final model's 68 % intervals: how often they cover the truth
    ... [NOISE_SCALE]: records' sensor noise in units of the profile's (2 = the paper's ± as 1 sigma)
"""

from __future__ import annotations

import sys
import time

import numpy as np

from rig.diagnosis import diagnose
from rig.sim.synth import SynthSpec, make_record, random_effect

EFFECTS = ["second_state_variable", "aging_law", "sensor_lag", "finite_stiffness", "normal_force_variation",
           "slip_wear_drift", "force_offset_drift", "position_periodic", "time_delay"]


def speed():
    import os

    # (rate, duration, jitter, budget): 1 h at 25 Hz and 1 kHz; 75,000 irregular samples (2.8 h at ~7.5 Hz)
    for rate, dur, jit, budget in ((25.0, 3600.0, 0.0, 20.0), (1000.0, 3600.0, 0.0, 30.0), (7.5, 10000.0, 0.6, 20.0)):
        trial, _ = make_record(SynthSpec(rate_hz=rate, duration_s=dur, seed=1, protocol="varied", jitter=jit))
        diagnose(trial.select(np.arange(len(trial)) < 2000))  # JIT warm-up
        t0 = time.perf_counter()
        d = diagnose(trial)
        dt = time.perf_counter() - t0
        print(f"speed: {dur / 3600:.2g} h at {rate:g} Hz{' (irregular)' if jit else ''} ({len(trial)} samples, "
              f"{d.timings['n_bins']} fit bins): {dt:.1f} s (budget {budget:g} s) "
              f"findings={[f.cause for f in d.findings]}; load average {os.getloadavg()[0]:.2f}", flush=True)


def real():
    """`rig diagnose tests/data/giacomel-sepiolite-velstep2.csv` in-process: 75,220 irregular rows
    (2.8 h at ~7 Hz), reading the CSV included, after a JIT warm-up on a cut of it."""
    import os
    from pathlib import Path

    from rig.log import load_trial

    path = Path(__file__).resolve().parent.parent / "tests" / "data" / "giacomel-sepiolite-velstep2.csv"
    warm = load_trial(path)
    diagnose(warm.select(np.arange(len(warm)) < 2000))  # JIT warm-up
    t0 = time.perf_counter()
    trial = load_trial(path)
    t_read = time.perf_counter() - t0
    d = diagnose(trial)
    dt = time.perf_counter() - t0
    print(f"real: {path.name} ({len(trial)} rows, {d.timings['n_bins']} fit bins): {dt:.1f} s (reading {t_read:.1f} s; "
          f"budget 20 s) findings={[f.cause for f in d.findings]}; load average {os.getloadavg()[0]:.2f}", flush=True)


def clean(n):
    bad = 0
    for seed in range(n):
        rate = (25.0, 100.0, 1000.0)[seed % 3]
        proto = ("paper", "varied")[seed % 2]
        # every fifth record is long (1 h at 100 Hz or 1 kHz: where small periodic "findings" showed)
        dur = 3600.0 if seed % 5 == 4 and rate > 25.0 else 600.0
        trial, _ = make_record(SynthSpec(rate_hz=rate, duration_s=dur, seed=1000 + seed, protocol=proto, noise_scale=NOISE,
                                         with_ref=bool(seed % 4 < 2)))
        rep = diagnose(trial).report()
        ff = [f["cause"] for f in rep["findings"]] + [u["follows"] for u in rep["unexplained"]]
        bad += bool(ff)
        print(f"clean seed {1000 + seed} {rate:g} Hz {dur:g} s {proto}: {ff or 'nothing'}", flush=True)
    import os
    print(f"load average {os.getloadavg()[0]:.2f}, noise scale {NOISE:g}")
    print(f"false-finding rate: {bad}/{n} = {100.0 * bad / n:.1f} %")


def accuracy(n):
    import os

    only = [e for e in os.environ.get("BENCH_EFFECTS", "").split(",") if e]
    for eff in [e for e in EFFECTS if not only or e in only]:
        ok = 0
        named = 0
        errs = []
        for seed in range(n):
            rng = np.random.default_rng(500 + seed)
            base = "steady_state" if eff == "time_delay" else "rate_state"
            rate = (25.0, 100.0)[seed % 2] if eff not in ("sensor_lag", "finite_stiffness") else 100.0
            trial, truth = make_record(SynthSpec(rate_hz=rate, effects={eff: random_effect(eff, rng)},
                                                 seed=500 + seed, duration_s=600.0, protocol="varied", noise_scale=NOISE,
                                                 baseline=base, with_ref=bool(seed % 2)))
            rep = diagnose(trial, baseline=base).report()
            if rep["findings"] and rep["findings"][0]["cause"] == eff:
                named += 1
                e = max((abs(v - truth["params"][k]) / abs(truth["params"][k])
                         for k, v in rep["findings"][0]["params"].items()), default=0.0)
                errs.append(e)
                ok += e <= 0.25
        print(f"{eff:24s} named {named}/{n}, within 25 %: {ok}/{n}, median worst-param error "
              f"{100 * np.median(errs) if errs else float('nan'):.1f} %", flush=True)


def coverage(n):
    """Issue 20, Deliver 6: over ``n`` generated records with known truth (clean and load-point
    spring records, 25/100 Hz, with and without position_ref_um), how often the final model's
    +-1 params_sd (and L's interval) covers the truth; a 68 % interval should cover it in 55-80 %."""
    import os

    hits: dict[str, list[bool]] = {}
    t0 = time.perf_counter()
    for seed in range(n):
        rate = (25.0, 100.0)[seed % 2]
        spring = seed % 3 == 2
        eff = {"finite_stiffness": {"stiffness_kN_per_m": 150.0 + 50.0 * (seed % 5)}} if spring else {}
        trial, truth = make_record(SynthSpec(rate_hz=rate, duration_s=600.0, seed=900 + seed, protocol="varied",
                                             effects=eff, with_ref=bool(seed % 4 < 2), noise_scale=NOISE))
        if spring:
            trial.metadata["position_source"] = "load_point"
        rep = diagnose(trial).report()
        m = rep["model"]
        sd, iv = m.get("params_sd", {}), m.get("intervals", {})
        for k in ("A_mu", "B_mu", "L_um", "stiffness_kN_per_m"):
            if k not in truth["params"] or k not in m["params"] or sd.get(k) is None:
                continue
            hits.setdefault(k, []).append(abs(m["params"][k] - truth["params"][k]) <= sd[k])
            if k in iv:
                hits.setdefault(k + " (interval)", []).append(iv[k][0] <= truth["params"][k] <= iv[k][1])
        print(f"coverage seed {900 + seed} {rate:g} Hz{' spring' if spring else ''}: "
              + " ".join(f"{k}={m['params'][k]:.4g}±{sd.get(k) or float('nan'):.2g} (truth {truth['params'][k]:.4g})"
                         for k in ("A_mu", "B_mu", "L_um", "stiffness_kN_per_m") if k in m["params"]
                         and k in truth["params"]), flush=True)
    print("| parameter | records | covered by ±1 sd (68 % interval) |\n|---|---|---|")
    for k, v in hits.items():
        print(f"| {k} | {len(v)} | {sum(v)}/{len(v)} = {100.0 * sum(v) / len(v):.0f} % |")
    print(f"{time.perf_counter() - t0:.0f} s wall, load average {os.getloadavg()[0]:.2f}, noise scale {NOISE:g}")


NOISE = float(sys.argv[3]) if len(sys.argv) > 3 else 1.0


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "speed"
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 10
    {"speed": lambda: speed(), "real": lambda: real(), "clean": lambda: clean(n), "accuracy": lambda: accuracy(n),
     "coverage": lambda: coverage(n)}[what]()
