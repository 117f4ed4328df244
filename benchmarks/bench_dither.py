"""What the paper's 0.1 % dither (500 Hz) does on the full simulated rig sliding at 1 µm/s,
with and without it (and, for comparison, 0.1 % of the valve's full scale), for servovalve
spool stiction bands of 0 to 5e-3 (command units; a real servovalve's threshold is < 0.5 %;
rig.sim.plant's stiction_band_cmd, set through the profile; config/rigs/sim.yaml: 1e-3).
Also the 500 Hz line the dither leaves in the unfiltered LVDT output (paper: "not
detectable"), against the LVDT's 0.076 µm quantization step.

Measured over the last 40 s of a 60 s run (boundary lubricant, PID of the profile): the
tracking error (reference - true LVDT-point position, rms and mean, µm), and stick-slip by
the criterion of rig.analysis.stability (stuck fraction of 0.1 s blocks below 0.1 V0,
spread of the block-mean velocity / V0); also the dither amplitude in command units.

Run: python benchmarks/bench_dither.py"""

from __future__ import annotations

import os
import time

import numpy as np

from rig.analysis import stability as S
from rig.config.profile import default_profile_path, load_profile
from rig.sim import SimRig

BANDS = (0.0, 1e-5, 1e-4, 5e-4, 1e-3, 2e-3, 5e-3)  # 1e-3: the profile's default (0.1 % threshold)


def run(band: float, dither: float, lub: str = "boundary", seed: int = 4, dur_s: float = 60.0,
        reference: str = "pid_output") -> dict:
    prof = load_profile(default_profile_path())
    prof = prof.model_copy(update={
        "controller": prof.controller.model_copy(update={"dither_amplitude_fraction": dither,
                                                         "dither_reference": reference}),
        "servovalve": prof.servovalve.model_copy(update={"stiction_band_cmd": band})})
    rig = SimRig(prof, lub, seed=seed)
    rate = prof.loop.rate_hz
    n = int(dur_s * rate)
    x = prof.stroke.home_um + np.arange(n) / rate
    out = rig.run(x)
    k0 = int(20 * rate)
    err = (out["position_ref_um"] - out["true_position_um"])[k0:]
    v = out["true_velocity_um_s"][k0:]
    every = int(S.BLOCK_S * rate)
    vb = v[: v.size // every * every].reshape(-1, every).mean(axis=1)
    amp_cmd = float(np.mean(np.abs(out["dither"][k0:]))) / prof.actuator.full_scale_force_N
    # the 500 Hz line in the unfiltered LVDT output (1 kHz samples: the Nyquist line, amplitude
    # 2 |mean(x_n (-1)^n)| after removing the ramp), true (noise-free) and as measured
    sgn = (-1.0) ** np.arange(n - k0)
    def line(y):
        y = y - np.polyval(np.polyfit(np.arange(y.size), y, 1), np.arange(y.size))
        return float(abs(np.mean(y * sgn)))  # cos(pi n) has amplitude 1: mean(y cos) = a/1
    lvdt_true = line(out["true_position_um"][k0:])
    lvdt_meas = line(out["position_um"][k0:])
    return {"err_rms_um": float(np.sqrt(np.mean(err ** 2))), "err_mean_um": float(err.mean()),
            "stuck": float(np.mean(vb < S.STUCK_BELOW_FRAC)), "spread": float(vb.std()),
            "v_max": float(vb.max()), "dither_cmd": amp_cmd, "lvdt_500_true_um": lvdt_true,
            "lvdt_500_meas_um": lvdt_meas}


def main():
    print(f"load average at start: {os.getloadavg()}")
    t0 = time.perf_counter()
    print("boundary lubricant, 1 µm/s, 60 s (last 40 s judged); dither 0.1 % of |PID output| (~0.02 N = 2e-6 "
          "of the 10 kN full scale)")
    for band in BANDS:
        for dither, ref in ((0.0, "pid_output"), (1e-3, "pid_output"), (1e-3, "full_scale")):
            r = run(band, dither, reference=ref)
            lab = "off        " if not dither else ("0.1% PID   " if ref == "pid_output" else "0.1% full-s")
            print(f"stiction band {band:7.1e} cmd ({band * 1e4:6.3g} N)  dither {lab}: "
                  f"tracking error rms {r['err_rms_um']:.3f} µm (mean {r['err_mean_um']:+.3f})  "
                  f"stuck {r['stuck']:.3f}  spread {r['spread']:.3f} V0  v_max {r['v_max']:.2f} µm/s  "
                  f"dither {r['dither_cmd']:.2e} cmd  LVDT 500 Hz line: true {r['lvdt_500_true_um']:.1e} µm, "
                  f"measured {r['lvdt_500_meas_um']:.1e} µm", flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s, load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
