"""Coverage of the 68 % intervals: over simulated trials with known truth, how often each
parameter's reported interval contains the truth (issue 20, Deliver 6: 55-80 % is honest).

    nice -n 10 .venv/bin/python benchmarks/bench_coverage.py [--trials 20] [--engine sim|main|synth|both|all]
        [--estimators "identify whole-record (jacobian),diagnose final model"]

Trials: the paper's step protocol (rig.analysis.reproduce.step_recipe on the simulated rig, or
the kinematic generator's paper_step_protocol) or the README's main job (``main``: its recipe on
the simulated rig), boundary lubricant, truth drawn per trial around
Table 2 (A, B, L within +-15 %), fixed seeds. Each trial's record goes to every estimator of
:data:`ESTIMATORS`; an estimator returns ``{name: (value, lo, hi) or None}`` for A_mu, B_mu,
L_um (None: no interval, left out of that row). To add one: write ``def est(trial) -> dict``
and register it in ESTIMATORS; the table gains its rows. Prints a line per trial, then the
table (markdown: coverage, mean bias, rms pull = error / half-width) beside os.getloadavg().
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rich.progress import Progress  # noqa: E402

PARAMS = ("A_mu", "B_mu", "L_um")
TRUTH = {"A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.2}
MAIN_RECIPE = Path(__file__).resolve().parents[1] / "config" / "recipes" / "velocity-steps.yaml"
LABELS = {"sim": "simulated rig (closed loop, paper protocol, 25 Hz)",
          "main": "simulated rig (closed loop, the README's main job, 25 Hz)",
          "synth": "generated (open loop, 25 Hz)"}


def whole_record(trial) -> dict:
    """identify's whole-record fit (slip law, Jacobian errors with the effective sample size)."""
    from rig.analysis.identify import identify_trials

    w = identify_trials([trial], directions="up").report()["whole_record"]
    return {k: (w["params"][k], *w["intervals"][k]) for k in PARAMS}


def whole_record_bootstrap(trial) -> dict:
    """identify's whole-record fit with --uncertainty bootstrap:30."""
    from rig.analysis.identify import identify_trials

    w = identify_trials([trial], directions="up", uncertainty="bootstrap:30").report()["whole_record"]
    return {k: (w["params"][k], *w["intervals"][k]) for k in PARAMS}


def diagnose_final(trial) -> dict:
    """diagnose's final model: its value +- params_sd, or its interval where it reports one (L_um)."""
    from rig.diagnosis import diagnose

    m = diagnose(trial).report()["model"]
    out = {}
    for k in PARAMS:
        v, sd = m["params"].get(k), m.get("params_sd", {}).get(k)
        # no standard error (a final fit without a Jacobian): no interval, counted apart
        out[k] = None if v is None or sd is None else (v, *m.get("intervals", {}).get(k, (v - sd, v + sd)))
    return out


#: name -> estimator(trial) -> {param: (value, lo, hi)}
ESTIMATORS = {"identify whole-record (jacobian)": whole_record,
              "identify whole-record (bootstrap:30)": whole_record_bootstrap,
              "diagnose final model": diagnose_final}


def make_trial(engine: str, k: int):
    """Trial k: truth drawn with a fixed seed, the record from the simulated rig or the generator."""
    from rig.analysis.reproduce import step_recipe
    from rig.model.spec import FrictionModel

    rng = np.random.default_rng(1000 + k)
    truth = {p: TRUTH[p] * float(rng.uniform(0.85, 1.15)) for p in PARAMS}
    model = FrictionModel(params={"mu0": 0.1, **truth})
    if engine in ("sim", "main"):
        from rig.config.profile import default_profile_path, load_profile
        from rig.config.recipe import load_recipe
        from rig.session.sim import simulate

        prof = load_profile(default_profile_path())
        # main: the README's main job (config/recipes/velocity-steps.yaml: 40 µm/s², feed-forward on,
        # 2 s holds; its planner's 6 L before each step), with this trial's truth and seed
        recipe = load_recipe(MAIN_RECIPE) if engine == "main" else \
            step_recipe("boundary", seed=k, slip_before_um=max(120.0, 6.0 * truth["L_um"]))
        log, _ = simulate(recipe, prof, model, seed=k)
        return truth, log.trial_data(25.0, source=f"{engine}:{k}")
    from rig.sim import synth

    return truth, synth.generate(model, synth.paper_step_protocol(), seed=k).trial


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--engine", choices=("sim", "main", "synth", "both", "all"), default="both")
    ap.add_argument("--estimators", default="identify whole-record (jacobian)",
                    help=f"comma-separated names of ESTIMATORS (all: {', '.join(ESTIMATORS)})")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.estimators.split(",") if n.strip()]
    engines = {"both": ("sim", "synth"), "all": ("sim", "main", "synth")}.get(a.engine, (a.engine,))
    hits = {(e, n): {p: [] for p in PARAMS} for e in engines for n in names}
    bias = {(e, n): {p: [] for p in PARAMS} for e in engines for n in names}
    pulls = {(e, n): {p: [] for p in PARAMS} for e in engines for n in names}
    t0 = time.perf_counter()
    with Progress() as prog:
        task = prog.add_task("trials", total=a.trials * len(engines))
        for e in engines:
            for k in range(a.trials):
                truth, tr = make_trial(e, k)
                for n in names:
                    res = ESTIMATORS[n](tr)
                    for p in PARAMS:
                        if res[p] is None:
                            continue
                        v, lo, hi = res[p]
                        hits[(e, n)][p].append(lo <= truth[p] <= hi)
                        bias[(e, n)][p].append((v - truth[p]) / truth[p])
                        pulls[(e, n)][p].append((v - truth[p]) / max(0.5 * (hi - lo), 1e-300))
                    prog.console.print(f"{e} {k} {n}: " + " ".join(
                        f"{p} {res[p][0]:.4g} [{res[p][1]:.4g}, {res[p][2]:.4g}] (truth {truth[p]:.4g})"
                        if res[p] else f"{p} -" for p in PARAMS))
                prog.advance(task)
    print(f"\n{a.trials} trials per engine, {time.perf_counter() - t0:.0f} s, load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| records | estimator | " + " | ".join(f"{p}: covered (68 %)" for p in PARAMS) + " | " +
          " | ".join(f"{p}: mean bias (rms pull)" for p in PARAMS) + " |")
    print("|---|---|" + "---|" * (2 * len(PARAMS)))
    for (e, n), h in hits.items():
        cov = " | ".join(f"{100 * np.mean(h[p]):.0f} % ({sum(h[p])}/{len(h[p])})" for p in PARAMS)
        # pull: the error over the interval's half-width (1 for an honest interval, in rms)
        b = " | ".join(f"{100 * np.mean(bias[(e, n)][p]):+.1f} % "
                       f"({np.sqrt(np.mean(np.square(pulls[(e, n)][p]))):.2f})" for p in PARAMS)
        print(f"| {LABELS[e]} | {n} | {cov} | {b} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
