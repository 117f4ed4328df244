"""Reproduce Table 2 of Dupont & Dunlap (1995) on the simulated rig.

For each lubricant (dry, paraffin oil, boundary lubricant), ``n`` simulated trials
of the paper's protocol (section 4.2: velocity steps 1->2, 1->5, 1->10 µm/s from
steady sliding, logged at 25 Hz with the rig's sensor noise), each with its own
friction parameters, are identified by the paper's method
(:mod:`rig.analysis.identify`); the trial values (mean over the trial's three
steps) are averaged over trials: mean ± standard error of the mean, as in Table 2.

**Drawing per-trial values.** Table 2 gives the standard deviation *of the mean*
over at least eight trials, so the trial-to-trial standard deviation is
``sd = sem * sqrt(8)`` (the paper's minimum n; a larger n would mean a larger
spread). Each trial's A, B, L are drawn independently from normal
distributions with the Table-2 mean and that sd, truncated at ±2 sd (and at
A >= 0, L >= 2 µm, B > A); the truncation is symmetric, so the population mean
stays the Table-2 mean. Paraffin's A is "0.0*" in Table 2 (below the load cell's
noise): the trials use the simulated rig profile's value (2e-4 by default,
a direct jump ``2 N A ln 10 = 0.09 N`` under the ±0.25 N noise), because a
law with no direct effect at all makes the simulated interface creep jerkily
(see docs/sim.md); the tolerance for A there is the load cell's noise level
``0.25 N / (2 N ln 10) = 5.4e-4``. A draw whose critical stiffness (eq. 13 in
the fixture's force units) exceeds half of the simulated controller's kp is drawn
again: on the rig it would stick-slip, and the paper's identification needs
steady sliding (the paper set kp "as high as possible").

The recovered means are compared with the means of the values the trials were
made with (the identification's error), and with Table 2; ``k_cr`` is eq. (13)
on the means, with the propagated error (Table 2's own convention).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from rig.analysis.identify import _r, identify_trials, k_cr_table2, mean_sem
from rig.data import atomic_write_text
from rig.model.paper import TABLE2
from rig.model.spec import FrictionModel

SCHEMA = "rig.reproduce/1"
PAPER_MIN_TRIALS = 8
PARAFFIN_A_DEFAULT = 2e-4
A_NOISE_LEVEL = 0.25 / (2 * 100.0 * math.log(10.0))


def draw_trial_params(lubricant: str, n: int, rng: np.random.Generator, *, paraffin_A: float = PARAFFIN_A_DEFAULT,
                      kp_max_N_per_um: float | None = None, normal_force_N: float = 100.0):
    """Per-trial (A_mu, B_mu, L_um), see the module docstring. With ``kp_max_N_per_um``,
    draws whose quasi-static critical stiffness of the fixture, ``2 N (B - A) / L``
    (eq. 13 in force units), exceeds half of it are drawn again: such a trial would
    stick-slip on the rig and could not have been a velocity-step trial."""
    row = TABLE2[lubricant]
    out = []
    while len(out) < n:
        vals = {}
        for k in ("A_mu", "B_mu", "L_um"):
            mean, sem = row[k]
            sd = sem * math.sqrt(PAPER_MIN_TRIALS)
            z = rng.standard_normal()
            while abs(z) > 2.0:
                z = rng.standard_normal()
            vals[k] = mean + sd * z
        if lubricant == "paraffin":
            vals["A_mu"] = paraffin_A
        if vals["A_mu"] < 0 or vals["L_um"] < 2.0 or vals["B_mu"] <= vals["A_mu"]:
            continue
        if kp_max_N_per_um is not None and \
                2 * normal_force_N * (vals["B_mu"] - vals["A_mu"]) / vals["L_um"] > 0.5 * kp_max_N_per_um:
            continue
        out.append(vals)
    return out


def run_trial(task: dict) -> dict:
    """Simulate and identify one trial; ``task`` holds plain values only (lubricant, k, params,
    mu0, engine, seed, profile path, whole_record), so it runs the same in any process."""
    lubricant, k, p, mu0, engine, seed = (task["lubricant"], task["k"], task["params"], task["mu0"],
                                          task["engine"], task["seed"])
    whole_record = task["whole_record"]
    model = FrictionModel(params={"mu0": mu0, **p})
    t0 = time.perf_counter()
    if engine == "sim":
        from rig.analysis.simrun import run_sim_trial, step_recipe
        from rig.config.profile import default_profile_path, load_profile

        prof = load_profile(task["profile"] or default_profile_path())
        tr = run_sim_trial(step_recipe(lubricant, seed=seed, slip_before_um=max(120.0, 6.0 * p["L_um"])),
                           model, profile=prof,
                           seed=seed * 100003 + 1000 * list(TABLE2).index(lubricant) + k).trial
    else:
        from rig.sim import synth

        tr = synth.generate(model, synth.paper_step_protocol(pre_um=max(300.0, 6 * p["L_um"]),
                                                             back_um=max(300.0, 6 * p["L_um"])),
                            seed=seed * 100003 + k, lubricant=lubricant).trial
    t_sim = time.perf_counter() - t0
    idn = identify_trials([tr], directions="up", whole_record=whole_record)
    rep = idn.report
    row = {"truth": {k_: _r(v) for k_, v in p.items()},
           "recovered": {k_: rep["mean"][k_] for k_ in ("A_mu", "B_mu", "L_um")},
           "n_steps": rep["n_steps"], "sim_s": round(t_sim, 2),
           "steps": [{k_: s[k_] for k_ in ("v1_um_s", "v2_um_s", "A_mu", "B_mu", "L_um", "r2", "window_um")}
                     for s in rep["steps"]]}
    if whole_record:
        w = rep["whole_record"]
        row["whole_record"] = {k_: w["params"].get(k_) for k_ in ("A_mu", "B_mu", "L_um")}
    return row


def run_lubricant(lubricant: str, n_trials: int, *, seed: int = 0, profile=None, whole_record: bool = False,
                  progress=None, engine: str = "sim", map_fn=None) -> dict:
    """Simulate and identify ``n_trials`` trials of one lubricant. ``map_fn(fn, tasks)``
    (e.g. :func:`rig.catalog.batch.mapper`) runs the trials elsewhere; default serial here."""
    from rig.analysis.simrun import SIM_AVAILABLE

    rng = np.random.default_rng([seed, list(TABLE2).index(lubricant)])
    mu0 = 0.12
    prof = None
    kp_max = None
    if engine == "sim" and SIM_AVAILABLE:
        from rig.config.profile import default_profile_path, load_profile

        prof = load_profile(profile or default_profile_path())
        if lubricant in prof.lubricants:
            mu0 = prof.lubricants[lubricant].mu0
        kp_max = prof.controller.kp_N_per_um
    elif engine == "sim":
        engine = "synth"
    pars = draw_trial_params(lubricant, n_trials, rng, kp_max_N_per_um=kp_max)
    # one task per trial, by value (rig.catalog.batch runs them on Dask; serial by default)
    tasks = [{"lubricant": lubricant, "k": k, "params": p, "mu0": mu0, "engine": engine, "seed": seed,
              "profile": str(profile) if profile is not None else None, "whole_record": whole_record}
             for k, p in enumerate(pars)]
    if map_fn is None:
        trials_out = []
        for t in tasks:
            trials_out.append(run_trial(t))
            if progress:
                progress()
    else:
        trials_out = list(map_fn(run_trial, tasks))
    N = 100.0
    res = {"lubricant": lubricant, "n_trials": n_trials, "engine": engine, "mu0": mu0, "trials": trials_out,
           "n_trials_identified": sum(1 for t in trials_out if t["n_steps"] > 0)}
    for label, key in (("truth", "truth"), ("recovered", "recovered"), ("whole_record", "whole_record")):
        if key == "whole_record" and not whole_record:
            continue
        mean, sem = {}, {}
        # the same trials for truth and recovered: those the identification could use
        used = [t for t in trials_out if t["n_steps"] > 0]
        for k_ in ("A_mu", "B_mu", "L_um"):
            mean[k_], sem[k_] = mean_sem([t[key][k_] for t in used if t[key].get(k_) is not None])
        mean["k_cr_kN_per_m"], sem["k_cr_kN_per_m"] = k_cr_table2(mean["A_mu"], sem["A_mu"], mean["B_mu"],
                                                                  sem["B_mu"], mean["L_um"], sem["L_um"], N)
        res[label] = {"mean": {k_: _r(v) for k_, v in mean.items()}, "sem": {k_: _r(v) for k_, v in sem.items()}}
    paper = {k_: {"mean": TABLE2[lubricant][k_][0], "sem": TABLE2[lubricant][k_][1]}
             for k_ in ("A_mu", "B_mu", "L_um", "k_cr_kN_per_m")}
    res["paper"] = paper
    # the check: recovered means within the paper's standard errors of the trials' true means
    checks = {}
    for k_ in ("A_mu", "B_mu", "L_um"):
        tol = paper[k_]["sem"] if paper[k_]["sem"] > 0 else A_NOISE_LEVEL
        d = res["recovered"]["mean"][k_] - res["truth"]["mean"][k_]
        checks[k_] = {"diff": _r(d), "tolerance": _r(tol), "ok": bool(abs(d) <= tol)}
    res["checks"] = checks
    return res


def reproduce(n_trials: int = 8, *, seed: int = 0, lubricants=None, profile=None, whole_record: bool = False,
              progress=None, engine: str = "sim", map_fn=None) -> dict:
    lubricants = list(lubricants or TABLE2)
    out = {"schema": SCHEMA, "n_trials": n_trials, "seed": seed,
           "per_trial_sd": "Table-2 sem x sqrt(8), normal truncated at 2 sd",
           "lubricants": {}}
    for lub in lubricants:
        out["lubricants"][lub] = run_lubricant(lub, n_trials, seed=seed, profile=profile, whole_record=whole_record,
                                               progress=progress, engine=engine, map_fn=map_fn)
    return out


def write_json(rep: dict, path) -> None:
    atomic_write_text(path, json.dumps(rep, indent=2, allow_nan=False) + "\n")


def plot_reproduce(rep: dict, path) -> None:
    """Bars: paper vs recovered vs truth (mean ± sem) for A, B, L, k_cr per lubricant."""
    from rig.analysis.plots import _plt, save

    plt = _plt()
    keys = ("A_mu", "B_mu", "L_um", "k_cr_kN_per_m")
    fig, axs = plt.subplots(1, 4, figsize=(15, 3.8))
    lubs = list(rep["lubricants"])
    x = np.arange(len(lubs))
    for ax, k in zip(axs, keys):
        for j, (label, c) in enumerate((("paper", "0.5"), ("truth", "C2"), ("recovered", "C0"),
                                         ("whole_record", "C3"))):
            m, e = [], []
            for lub in lubs:
                r = rep["lubricants"][lub]
                if label == "paper":
                    m.append(r["paper"][k]["mean"])
                    e.append(r["paper"][k]["sem"])
                elif label in r:
                    m.append(r[label]["mean"][k] or 0.0)
                    e.append(r[label]["sem"][k] or 0.0)
            if len(m) == len(lubs):
                ax.bar(x + 0.2 * (j - 1.5), m, 0.2, yerr=e, color=c, label=label, capsize=2)
        ax.set_xticks(x)
        ax.set_xticklabels(lubs)
        ax.set_title(k)
    axs[0].legend(fontsize=7)
    fig.suptitle(f"Table 2 reproduction: {rep['n_trials']} simulated trials per lubricant (mean ± s.e.)")
    fig.tight_layout()
    save(fig, path)
