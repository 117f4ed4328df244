"""Speed of the identification (task: a one-hour 1 kHz record under 10 s, a 25 Hz trial
under 1 s). Run: python benchmarks/bench_identify.py. Times are wall-clock after a warm-up
call (numba kernels compiled and cached); the machine is shared, so they are pessimistic."""

from __future__ import annotations

import time

from rig.sim import synth
from rig.analysis.identify import identify_trials
from rig.model.spec import FrictionModel


def timed(fn, repeat=3):
    best = float("inf")
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main():
    m = FrictionModel.for_lubricant("boundary", 0.12)
    # warm-up (compilation)
    warm = synth.generate(m, synth.paper_step_protocol(), seed=0).trial
    identify_trials([warm])

    trial25 = synth.generate(m, synth.paper_step_protocol(), seed=1, rate_hz=25.0).trial
    for label, kw in (("per-step only", {"whole_record": False}), ("per-step + whole-record", {})):
        for ev in (True, False):
            t, idn = timed(lambda: identify_trials([trial25], use_events=ev, **kw))
            print(f"25 Hz trial ({len(trial25)} samples, {trial25.time_s[-1]:.0f} s), {label}, "
                  f"steps from {'events' if ev else 'data'}: {t:.3f} s ({idn.report()['n_steps']} steps)")

    # one hour at 1 kHz: the paper's protocol repeated
    highs = (2.0, 5.0, 10.0) * 4
    segs = synth.paper_step_protocol(highs=highs, pre_um=200.0, back_um=200.0)
    t0 = time.perf_counter()
    rec = synth.generate(m, segs, seed=2, rate_hz=1000.0)
    tr = rec.trial
    print(f"generated {len(tr)} samples ({tr.time_s[-1] / 3600:.2f} h at 1 kHz) in {time.perf_counter() - t0:.1f} s")
    for label, kw in (("per-step only", {"whole_record": False}), ("per-step + whole-record", {})):
        for ev in (True, False):
            t, idn = timed(lambda: identify_trials([tr], use_events=ev, **kw), repeat=2)
            r = idn.report()
            print(f"1 kHz, {tr.time_s[-1] / 3600:.2f} h, {label}, steps from {'events' if ev else 'data'}: "
                  f"{t:.2f} s ({r['n_steps']} steps; A={r['mean']['A_mu']:.4g} B={r['mean']['B_mu']:.4g} "
                  f"L={r['mean']['L_um']:.4g})")


if __name__ == "__main__":
    main()
