"""``rig identify``, ``rig stribeck``, ``rig stability``, ``rig reproduce``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

console = Console(width=None if Console().is_terminal else 140)
err_console = Console(stderr=True)


def _fail(msg: str, code: int = 2):
    err_console.print(f"[red]error:[/red] {msg}", soft_wrap=True)
    raise typer.Exit(code)


def _load(paths: list[Path]):
    from rig.data import DataFormatError
    from rig.log import load_trial

    trials = []
    for p in paths:
        if not p.exists():
            _fail(f"{p}: no such file")
        try:
            trials.append(load_trial(p))
        except DataFormatError as exc:
            _fail(str(exc))
        except Exception as exc:  # noqa: BLE001 - e.g. a damaged MCAP
            _fail(f"{p}: cannot read: {exc}")
    return trials


def _fmt(v, nd=4):
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.{nd}g}"
    return str(v)


def identify_cmd(
    data: list[Path] = typer.Argument(..., help="One or more trial files (.csv or .mcap)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rig.identify/1 report here."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG (friction after each step, fits, windows)."),
    events: bool = typer.Option(True, "--events/--no-events", help="Use the log's step events when present."),
    velocity: str = typer.Option("local_poly", "--velocity", help="Velocity estimator for plots: paper | local_poly."),
    whole: bool = typer.Option(True, "--whole/--no-whole", help="Also fit the model to the whole record."),
    whole_velocity: str = typer.Option("segments", "--whole-velocity",
                                       help="Velocity for the whole-record fit: segments | local_poly | paper."),
    stiffness: Optional[bool] = typer.Option(None, "--stiffness/--no-stiffness",
                                             help="Whole-record fit with a machine stiffness (default: when the "
                                                  "file says its position is the load point)."),
    direction: str = typer.Option("both", "--direction", help="Steps to use: both | up | down."),
    min_ratio: float = typer.Option(1.25, "--min-ratio", help="Smallest velocity ratio counted as a step."),
):
    """Identify A, B, L by the paper's velocity-step method (eqs. 10-14) and a whole-record fit."""
    from rig.analysis.identify import identify_trials, write_json

    if direction not in ("both", "up", "down"):
        _fail(f"--direction must be both, up or down (got {direction!r})")
    if velocity not in ("paper", "local_poly"):
        _fail(f"--velocity must be paper or local_poly (got {velocity!r})")
    if whole_velocity not in ("segments", "paper", "local_poly"):
        _fail(f"--whole-velocity must be segments, paper or local_poly (got {whole_velocity!r})")
    trials = _load(data)
    try:
        idn = identify_trials(trials, use_events=events, velocity_method=velocity, whole_record=whole,
                              whole_velocity=whole_velocity, stiffness=stiffness, directions=direction,
                              min_ratio=min_ratio, names=[str(p) for p in data])
    except ValueError as exc:
        _fail(str(exc))
    rep = idn.report
    if not rep["steps"]:
        _fail(f"{', '.join(map(str, data))}: no velocity steps found (ratio >= {min_ratio})", 1)
    table = Table(title="velocity steps (eqs. 10-12)")
    for c in ("trial", "t (s)", "v1 (µm/s)", "v2 (µm/s)", "A_mu", "B_mu", "L (µm)", "r2", "window (µm)", "t_r (s)"):
        table.add_column(c, justify="right")
    for s in rep["steps"]:
        table.add_row(str(s["trial"]), _fmt(s["t_s"], 6), _fmt(s["v1_um_s"]), _fmt(s["v2_um_s"]), _fmt(s["A_mu"], 3),
                      _fmt(s["B_mu"], 3), _fmt(s["L_um"], 3), _fmt(s["r2"], 2), str(s["window_um"]),
                      _fmt(s.get("t_r_s"), 3) + (" [red]rejected[/red]" if "rejected" in s else ""))
    console.print(table)
    m, e = rep["mean"], rep["sem"]
    console.print(f"mean ± s.e. over {rep['sem_over']} (n={rep['n_steps'] if rep['sem_over'] == 'steps' else rep['n_trials']}): "
                  f"A_mu = {_fmt(m['A_mu'], 3)} ± {_fmt(e['A_mu'], 2)}, B_mu = {_fmt(m['B_mu'], 3)} ± {_fmt(e['B_mu'], 2)}, "
                  f"L = {_fmt(m['L_um'], 3)} ± {_fmt(e['L_um'], 2)} µm, k_cr (eq. 13) = {_fmt(m['k_cr_kN_per_m'], 3)} ± "
                  f"{_fmt(e['k_cr_kN_per_m'], 2)} kN/m, t_r (eq. 14) = {_fmt(m['t_r_s'], 3)} s")
    wr = rep.get("whole_record")
    for w in ([wr] if isinstance(wr, dict) else (wr or [])):
        if not w.get("ok", True) and "params" not in w:
            console.print(f"whole-record fit failed: {w.get('reason')}")
            continue
        parts = ", ".join(f"{k} = {_fmt(v, 4)} ± {_fmt(w['err_corr'].get(k), 2)}" for k, v in w["params"].items())
        console.print(f"whole-record fit ({w['model']}, velocity {w['velocity']}): {parts}; rms {_fmt(w['rms_N'], 3)} N")
    for r in rep.get("rejected_steps", []):
        console.print(f"rejected step at t = {_fmt(r['t_s'], 6)} s: {r['reason']}", highlight=False)
    for note in rep.get("notes", []):
        console.print(f"[yellow]note:[/yellow] {note}", highlight=False)
    if json_out:
        write_json(rep, json_out)
        console.print(f"wrote {json_out}")
    if plot:
        from rig.analysis.plots import plot_identification

        plot_identification(idn, plot)
        console.print(f"wrote {plot}")


