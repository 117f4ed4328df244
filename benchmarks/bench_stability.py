"""Stability of steady sliding on the full simulated rig: paper (eq. 8, fixture force units),
the discrete-time analysis of the rig's loop (rig.analysis.stability.k_cr_loop: PID at 1 kHz,
zero-order hold, the rig's actuator and sensors) and the simulated boundary (a kp scan with
the criterion of stability.sliding_run), for the three lubricants, PD (ki = 0) and PID
(the profile's ki). Writes docs/stability-map.png and docs/stability-map.json.

Run: python benchmarks/bench_stability.py [--quick | --replot]"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from rig.analysis import stability as S
from rig.model.paper import TABLE2
from rig.config.profile import default_profile_path, load_profile

ROOT = Path(__file__).resolve().parents[1]


def replot():
    scans = json.loads((ROOT / "docs" / "stability-map.json").read_text())
    S.plot_map(scans, ROOT / "docs" / "stability-map.png",
               title="full simulated rig at V0 = 1 µm/s: kp scan (criterion: stuck fraction, velocity spread)")


def main():
    if "--replot" in sys.argv:
        return replot()
    quick = "--quick" in sys.argv
    prof = load_profile(default_profile_path())
    N = prof.normal.nominal_force_N
    scans = []
    t_all = time.perf_counter()
    print(f"load average at start: {os.getloadavg()}")
    for name in TABLE2:
        model = prof.friction_model(name)
        a_eff = S.effective_A_mu(model, 1.0)
        for ki in (0.0, prof.controller.ki_N_per_um_s):
            k8 = S.k_cr_eq8_N_per_um(a_eff, model.get("B_mu"), model.get("L_um"), N, prof.actuator.moving_mass_kg,
                                     prof.controller.kd_N_s_per_um, 1.0)
            lm = S.LoopModel.from_profile(prof, model, ki_N_per_um_s=ki)
            k_lin = S.k_cr_loop(lm)
            factors = S.SCAN_FACTORS
            k_ref = k_lin
            if not k_lin:
                # no finite k_cr in the analysis: scan down from the paper's value
                k_ref = k8
                factors = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5)
            if quick:
                factors = factors[::3]
            for noise, bump in ((True, 0.05), (False, 0.005)):
                if not noise and (not ki or not k_lin):
                    continue  # the noise-free check is for the PID's gradual (noise-driven) onset
                t0 = time.perf_counter()
                # noise-free: a 0.005 L bump must grow to the criterion by itself: 3000 s runs
                r = S.scan_boundary(name, ki_N_per_um_s=ki, factors=factors, k_ref_N_per_um=k_ref, bump_L=bump,
                                    sensor_noise=noise, duration_s=None if noise else 3000.0)
                r["k_cr_eq8_N_per_um"] = k8
                lv = prof.sensors.lvdt
                if noise:
                    # what the LVDT noise alone drives in the linear loop (stability.noise_spread)
                    for x in r["runs"]:
                        x["spread_linear_noise"] = S.noise_spread(lm, x["kp_N_per_um"], lv.noise_sigma_um,
                                                                  lv.quantization_um)
                    r["k_noise_criterion_N_per_um"] = S.k_noise_criterion(lm, lv.noise_sigma_um,
                                                                          lv.quantization_um)
                r["k_cr_table2_per_rider_kN_per_m"] = TABLE2[name]["k_cr_kN_per_m"][0]
                scans.append(r)
                dt = time.perf_counter() - t0
                lo, hi = r["bracket_N_per_um"]
                rb = r["rel_bracket"] or (float("nan"), float("nan"))
                print(f"{name:9s} {'PID' if ki else 'PD ':3s} ki={ki:g} {'noisy' if noise else 'noise-free'}: Table 2 (per rider) "
                      f"{TABLE2[name]['k_cr_kN_per_m'][0]:6.1f}  eq.8 fixture {k8 * 1e3:7.2f}  "
                      f"loop analysis {k_lin * 1e3 if k_lin else float('nan'):7.2f}  "
                      f"simulated in [{lo * 1e3 if lo else float('nan'):.2f}, {hi * 1e3 if hi else float('nan'):.2f}] "
                      f"kN/m, [{100 * rb[0]:+.1f}, {100 * rb[1]:+.1f}] % of the analysis  "
                      f"({len(r['runs'])} runs x {r['duration_s']:.0f} s, {dt:.1f} s)")
                if r.get("k_onset_N_per_um"):
                    print(f"      onset of a sustained oscillation (spread > {S.ONSET_SPREAD:g} V0): "
                          f"{r['k_onset_N_per_um'] * 1e3:.2f} kN/m, {100 * r['onset_rel_diff']:+.1f} % vs the analysis")
                if r.get("k_noise_criterion_N_per_um"):
                    kn = r["k_noise_criterion_N_per_um"]
                    print(f"      linear loop + LVDT noise: spread {S.SPREAD_MAX:g} V0 reached at {kn * 1e3:.2f} kN/m "
                          f"({100 * (kn / k_lin - 1):+.1f} % vs k_cr)")
                for x in r["runs"]:
                    lin = x.get("spread_linear_noise")
                    print(f"      kp {x['kp_N_per_um'] * 1e3:8.2f} kN/m  stuck {x['stuck_fraction']:.3f}  spread "
                          f"{x['spread']:.3f}" + (f" (linear + noise {lin:.3f})" if lin is not None else "") +
                          f"  v_max {x['v_max_um_s']:.2f}  {'STICK-SLIP' if x['stick_slip'] else 'steady'}")
    print(f"criterion: {scans[0]['criterion']}")
    print(f"total {time.perf_counter() - t_all:.0f} s, load average at end: {os.getloadavg()}")
    if not quick:
        S.plot_map(scans, ROOT / "docs" / "stability-map.png",
                   title="full simulated rig at V0 = 1 µm/s: kp scan (criterion: stuck fraction, velocity spread)")
        (ROOT / "docs" / "stability-map.json").write_text(json.dumps(scans, indent=1, default=float) + "\n")
        print("wrote docs/stability-map.png, docs/stability-map.json")


if __name__ == "__main__":
    main()
