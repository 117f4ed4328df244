"""The full stability sweep (task: the boundary found by simulation must agree with eq. (8)
within 5 % for each lubricant of Table 2), with the light model of Fig. 1 and with the full
simulated rig (PD, ki = 0; the PID's bias carries the steady friction).
Run: python benchmarks/bench_identify_stability.py [--no-full-rig]"""

from __future__ import annotations

import sys
import time

from rig.analysis import stability as S
from rig.model.spec import FrictionModel
from rig.model.paper import TABLE2


def main():
    full = "--no-full-rig" not in sys.argv
    out = {"fig1": [], "full_rig": []}  # noqa: F841 (kept for interactive use)
    print("Fig. 1 system (mass 10 kg, kd 0.003 N s/µm, N 100 N, V0 1 µm/s), Table 2 means, 12 bisections:")
    for name in TABLE2:
        t0 = time.perf_counter()
        r = S.check_lubricant(name, iters=12, periods=30.0)
        dt = time.perf_counter() - t0
        out["fig1"].append({k: v for k, v in r.items() if k != "runs"})
        print(f"  {name:9s} A_eff={r['A_eff_mu']:.3g}  eq.8 {r['k_cr_eq8_N_per_um'] * 1e3:8.3f} kN/m  "
              f"simulated {r['k_sim_N_per_um'] * 1e3:8.3f} kN/m  diff {100 * r['rel_diff']:+.3f} %  ({dt:.1f} s)")
    # paraffin with A = 0 exactly and kd -> 0: eq. (8) diverges
    for kd in (3e-3, 3e-4, 3e-5, 0.0):
        k = S.k_cr_eq8_N_per_um(0.0, 0.0111, 22.4, 100.0, 10.0, kd, 1.0)
        print(f"  paraffin, A = 0, kd = {kd:g} N s/µm: eq. (8) k_cr = {k * 1e3:.4g} kN/m")
    m = FrictionModel.for_lubricant("paraffin", 0.12)
    r = S.check_lubricant("paraffin", kd_N_s_per_um=0.0, iters=12, model=m)
    print(f"  paraffin, A = 0, kd = 0, regularised law (A_eff = {r['A_eff_mu']:.3g}): eq. (8) "
          f"{r['k_cr_eq8_N_per_um'] * 1e3:.3f} kN/m, simulated {r['k_sim_N_per_um'] * 1e3:.3f} kN/m "
          f"({100 * r['rel_diff']:+.3f} %)")
    out["fig1"].append({k: v for k, v in r.items() if k != "runs"} | {"note": "kd = 0"})
    if full:
        print("Full simulated rig (config/rigs/sim.yaml, PD: ki = 0), the profile's lubricants:")
        for name in TABLE2:
            t0 = time.perf_counter()
            f = S.full_rig_boundary(name)
            dt = time.perf_counter() - t0
            out["full_rig"].append({k: v for k, v in f.items() if k != "runs"})
            ks = f["k_sim_N_per_um"]
            print(f"  {name:9s} eq.8 {f['k_cr_eq8_N_per_um'] * 1e3:8.3f} kN/m, with leakage damping "
                  f"{f['k_cr_eq8_with_leak_N_per_um'] * 1e3:8.3f} kN/m; SimRig "
                  f"{ks * 1e3 if ks else float('nan'):8.3f} kN/m "
                  f"(vs eq.8 {100 * f['rel_diff'] if ks else float('nan'):+.2f} %, vs eq.8+leak "
                  f"{100 * (ks / f['k_cr_eq8_with_leak_N_per_um'] - 1) if ks else float('nan'):+.2f} %)  ({dt:.1f} s)")
        # paraffin again without the derivative term (which injects the LVDT's noise)
        t0 = time.perf_counter()
        f = S.full_rig_boundary("paraffin", kd_N_s_per_um=0.0)
        ks = f["k_sim_N_per_um"]
        print(f"  paraffin, kd = 0: eq.8 {f['k_cr_eq8_N_per_um'] * 1e3:8.3f} kN/m, with leakage damping "
              f"{f['k_cr_eq8_with_leak_N_per_um'] * 1e3:8.3f} kN/m; SimRig {ks * 1e3 if ks else float('nan'):8.3f} "
              f"kN/m (vs eq.8+leak {100 * (ks / f['k_cr_eq8_with_leak_N_per_um'] - 1) if ks else float('nan'):+.2f} %)"
              f"  ({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