def register(app: typer.Typer) -> None:
    app.command("identify")(identify_cmd)
    for name in ("stribeck", "stability", "reproduce"):
        mod_cmd = _optional(name)
        if mod_cmd is not None:
            app.command(name)(mod_cmd)


def _optional(name: str):
    return globals().get(f"{name}_cmd")


def stribeck_cmd(
    data: list[Path] = typer.Argument(..., help="Stepped-velocity pass(es), .csv or .mcap."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rig.stribeck/1 report here."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG like Figs. 6 and 7."),
    events: bool = typer.Option(True, "--events/--no-events", help="Use the log's level events when present."),
    window_um: float = typer.Option(50.0, "--window-um", help="Average over the last this many µm of each level."),
):
    """Steady-state friction per velocity level, up and down branches, and A - B by eq. (7)."""
    from rig.analysis.stribeck import plot_stribeck, stribeck, write_json

    trials = _load(data)
    rep = stribeck(trials, use_events=events, window_um=window_um, names=[str(p) for p in data])
    if not rep["levels"]:
        _fail(f"{', '.join(map(str, data))}: no velocity levels found", 1)
    table = Table(title=f"steady-state friction (last {window_um:g} µm of each level)")
    for c in ("branch", "v (µm/s)", "mu", "sd over trials", "trials"):
        table.add_column(c, justify="right")
    for d in ("up", "down"):
        for b in rep["branches"][d]:
            table.add_row(d, _fmt(b["v_um_s"]), _fmt(b["mu"], 5), _fmt(b["mu_sd"], 2), str(b["n_trials"]))
    console.print(table)
    for key, label in (("fit", "all levels"), ("fit_up", "up branch"), ("fit_down", "down branch")):
        f = rep[key]
        console.print(f"eq. (7), {label}: A - B = {_fmt(f['A_minus_B'], 4)} ± {_fmt(f['A_minus_B_err'], 2)}, "
                      f"mu0 = {_fmt(f['mu0'], 5)} (n={f['n']})")
    if json_out:
        write_json(rep, json_out)
        console.print(f"wrote {json_out}")
    if plot:
        plot_stribeck(rep, plot)
        console.print(f"wrote {plot}")


