"""Speed of the simulated rig's closed loop (PID + dither + plant + sensors), logging excluded.

Reference: one hour at 1 kHz of a velocity-step-like trajectory (1 and 10 µm/s segments
of 250 µm, reversing direction at the ends of a 3 mm span), boundary lubricant.
Prints closed-loop ticks/s and the real-time factor (simulated time / wall time, and
/ CPU time of this process, which a shared machine disturbs less) for
(a) ``SimRig.run_blocks`` with 100-tick blocks (what ``rig run --sim`` iterates over),
(b) the numba kernel alone.

    python benchmarks/bench_sim.py [--hours 1.0] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from rig.sim import plant as pl
from rig.sim import SimRig


def velocity_step_reference(hours: float = 1.0, rate_hz: float = 1000.0, x_lo_um: float = 1000.0,
                            x_hi_um: float = 4000.0) -> np.ndarray:
    n = int(round(hours * 3600.0 * rate_hz))
    dt = 1.0 / rate_hz
    x = np.empty(n)
    pos = x_lo_um
    direction = 1.0
    i = 0
    k = 0
    while i < n:
        v = (1.0, 10.0)[k % 2]
        m = min(n - i, int(round(250.0 / v / dt)))
        seg = pos + direction * v * dt * np.arange(1, m + 1)
        x[i:i + m] = seg
        pos = seg[-1]
        i += m
        k += 1
        if (direction > 0 and pos >= x_hi_um) or (direction < 0 and pos <= x_lo_um):
            direction = -direction
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    xref = velocity_step_reference(args.hours)
    n = xref.size
    sim_s = n / 1000.0
    rig = SimRig(None, "boundary", seed=0)
    for _ in rig.run_blocks(xref[:5000]):  # compile / load the numba cache
        pass

    best = best_cpu = float("inf")
    for _ in range(args.repeat):
        rig = SimRig(None, "boundary", seed=0)
        t0, c0 = time.perf_counter(), time.process_time()
        ticks = 0
        for block in rig.run_blocks(xref, block_ticks=100):
            ticks += block["t_s"].size
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    assert ticks == n
    print(f"run_blocks (100-tick blocks, noise included): {n / best:,.0f} ticks/s, "
          f"real-time factor {sim_s / best:,.0f}x ({best:.2f} s wall for {sim_s / 3600:.2f} h); "
          f"CPU time: {n / best_cpu:,.0f} ticks/s, {sim_s / best_cpu:,.0f}x")

    noise = np.random.default_rng(0).standard_normal((n, 4))
    out = np.empty((pl.N_OUT, n))
    best_k = best_kc = float("inf")
    for _ in range(args.repeat):
        rig = SimRig(None, "boundary", seed=0)
        rig.reset(float(xref[0]), 1.0)
        t0, c0 = time.perf_counter(), time.process_time()
        pl.run_closed_loop(rig.q, rig.fp, rig.fs, rig.st, rig.ring, rig.c, rig.cs, xref, np.empty(0), 0, noise, 0, out, 0, n)
        best_k = min(best_k, time.perf_counter() - t0)
        best_kc = min(best_kc, time.process_time() - c0)
    print(f"numba kernel alone (noise pre-drawn):          {n / best_k:,.0f} ticks/s, "
          f"real-time factor {sim_s / best_k:,.0f}x; CPU time: {n / best_kc:,.0f} ticks/s, {sim_s / best_kc:,.0f}x")
    if hasattr(os, "getloadavg"):
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs (wall figures suffer when shared)")
    err = out[1] - out[11]
    print(f"check: max |x_ref - x_true| after 10 s = {np.abs(err[10000:]).max():.2f} µm, "
          f"NaN: {int(np.isnan(out).sum())}")


if __name__ == "__main__":
    main()
