"""Coverage of the 68 % intervals: over simulated trials with known truth, how often each
parameter's reported interval contains the truth (issue 20, Deliver 6: 55-80 % is honest).

    nice -n 10 .venv/bin/python benchmarks/bench_coverage.py [--trials 20] [--first 0]
        [--engine sim|main|synth|both|all]
        [--estimators "identify whole-record (jacobian),diagnose final model"] [--out rows.json]
    .venv/bin/python benchmarks/bench_coverage.py --merge a.json b.json   # one table of saved runs

Trials: the paper's step protocol (rig.analysis.reproduce.step_recipe on the simulated rig, or
the kinematic generator's paper_step_protocol) or the README's main job (``main``: its recipe on
the simulated rig), boundary lubricant, truth drawn per trial around
Table 2 (A, B, L within +-15 %), fixed seeds. Each trial's record goes to every estimator of
:data:`ESTIMATORS`; an estimator returns ``{name: (value, lo, hi) or None}`` for A_mu, B_mu,
L_um (None: no interval, left out of that row). To add one: write ``def est(trial) -> dict``
and register it in ESTIMATORS; the table gains its rows. Prints a line per trial, then the
table (markdown: coverage with its binomial standard error, mean bias, rms pull = error /
half-width) beside os.getloadavg(). The binomial noise matters: over n trials a true coverage
p = 0.68 is counted with a standard error sqrt(p (1 - p) / n), 10.4 points at 20 trials (a
true 68 % falls outside 55-80 % about 1 time in 4) and 7.4 at 40; a row is only "off" when its
count is more than about two standard errors outside the 55-80 % band. ``--out`` saves each
trial's values (JSON) so that runs over disjoint trials (``--first``) make one table (``--merge``).
"""

from __future__ import annotations

import argparse
import json
import math
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


def binomial_se(k: int, n: int, p: float = 0.68) -> float:
    """Standard error of a coverage counted over n trials, at the nominal p (a fraction)."""
    return math.sqrt(p * (1.0 - p) / n) if n else float("nan")


def verdict(k: int, n: int, lo: float = 0.55, hi: float = 0.80) -> str:
    """'in', 'low' or 'high' when k/n is more than two binomial standard errors outside [lo, hi],
    else 'in (noise)' when outside the band but within two standard errors of it."""
    if not n:
        return "-"
    f, se = k / n, binomial_se(k, n)
    if f < lo - 2 * se:
        return "low"
    if f > hi + 2 * se:
        return "high"
    return "in" if lo <= f <= hi else "in (noise)"


def run_trials(engines, names, first: int, n: int, prog) -> list[dict]:
    """Each trial's estimates as rows {engine, estimator, trial, param, truth, value, lo, hi}."""
    rows = []
    task = prog.add_task("trials", total=n * len(engines))
    for e in engines:
        for k in range(first, first + n):
            truth, tr = make_trial(e, k)
            for name in names:
                res = ESTIMATORS[name](tr)
                for p in PARAMS:
                    if res[p] is not None:
                        rows.append({"engine": e, "estimator": name, "trial": k, "param": p,
                                     "truth": truth[p], "value": res[p][0], "lo": res[p][1], "hi": res[p][2]})
                prog.console.print(f"{e} {k} {name}: " + " ".join(
                    f"{p} {res[p][0]:.4g} [{res[p][1]:.4g}, {res[p][2]:.4g}] (truth {truth[p]:.4g})"
                    if res[p] else f"{p} -" for p in PARAMS))
            prog.advance(task)
    return rows


def table(rows: list[dict]) -> list[str]:
    """Markdown: per (records, estimator), each parameter's coverage +- its binomial standard error
    (count, and whether it is off beyond the noise), mean bias and rms pull."""
    out = ["| records | estimator | " + " | ".join(f"{p}: covered (68 %) +- se" for p in PARAMS) + " | " +
           " | ".join(f"{p}: mean bias (rms pull)" for p in PARAMS) + " |",
           "|---|---|" + "---|" * (2 * len(PARAMS))]
    keys = list(dict.fromkeys((r["engine"], r["estimator"]) for r in rows))
    for e, name in keys:
        cov, bias = [], []
        for p in PARAMS:
            rr = [r for r in rows if (r["engine"], r["estimator"], r["param"]) == (e, name, p)]
            k = sum(r["lo"] <= r["truth"] <= r["hi"] for r in rr)
            n = len(rr)
            b = [(r["value"] - r["truth"]) / r["truth"] for r in rr]
            # pull: the error over the interval's half-width (1 for an honest interval, in rms)
            pull = [(r["value"] - r["truth"]) / max(0.5 * (r["hi"] - r["lo"]), 1e-300) for r in rr]
            cov.append(f"{100 * k / max(n, 1):.0f} +- {100 * binomial_se(k, n):.0f} % ({k}/{n}, {verdict(k, n)})")
            bias.append(f"{100 * np.mean(b):+.1f} % ({np.sqrt(np.mean(np.square(pull))):.2f})" if n else "-")
        out.append(f"| {LABELS[e]} | {name} | " + " | ".join(cov) + " | " + " | ".join(bias) + " |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--first", type=int, default=0, help="first trial's index (seeds 1000 + k and k)")
    ap.add_argument("--engine", choices=("sim", "main", "synth", "both", "all"), default="both")
    ap.add_argument("--estimators", default="identify whole-record (jacobian)",
                    help=f"comma-separated names of ESTIMATORS (all: {', '.join(ESTIMATORS)})")
    ap.add_argument("--out", type=Path, help="save each trial's values here (JSON)")
    ap.add_argument("--merge", type=Path, nargs="+", help="print one table of saved runs, run nothing")
    a = ap.parse_args(argv)
    if a.merge:
        rows = [r for f in a.merge for r in json.loads(f.read_text())]
        print("\n".join(table(rows)))
        return 0
    names = [n.strip() for n in a.estimators.split(",") if n.strip()]
    engines = {"both": ("sim", "synth"), "all": ("sim", "main", "synth")}.get(a.engine, (a.engine,))
    t0 = time.perf_counter()
    with Progress() as prog:
        rows = run_trials(engines, names, a.first, a.trials, prog)
    if a.out:
        a.out.write_text(json.dumps(rows))
    print(f"\n{a.trials} trials per engine (from {a.first}), {time.perf_counter() - t0:.0f} s, load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("\n".join(table(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