def stability_cmd(
    lubricant: Optional[str] = typer.Option(None, "--lubricant", help="dry | paraffin | boundary (Table 2 values)."),
    params: Optional[Path] = typer.Option(None, "--params", help="A rig identify JSON report (its mean A, B, L)."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="Rig profile (mass, kd, normal force); "
                                                                   "default config/rigs/sim.yaml."),
    margin: float = typer.Option(2.0, "--margin", help="Advice: kp >= margin x k_cr (eq. 8)."),
    v0: float = typer.Option(1.0, "--v0", help="Sliding velocity V0 (µm/s)."),
    simulate: bool = typer.Option(False, "--simulate", help="Check eq. (8) by closed-loop simulation (Fig. 1)."),
    full_rig: bool = typer.Option(False, "--full-rig", help="With --simulate: also bisect with the full simulated "
                                                            "rig (PD: ki = 0)."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write the stability map PNG."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the report as JSON."),
):
    """Critical stiffness by eqs. (8) and (13), PD gain advice, and the check by simulation."""
    from rig.analysis import stability as S
    from rig.data import atomic_write_text
    from rig.model.paper import TABLE2
    from rig.model.spec import FrictionModel

    if lubricant and params:
        _fail("give --lubricant or --params, not both")
    if margin <= 0:
        _fail(f"--margin must be positive (got {margin})")
    if v0 <= 0:
        _fail(f"--v0 must be positive (got {v0})")
    mass, kd, N = S.DEFAULT_MASS_KG, S.DEFAULT_KD_N_S_PER_UM, 100.0
    prof = None
    try:
        from rig.config.profile import default_profile_path, load_profile

        ppath = profile or default_profile_path()
        if profile is not None and not Path(profile).exists():
            _fail(f"{profile}: no such profile")
        prof = load_profile(ppath)
        mass, kd, N = prof.actuator.moving_mass_kg, prof.controller.kd_N_s_per_um, prof.normal.nominal_force_N
    except typer.Exit:
        raise
    except ImportError:
        pass
    except Exception as exc:  # noqa: BLE001 - ProfileError names file/field/line
        _fail(str(exc))
    sets: dict[str, dict] = {}
    if params:
        if not params.exists():
            _fail(f"{params}: no such file")
        try:
            rep = json.loads(params.read_text())
            m = rep["mean"]
            sets[params.stem] = {"A_mu": float(m["A_mu"]), "B_mu": float(m["B_mu"]), "L_um": float(m["L_um"])}
            N = float(rep.get("normal_force_N", N))
        except (KeyError, TypeError, ValueError) as exc:
            _fail(f"{params}: not a rig identify report with mean A_mu, B_mu, L_um ({exc})")
    else:
        names = [lubricant] if lubricant else list(TABLE2)
        for nm in names:
            if nm not in TABLE2:
                _fail(f"unknown lubricant {nm!r}; known: {', '.join(TABLE2)}")
            sets[nm] = {k: TABLE2[nm][k][0] for k in ("A_mu", "B_mu", "L_um")}
    analyses = {}
    table = Table(title=f"critical stiffness at V0 = {v0:g} µm/s (m = {mass:g} kg, kd = {kd:g} N s/µm, N = {N:g} N)")
    for c in ("set", "A_mu", "B_mu", "L (µm)", "k_cr eq.13 (kN/m, N)", "eq.13 x2 (kN/m, 2N)", "k_cr eq.8 (kN/m, 2N)",
              "eq.8 kd=0", "mass term", f"kp min (x{margin:g})"):
        table.add_column(c, justify="right")
    for nm, p in sets.items():
        a = S.analyse(S.StabilityInputs(p["A_mu"], p["B_mu"], p["L_um"], N, mass, kd, v0), margin)
        analyses[nm] = a
        table.add_row(nm, _fmt(p["A_mu"], 3), _fmt(p["B_mu"], 3), _fmt(p["L_um"], 3), _fmt(a["k_cr_eq13_kN_per_m"]),
                      _fmt(a["k_cr_eq13_fixture_kN_per_m"]), _fmt(a["k_cr_eq8_kN_per_m"]),
                      _fmt(a["k_cr_eq8_kd0_kN_per_m"]) if a["k_cr_eq8_kd0_kN_per_m"] else "inf",
                      _fmt(a["mass_term"], 2), _fmt(a["kp_min_N_per_um"] * 1e3 if a["kp_min_N_per_um"] else None)
                      + " kN/m")
    console.print(table)
    for nm, a in analyses.items():
        console.print(f"{nm}: {a['advice']}")
    console.print("[dim]eq. (8) uses the fixture's total friction 2 N mu (A = 2 N A_mu); eq. (13) and Table 2 use N "
                  "(one interface). With A + kv V0 = 0 eq. (8) has no finite k_cr.[/dim]")
    checks = []
    if simulate:
        for nm, p in sets.items():
            model = FrictionModel(params={"mu0": 0.12, **p})
            c = S.check_lubricant(nm, mass_kg=mass, kd_N_s_per_um=kd, normal_force_N=N, V0_um_s=v0, model=model)
            checks.append(c)
            console.print(f"{nm}: Fig. 1 simulation boundary {_fmt(c['k_sim_N_per_um'] * 1e3 if c['k_sim_N_per_um'] else None)}"
                          f" kN/m vs eq. (8) {_fmt(c['k_cr_eq8_N_per_um'] * 1e3)} kN/m (A_eff = {_fmt(c['A_eff_mu'], 3)}): "
                          f"{_fmt(100 * c['rel_diff'] if c['rel_diff'] is not None else None, 3)} %")
            if full_rig:
                if prof is None:
                    _fail("--full-rig needs the simulated rig (rig.sim) and a profile")
                if nm not in prof.lubricants:
                    console.print(f"{nm}: not a lubricant of the profile; full-rig check skipped")
                    continue
                f = S.full_rig_boundary(nm, profile=ppath, V0_um_s=v0)
                checks.append(f)
                console.print(f"{nm}: full simulated rig (PD, ki = 0) boundary "
                              f"{_fmt(f['k_sim_N_per_um'] * 1e3 if f['k_sim_N_per_um'] else None)} kN/m vs eq. (8) "
                              f"{_fmt(f['k_cr_eq8_N_per_um'] * 1e3)} kN/m; with the actuator's leakage damping "
                              f"(kv + {f['kv_leak_N_s_per_um']:g} N s/µm) {_fmt(f['k_cr_eq8_with_leak_N_per_um'] * 1e3)} kN/m")
                ks = f["k_sim_N_per_um"]
                if not ks or abs(ks / f["k_cr_eq8_with_leak_N_per_um"] - 1) > 0.05:
                    console.print(f"[yellow]{nm}: the full rig departs from eq. (8): with a small direct effect the "
                                  "D term on the noisy LVDT makes the interface velocity jitter (peaks beyond V0) "
                                  "and the linear analysis no longer applies; with kd = 0 the rig follows eq. (8) "
                                  "(docs/identification.md, section 5)[/yellow]")
    if json_out:
        doc = {"schema": "rig.stability/1", "V0_um_s": v0, "mass_kg": mass, "kd_N_s_per_um": kd,
               "normal_force_N": N, "analyses": analyses, "checks": checks}
        atomic_write_text(json_out, json.dumps(doc, indent=2, allow_nan=False, default=float) + "\n")
        console.print(f"wrote {json_out}")
    if plot:
        S.plot_map(checks, analyses, plot)
        console.print(f"wrote {plot}")


