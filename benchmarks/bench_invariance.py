"""The answer depends on the physics only (diagnosis.md; issue 20, Deliver 1): every record the
project has x every harmless transformation -> causes and parameters, with a verdict.

    python benchmarks/bench_invariance.py            # everything: real, converted, synthetic, clean
    python benchmarks/bench_invariance.py real       # the shared real records and tests/data's converted ones
    python benchmarks/bench_invariance.py synth      # every cause, two clean, the load-point step
    python benchmarks/bench_invariance.py real basalt   # only the records whose label contains "basalt"
    python benchmarks/bench_invariance.py variants      # the real records x the same transformations with
                                                        # other parameters (VARIANTS: where the rate switches,
                                                        # which end is trimmed, other offsets, decimation by 3)

The causes column gives each finding's `stability` (when under 1) and `alternatives` in brackets.
Verdict per row (rig.diagnosis.transforms.differences, the spec's test): "same" when the causes are
those of the original and every parameter is within 25 % or within the reported uncertainty (the
original's value inside the copy's interval or +- error, or the copy's inside the original's, at
two errors; a stiffness and a force drift scaled with the forces under "scale", a position period's
phase moved with the first position); a parameter both reports flag as not determined ("(nd)" in
the table) and give no uncertainty for agrees. Otherwise what differs.
Printed with the load average (2 cores shared).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from rig.diagnosis import diagnose
from rig.diagnosis.transforms import (TRANSFORMS, decimate, differences, not_determined, origin_moved_um, shift,
                                      switch_rate, trim)
from rig.sim.synth import SynthSpec, make_record, random_effect

ROOT = Path(__file__).resolve().parent.parent
ONLY = ""  # the second argument: only the records whose label contains it
EFFECTS = ["second_state_variable", "aging_law", "sensor_lag", "finite_stiffness", "normal_force_variation",
           "slip_wear_drift", "force_offset_drift", "position_periodic", "time_delay"]


def real_records():
    from rig.log import load_trial

    paths = sorted((ROOT.parent / "shared" / "data" / "real").glob("*.csv")) + sorted((ROOT / "tests" / "data").glob(
        "giacomel-*.csv"))
    for p in paths:
        yield p.stem, load_trial(p), "rate_state"


def synth_records():
    for i, eff in enumerate(EFFECTS):
        rng = np.random.default_rng(700 + i)
        e = {eff: random_effect(eff, rng)}
        rate = 100.0 if eff in ("sensor_lag", "finite_stiffness") else 25.0
        trial, _ = make_record(SynthSpec(rate_hz=rate, duration_s=600.0, seed=700 + i, protocol="varied",
                                         effects=e, with_ref=bool(i % 2),
                                         baseline="steady_state" if eff == "time_delay" else "rate_state"))
        yield f"synth {eff}", trial, "steady_state" if eff == "time_delay" else "rate_state"
    for s in (1, 2):
        trial, _ = make_record(SynthSpec(rate_hz=25.0, duration_s=600.0, seed=800 + s, protocol="varied"))
        yield f"synth clean {s}", trial, "rate_state"
    trial, _ = make_record(SynthSpec(protocol=[(60.0, 1.0), (60.0, 10.0)], duration_s=120.0, rate_hz=100.0,
                                     effects={"finite_stiffness": {"stiffness_kN_per_m": 300.0}}, with_ref=False,
                                     seed=7))
    trial.metadata["position_source"] = "load_point"
    yield "synth load-point step k=300", trial, "rate_state"


def _trim_start(trial, frac: float = 0.03):
    t = np.asarray(trial.time_s, dtype=float)
    return trial.select(t >= t[0] + frac * (t[-1] - t[0]))


def _trim_end(trial, frac: float = 0.08):
    t = np.asarray(trial.time_s, dtype=float)
    return trial.select(t <= t[-1] - frac * (t[-1] - t[0]))


def _switch_at_step(trial):
    """10 Hz, then 100 Hz from half a second before the record's first velocity step (the issue's
    example: slow before the step, fast after it)."""
    from rig.diagnosis.core import _inputs
    from rig.diagnosis.prep import canonical

    steps = _inputs(canonical(trial))[1]
    t = np.asarray(trial.time_s, dtype=float)
    at = (float(steps[0].t_s) - 0.5) / (t[-1] - t[0]) if steps else 0.5
    return TRANSFORMS["rate10to100"](trial) if not steps else switch_rate(trial, 10.0, 100.0, max(at, 0.0))


# the spec's transformations with other parameters than TRANSFORMS': name -> (function, the verdict's kind)
VARIANTS = {
    "shift -50 s, -20 mm": (lambda tr: shift(tr, -50.0, -20000.0), "shift"),
    "shift +1.7e6 s, +123 mm": (lambda tr: shift(tr, 1.7e6, 123456.0), "shift"),
    "decimate3": (lambda tr: decimate(tr, 3), "decimate2"),
    "10 -> 100 Hz at the step": (_switch_at_step, "rate10to100"),
    "5 -> 50 Hz at 30 %": (lambda tr: switch_rate(tr, 5.0, 50.0, 0.3), "rate10to100"),
    "20 -> 200 Hz at 70 %": (lambda tr: switch_rate(tr, 20.0, 200.0, 0.7), "rate10to100"),
    "trim 3 % at the start": (_trim_start, "trim5"),
    "trim 8 % at the end": (_trim_end, "trim5"),
    "trim 2 % each end": (lambda tr: trim(tr, 0.02), "trim5"),
}


def _row(rep):
    causes = [f["cause"] for f in rep["findings"]]
    alts = {f["cause"]: ([f"stability {f['stability']:.1f}"] if f.get("stability") not in (None, 1.0) else [])
            + [a["cause"] for a in f.get("alternatives", [])] for f in rep["findings"]}
    params = {k: v for k, v in rep["model"]["params"].items() if k != "mu0" and k != "v_init_um_s"}
    return causes, alts, params


def verdict(ref: dict, got: dict, name: str, origin_um: float) -> str:
    """"same", or what differs (rig.diagnosis.transforms.differences: the spec's test)."""
    return "; ".join(differences(ref, got, name, origin_um)) or "same"


def fmt(params, loose=()) -> str:
    """``name=value``, with "(nd)" beside a value its report flags as not determined."""
    return " ".join(f"{k}={v:.3g}" + (" (nd)" if k in loose else "") for k, v in params.items() if v is not None)


def main(which: str = "all") -> int:
    from rich.progress import Progress

    recs = []
    if which in ("all", "real", "variants"):
        recs += list(real_records())
    if which in ("all", "synth"):
        recs += list(synth_records())
    # (name, transformation, the verdict's kind)
    table = VARIANTS if which == "variants" else {n: (f, n) for n, f in TRANSFORMS.items()}
    names = ["orig"] + list(table)
    t_start = time.perf_counter()
    lines = ["| record | transformation | causes (alternatives) | final model | verdict | time |",
             "|---|---|---|---|---|---|"]
    n_same = n_all = 0
    with Progress(transient=True) as bar:
        task = bar.add_task("records x transformations", total=len(recs) * len(names))
        for label, trial, baseline in recs:
            if ONLY and ONLY not in label:
                continue
            ref = None
            for name in names:
                bar.update(task, description=f"{label}: {name}")
                t2, kind = (trial, name) if name == "orig" else (table[name][0](trial), table[name][1])
                t0 = time.perf_counter()
                try:
                    rep = diagnose(t2, baseline=baseline).report()
                except ValueError as exc:
                    rep = {"findings": [{"cause": "(error: " + str(exc)[:60] + ")"}], "model": {"params": {}}}
                row = _row(rep)
                dt = time.perf_counter() - t0
                if ref is None:
                    ref, v = rep, "(reference)"
                else:
                    v = verdict(ref, rep, kind, 0.0 if kind == "shift" else origin_moved_um(trial, t2, kind))
                    n_all += 1
                    n_same += v == "same"
                cz = ", ".join(c + (f" ({'/'.join(row[1][c])})" if row[1].get(c) else "") for c in row[0]) or "none"
                nd = not_determined(rep) if rep["model"]["params"] else set()
                line = f"| {label} | {name} | {cz} | {fmt(row[2], nd)} | {v} | {dt:.1f} s |"
                lines.append(line)
                bar.console.print(line)
                bar.advance(task)
    print("\n".join(lines))
    print(f"\n{n_same}/{n_all} transformed records give the original's answer; {time.perf_counter() - t_start:.0f} s "
          f"wall, load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    if len(args) == 2 and args[0] in ("all", "real", "synth", "variants"):
        ONLY = args.pop()
    if len(args) > 1 or (args and args[0] not in ("all", "real", "synth", "variants")):
        print(__doc__ if args and args[0] in ("-h", "--help") else
              f"usage: python benchmarks/bench_invariance.py [all|real|synth|variants] (not {' '.join(args)!r})",
              file=sys.stdout if args and args[0] in ("-h", "--help") else sys.stderr)
        sys.exit(0 if args and args[0] in ("-h", "--help") else 2)
    sys.exit(main(args[0] if args else "all"))
