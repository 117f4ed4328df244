"""Speed of `rig identify` on a one-hour 1 kHz CSV with a sawtooth position (issue 10 item 7,
issue 13: it ran past 180 s). Target: well under 30 s on this machine.

The record: 3.6 M rows, a 5 s cycle repeated 720 times -- 3 s at 5 um/s, 1.5 s at 20 um/s
(an up-step, 15 and 30 um of slip on its sides), 0.5 s back at -90 um/s (the return that makes
the sawtooth) -- friction from the
steady-state rate-and-state curve (a - b = -0.003 per e-fold) plus 0.25 N noise, LVDT noise
0.25 um quantized to 0.076 um. Written as a measured-data CSV and identified from the file,
as a user would (`rig identify FILE`), so the CSV reader is timed too.

Run: python benchmarks/bench_identify_long.py [--keep PATH]. Wall time after a warm-up call
(numba kernels compiled and cached); the machine is shared, so the load average is printed
beside every figure.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.analysis.identify import identify_trials
from rig.log import load_trial
from rig.data import TrialData, write_csv


def sawtooth_record(hours: float = 1.0, rate_hz: float = 1000.0, seed: int = 13) -> TrialData:
    rng = np.random.default_rng(seed)
    n = int(round(hours * 3600.0 * rate_hz))
    t = np.arange(n) / rate_hz
    phase = np.mod(t, 5.0)
    v = np.where(phase < 3.0, 5.0, np.where(phase < 4.5, 20.0, -90.0))  # um/s
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate_hz)])
    N = 100.0
    mu = np.sign(v) * (0.12 - 0.003 * np.log(np.abs(v)))
    F = 2.0 * N * mu + rng.normal(0.0, 0.25, n)
    xm = np.round((x + rng.normal(0.0, 0.25, n)) / 0.076) * 0.076
    n1 = N + rng.normal(0.0, 0.6, n)
    n2 = N + rng.normal(0.0, 0.6, n)
    return TrialData(time_s=t, position_um=xm, friction_N=F, normal_1_N=n1, normal_2_N=n2,
                     metadata={"normal_force_N": "100", "generator": "benchmarks/bench_identify_long.py"},
                     source="sawtooth")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", help="write the CSV here and keep it")
    ap.add_argument("--hours", type=float, default=1.0)
    a = ap.parse_args(argv)
    warm = sawtooth_record(hours=0.02)
    identify_trials([warm])  # compile / load the numba caches
    tr = sawtooth_record(hours=a.hours)
    with tempfile.TemporaryDirectory() as d:
        path = Path(a.keep) if a.keep else Path(d) / "sawtooth-1khz.csv"
        t0 = time.perf_counter()
        write_csv(tr, path)
        print(f"wrote {len(tr)} rows ({a.hours:g} h at 1 kHz) in {time.perf_counter() - t0:.1f} s")
        t0 = time.perf_counter()
        trial = load_trial(path)
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        idn = identify_trials([trial], names=[str(path)])
        t_id = time.perf_counter() - t0
        r = idn.report()
        la = os.getloadavg()
        print(f"rig identify {path.name}: read CSV {t_read:.1f} s (rig.data.read_csv) + identify {t_id:.1f} s "
              f"= {t_read + t_id:.1f} s (budget 30 s); load average {la[0]:.2f} {la[1]:.2f} on "
              f"{os.cpu_count()} cores; {r['n_steps']} steps accepted, {len(r['rejected_steps'])} rejected")
        t0 = time.perf_counter()
        idn = identify_trials([tr])
        print(f"identify on the same record in memory: {time.perf_counter() - t0:.1f} s; load average "
              f"{os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