def reproduce_cmd(
    trials: int = typer.Option(8, "--trials", min=2, help="Simulated trials per lubricant (the paper: >= 8)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the parameter draws and the sensor noise."),
    lubricant: Optional[list[str]] = typer.Option(None, "--lubricant", help="Only these lubricants."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="Rig profile (default config/rigs/sim.yaml)."),
    whole: bool = typer.Option(False, "--whole/--no-whole", help="Also the whole-record fit of every trial."),
    engine: str = typer.Option("sim", "--engine", help="sim (full simulated rig) | synth (kinematic generator)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rig.reproduce/1 report here."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG (paper vs recovered vs truth)."),
):
    """Simulated trials in the paper's protocol, identified: our Table 2 beside the paper's."""
    from rich.progress import BarColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    from rig.analysis.reproduce import plot_reproduce, reproduce, write_json
    from rig.model.paper import TABLE2

    lubs = list(lubricant) if lubricant else list(TABLE2)
    for nm in lubs:
        if nm not in TABLE2:
            _fail(f"unknown lubricant {nm!r}; known: {', '.join(TABLE2)}")
    if engine not in ("sim", "synth"):
        _fail(f"--engine must be sim or synth (got {engine!r})")
    if profile is not None and not profile.exists():
        _fail(f"{profile}: no such profile")
    with Progress("[progress.description]{task.description}", BarColumn(), "{task.completed}/{task.total} trials",
                  TimeElapsedColumn(), TimeRemainingColumn(), console=console) as prog:
        task = prog.add_task("simulating and identifying", total=trials * len(lubs))
        rep = reproduce(trials, seed=seed, lubricants=lubs, profile=profile, whole_record=whole,
                        progress=lambda: prog.advance(task), engine=engine)
    table = Table(title=f"Table 2, paper vs {trials} simulated trials per lubricant (mean ± s.e. of the mean)")
    table.add_column("parameter")
    for lub in lubs:
        table.add_column(f"{lub}: paper", justify="right")
        table.add_column(f"{lub}: ours", justify="right")
        table.add_column(f"{lub}: trials' truth", justify="right")
    scale = {"A_mu": 1e3, "B_mu": 1e3, "L_um": 1.0, "k_cr_kN_per_m": 1.0}
    label = {"A_mu": "A_mu x 10^3", "B_mu": "B_mu x 10^3", "L_um": "L (µm)", "k_cr_kN_per_m": "k_cr (kN/m)"}
    for k in ("A_mu", "B_mu", "L_um", "k_cr_kN_per_m"):
        row = [label[k]]
        for lub in lubs:
            r = rep["lubricants"][lub]
            s = scale[k]

            def pm(m, e):
                return f"{m * s:.3g} ± {e * s:.2g}" if m is not None and e is not None else "-"

            ok = r["checks"].get(k, {}).get("ok", True)
            row += [pm(r["paper"][k]["mean"], r["paper"][k]["sem"]),
                    ("" if ok else "[red]") + pm(r["recovered"]["mean"][k], r["recovered"]["sem"][k]),
                    pm(r["truth"]["mean"][k], r["truth"]["sem"][k])]
        table.add_row(*row)
    if whole:
        for k in ("A_mu", "B_mu", "L_um"):
            row = [f"{label[k]} (whole-record)"]
            for lub in lubs:
                w = rep["lubricants"][lub]["whole_record"]
                row += ["", f"{w['mean'][k] * scale[k]:.3g} ± {w['sem'][k] * scale[k]:.2g}", ""]
            table.add_row(*row)
    console.print(table)
    for lub in lubs:
        c = rep["lubricants"][lub]["checks"]
        bad = [k for k, v in c.items() if not v["ok"]]
        console.print(f"{lub}: recovered - truth within the paper's s.e.: "
                      + ("all" if not bad else f"[red]not for {', '.join(bad)}[/red]")
                      + f" ({rep['lubricants'][lub]['engine']})")
    if json_out:
        write_json(rep, json_out)
        console.print(f"wrote {json_out}")
    if plot:
        plot_reproduce(rep, plot)
        console.print(f"wrote {plot}")
