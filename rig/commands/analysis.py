"""``rig identify``, ``rig stribeck``, ``rig stability``, ``rig reproduce``."""

from __future__ import annotations

import json
import math
from contextlib import nullcontext
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from rig.analysis.report import fmt as _fmt
from rig.commands.common import (EXIT_BAD_INPUT, JSON_HELP, Lubricant, check_output_path, emit_outputs, err_console,
                                 fail, json_to_stdout, progress_bar)

console = Console(width=None if Console().is_terminal else 140, highlight=False)

def _fail(msg: str, code: int = EXIT_BAD_INPUT):
    fail(msg, code)


class Velocity(str, Enum):
    paper = "paper"
    local_poly = "local_poly"


class WholeVelocity(str, Enum):
    segments = "segments"
    local_poly = "local_poly"
    paper = "paper"


class Direction(str, Enum):
    both = "both"
    up = "up"
    down = "down"


def _choices(name: str, values: tuple[str, ...]) -> type[Enum]:
    """A str Enum of an option's choices (typer lists them in --help)."""
    return Enum(name, {v: v for v in values}, type=str)


# identify's whole-record options (rig.analysis.identify: LAWS, DETRENDS)
Law = _choices("Law", ("slip", "aging", "both"))
Detrend = _choices("Detrend", ("none", "linear", "auto"))
Names = _choices("Names", ("spec", "rsf"))


#: --names rsf: the friction lab's names of the spec's (rig.model.spec.RSF_NAMES)
def _rsf_label(k: str, names: str) -> str:
    from rig.model.spec import RSF_NAMES

    if names != "rsf":
        return k
    return {**RSF_NAMES, "k_mu_per_um": "k_per_um", "L": "Dc"}.get(k, k)


class Engine(str, Enum):
    sim = "sim"
    synth = "synth"


def _con(json_out) -> Console:
    """Where the tables go: stdout, or stderr when ``--json -`` puts the JSON there."""
    return err_console if json_to_stdout(json_out) else console


def _outputs(**paths) -> None:
    """Output paths checked before the work (a directory, a wrong suffix: exit 2 at once)."""
    suffix = {"plot": (".png",), "json": ()}  # the plots are PNG (rig.analysis.plots.save)
    for name, p in paths.items():
        if p is not None:
            check_output_path(p, f"--{name}", suffix.get(name, ()))


def _load(paths: list[Path]):
    from rig.analysis.identify import MIN_RECORD_SAMPLES
    from rig.data import DataFormatError
    from rig.log import load_trial

    trials = []
    for p in paths:
        try:
            trials.append(load_trial(p))
        except DataFormatError as exc:
            _fail(str(exc))
        if len(trials[-1]) < MIN_RECORD_SAMPLES:
            _fail(f"{p}: {len(trials[-1])} sample(s): too few samples to analyse (at least {MIN_RECORD_SAMPLES})")
    return trials


def _named(msg: str, data) -> str:
    """An analysis error with the file(s) named."""
    return msg if any(str(p) in msg for p in data) else f"{', '.join(map(str, data))}: {msg}"


def identify_cmd(
    data: list[Path] = typer.Argument(..., help="One or more trial files (.csv or .mcap); a directory or a "
                                                "glob runs a batch into the catalogue."),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.identify/1)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG (friction after each step, fits, windows)."),
    events: bool = typer.Option(True, "--events/--no-events", help="Use the log's step events when present."),
    velocity: Velocity = typer.Option(Velocity.local_poly, "--velocity", help="Velocity estimator for plots."),
    whole: bool = typer.Option(True, "--whole/--no-whole", help="Also fit the model to the whole record."),
    whole_velocity: WholeVelocity = typer.Option(WholeVelocity.segments, "--whole-velocity",
                                                 help="Velocity for the whole-record fit."),
    stiffness: Optional[bool] = typer.Option(None, "--stiffness/--no-stiffness",
                                             help="Whole-record fit with a machine stiffness (default: when the "
                                                  "file says its position is the load point)."),
    direction: Direction = typer.Option(Direction.both, "--direction", help="Steps to use."),
    min_ratio: float = typer.Option(1.25, "--min-ratio", help="Smallest velocity ratio counted as a step."),
    law: Law = typer.Option(Law.slip, "--law", help="State law of the whole-record fit: slip (Ruina), aging "
                                                    "(Dieterich) or both side by side with the law the record "
                                                    "prefers."),
    detrend: Detrend = typer.Option(Detrend.none, "--detrend", help="Trend of mu with slip in the whole-record "
                                                                    "fit: none, linear (fitted) or auto (from the "
                                                                    "steady-state windows)."),
    uncertainty: str = typer.Option("jacobian", "--uncertainty", help="Whole-record errors: jacobian, "
                                                                      "bootstrap:N (block bootstrap in time) or "
                                                                      "mcmc:N (emcee)."),
    names: Names = typer.Option(Names.spec, "--names", help="Table names: spec (A_mu, B_mu, L_um) or rsf "
                                                            "(a, b, Dc_um, k_per_um)."),
    jobs: Optional[int] = typer.Option(None, "--jobs", help="Batch: N worker processes (default: all cores)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Batch: an existing Dask cluster, "
                                                                      "tcp://HOST:PORT."),
    db: Optional[Path] = typer.Option(None, "--db", help="Batch: the catalogue (default DIR/catalog.duckdb)."),
):
    """Identify A, B, L by the paper's velocity-step method (eqs. 10-14) and a whole-record fit.

    With a directory or a glob (or --jobs/--scheduler/--db), each file is identified on its
    own, in parallel, and the results go into the catalogue (docs/catalog.md)."""
    con = _con(json_out)
    if not min_ratio > 1:
        _fail(f"--min-ratio must be more than 1 (got {min_ratio:g})")
    _outputs(json=json_out, plot=plot)
    options = {"use_events": events, "velocity_method": velocity.value, "whole_record": whole,
               "whole_velocity": whole_velocity.value, "stiffness": stiffness, "directions": direction.value,
               "min_ratio": min_ratio, "law": law.value, "detrend": detrend.value, "uncertainty": uncertainty}
    _check_uncertainty(uncertainty)
    from rig.commands.catalog import identify_summary, is_batch, run_batch

    if is_batch([str(p) for p in data], jobs, scheduler, db):
        if json_out or plot:
            _fail("--json and --plot are for single runs; a batch writes its results into the catalogue")
        run_batch("identify", [str(p) for p in data], options, jobs=jobs, scheduler=scheduler, db=db,
                  summarize=identify_summary)
        return
    trials = _load(data)
    idn = _identify(trials, data, json_out, options)
    if not idn.steps:
        _fail(f"{', '.join(map(str, data))}: no velocity steps found (ratio >= {min_ratio:g})")
    idn.warnings += _calibration_warnings(trials, idn)  # issue 21
    _print_identification(con, idn, names.value, [Path(p).name for p in data])
    from rig.analysis.plots import plot_identification

    emit_outputs(con, json_out, idn.report(), plot, lambda path: plot_identification(idn, path))


def _check_uncertainty(uncertainty: str) -> None:
    """--uncertainty: one of the methods, and MCMC only with emcee installed."""
    from rig.fitting.stats import parse_uncertainty

    try:
        method, _ = parse_uncertainty(uncertainty)
    except ValueError as exc:
        _fail(str(exc))
    if method == "mcmc":
        try:
            import emcee  # noqa: F401
        except ImportError:
            _fail(f"--uncertainty {uncertainty}: needs emcee, an optional extra: pip install 'rig[mcmc]'")


COMPILING = ("compiling the identification kernels (first run after an install or a change, once; "
             "`rig warmup` does it ahead)...")


def _identify(trials, data: list[Path], json_out, options: dict):
    """identify_trials with what a person at the terminal sees meanwhile: a line while the kernels
    compile (the first run), a bar over the bootstrap refits or MCMC steps."""
    from rig.analysis.identify import identify_trials
    from rig.commands.warmup import IDENTIFY_KERNELS, cold_kernels
    from rig.fitting.stats import parse_uncertainty

    unc = options["uncertainty"]
    unc_method, unc_n = parse_uncertainty(unc)
    cold = cold_kernels(IDENTIFY_KERNELS)  # the first identify compiles for seconds: say so
    n_fits = len(trials) * (2 if options["law"] == "both" else 1)
    with_bar = bool(unc_n and options["whole_record"])
    if cold and with_bar:  # one live display at a time: the bar, after a line that says it compiles first
        err_console.print(COMPILING, markup=False)
    if with_bar:
        shown = progress_bar(json_out, f"{unc_method} ({unc})", total=n_fits * unc_n,
                             unit="refits" if unc_method == "bootstrap" else "steps")
    else:
        shown = err_console.status(COMPILING) if cold else nullcontext()
    with shown as bar:
        try:
            return identify_trials(trials, names=[str(p) for p in data], progress=getattr(bar, "advance", None),
                                   **options)
        except ValueError as exc:
            _fail(_named(str(exc), data))


def _print_identification(con, idn, names: str, files: list[str]) -> None:
    """The tables and lines of identify (an :class:`~rig.analysis.identify.Identification`): the steps,
    their mean, each file's whole-record fit (or both laws), the rejected steps, warnings and notes."""
    from rig.model.checks import MARK

    con.print(_steps_table(idn, names))
    _print_mean(con, idn, names)
    many = len(files) > 1
    if idn.law == "both":
        for i, (fits, c) in enumerate(zip(idn.laws, idn.comparisons)):
            _print_laws(con, fits, c, names, files[i] if many else None)
    elif idn.law is not None:
        for i, w in enumerate(idn.fits):
            label = files[i] if many else None
            where = "whole-record fit" + (f" (trial {i})" if many else "")  # the JSON's `where`
            _print_whole(con, w, names, _flagged(idn.warnings, where), MARK, label)
    for r in idn.rejected:
        con.print(f"rejected step at t = {_fmt(r.step.t_s, 6)} s: {r.reason}", markup=False, highlight=False)
    for w in idn.warnings:
        con.print(f"[yellow]warning {MARK}:[/yellow] {_named_trial(w['where'], files)}: {w['message']}",
                  highlight=False)
    for note in idn.notes:
        con.print(f"[yellow]note:[/yellow] {note}", highlight=False)


def _named_trial(where: str, files: list[str]) -> str:
    """A warning's place with the file's name for the JSON's '(trial i)' when several files are identified."""
    import re

    if len(files) < 2:
        return where
    return re.sub(r"\(trial (\d+)\)", lambda m: f"({files[int(m.group(1))]})" if int(m.group(1)) < len(files)
                  else m.group(0), where)


def _of(label: str | None) -> str:
    """' of FILE' when several files are identified at once (their fits are told apart by name)."""
    return f" of {label}" if label else ""


def _flagged(warns: list[dict], where: str) -> set[str]:
    from rig.model.checks import flagged

    return flagged(warns, where)


def _steps_table(idn, names: str) -> Table:
    """One row per step (eqs. 10-12), a flagged value marked."""
    from rig.model.checks import MARK

    table = Table(title="velocity steps (eqs. 10-12)")
    for c in ("trial", "t (s)", "v1 (µm/s)", "v2 (µm/s)", _rsf_label("A_mu", names), _rsf_label("B_mu", names),
              f"{_rsf_label('L', names)} (µm)", "r2", "window (µm)", "t_r (s)"):
        table.add_column(c, justify="right")
    table.add_column("accepted", justify="left", overflow="fold")
    n_trials = len(idn.trials)
    for r in idn.steps:
        fl = _flagged(idn.warnings, r.where(n_trials))

        def cell(k, nd, r=r, fl=fl):
            return _fmt(getattr(r, k), nd) + (f" [yellow]{MARK}[/yellow]" if k in fl else "")

        table.add_row(str(r.trial), _fmt(r.step.t_s, 6), _fmt(r.step.v1_um_s), _fmt(r.step.v2_um_s),
                      cell("A_mu", 3), cell("B_mu", 3), cell("L_um", 3), _fmt(r.r2, 2), _fmt(r.window_um),
                      _fmt(r.t_r_s, 3), f"[red]no: {r.reason}[/red]" if not r.ok else "yes")
    return table


def _print_mean(con, idn, names: str) -> None:
    """Mean ± s.e. over steps (or trials), eq. (13)'s k_cr and eq. (14)'s t_r."""
    from rig.model.checks import MARK

    m, e = idn.mean, idn.sem
    fl = _flagged(idn.warnings, f"mean over {idn.sem_over}")

    def mk(k):
        return f" [yellow]{MARK}[/yellow]" if k in fl else ""

    n_rej = len(idn.rejected)
    con.print(f"mean ± s.e. over {idn.sem_over} (n={idn.n_steps if idn.sem_over == 'steps' else len(idn.trials)}"
              + (f"; {n_rej} step(s) rejected" if n_rej else "") + "): "
              f"{_rsf_label('A_mu', names)} = {_fmt(m['A_mu'], 3)} ± {_fmt(e['A_mu'], 2)}{mk('A_mu')}, "
              f"{_rsf_label('B_mu', names)} = {_fmt(m['B_mu'], 3)} ± {_fmt(e['B_mu'], 2)}{mk('B_mu')}, "
              f"{_rsf_label('L', names)} = {_fmt(m['L_um'], 3)} ± {_fmt(e['L_um'], 2)} µm{mk('L_um')}, "
              f"k_cr (eq. 13) = {_fmt(m['k_cr_kN_per_m'], 3)} ± {_fmt(e['k_cr_kN_per_m'], 2)} kN/m{mk('k_cr_kN_per_m')}, "
              f"t_r (eq. 14) = {_fmt(m['t_r_s'], 3)} s")


def _calibration_warnings(trials, idn) -> list[dict]:
    """Forces outside a channel's verified range; step effects (eqs. 10-12, in N of friction at the smallest
    velocity ratio: A ln(v2/v1) 2N, B ln(v2/v1) 2N, (A - B) ln(v2/v1) 2N) below its stated uncertainty."""
    from rig.data import calibration_warnings

    A, B = (v if math.isfinite(v) else None for v in (idn.mean["A_mu"], idn.mean["B_mu"]))
    ratios = [r.step.v2_um_s / r.step.v1_um_s for r in idn.steps if r.step.v1_um_s]
    out = []
    for tr in trials:
        try:
            lnr, n2 = math.log(max(min(ratios), 1.0 / min(ratios))), 2.0 * tr.normal_force_N
        except (ValueError, TypeError):
            continue
        effects = {"the direct effect A ln(v2/v1) 2N": A * lnr * n2 if A is not None else None,
                   "the evolution effect B ln(v2/v1) 2N": B * lnr * n2 if B is not None else None,
                   "the steady-state change (A - B) ln(v2/v1) 2N": (A - B) * lnr * n2
                   if A is not None and B is not None else None}
        out += calibration_warnings(tr, effects)
    return out


_SPEC_KEYS = ("mu0", "A_mu", "B_mu", "L_um", "k_mu_per_um", "stiffness_kN_per_m", "rate_mu_per_mm")
_RSF_KEYS = ("mu0", "a", "b", "Dc_um", "a_minus_b", "k_per_um", "stiffness_kN_per_m", "rate_mu_per_mm")


def _print_whole(con, fit, names: str, fl=(), mark: str = "", label: str | None = None) -> None:
    """One whole-record fit (a :class:`~rig.analysis.identify.WholeRecordFit`, shown as its report, the
    uncertainty code's): each parameter with its s.e. and its 68 % interval where that is asymmetric (L),
    the correlation of A, B, L, the trend and the information criterion."""
    keys = _RSF_KEYS if names == "rsf" else _SPEC_KEYS
    w = fit.report()
    if not fit.params:
        con.print(f"whole-record fit{_of(label)} failed: {w.get('reason')}", markup=False, highlight=False)
        return
    p, sd, iv = w["params"], w.get("params_sd", w.get("err_corr", {})), w.get("intervals", {})
    parts = []
    for k in keys:
        if p.get(k) is None:
            continue
        txt = f"{k} = {_fmt(p[k], 4)} ± {_fmt(sd.get(k), 2)}"
        lo_hi = iv.get(k)
        if lo_hi and None not in lo_hi and sd.get(k):
            asym = abs((lo_hi[1] - p[k]) - (p[k] - lo_hi[0])) > 0.05 * sd[k]
            if asym:
                txt += f" [{_fmt(lo_hi[0], 4)}, {_fmt(lo_hi[1], 4)}]"
        src = k if names != "rsf" else {"a": "A_mu", "b": "B_mu", "Dc_um": "L_um"}.get(k, k)
        parts.append(txt + (f" [yellow]{mark}[/yellow]" if src in fl else ""))
    unc = w.get("uncertainty", {}).get("method", "jacobian") + " errors"
    if w.get("uncertainty", {}).get("jackknife"):
        unc += f" at least the leave-one-run-out jackknife's ({w['uncertainty']['jackknife']['runs']} runs)"
    rise = w.get("uncertainty", {}).get("velocity_rise", {}).get("raised")
    if rise:
        unc += f"; {', '.join(rise)} at least the change with the steps' estimated velocity"
    con.print(f"whole-record fit{_of(label)} ({w['model']}, velocity {w['velocity']}, {unc}, n_eff {_fmt(w.get('n_eff'), 4)} "
              f"of {w.get('n_points')}): {', '.join(parts)}; k_cr (eq. 13) = {_fmt(w.get('k_cr_kN_per_m'), 3)} kN/m; "
              f"rms {_fmt(w['rms_N'], 3)} N", highlight=False)
    c = w.get("correlation")
    if c:
        lab = {k: _rsf_label(k, names) for k in c["names"]}
        pairs = [(a, b) for a, b in (("A_mu", "B_mu"), ("A_mu", "L_um"), ("B_mu", "L_um")) if a in c["names"] and b in c["names"]]
        txt = ", ".join(f"{lab[a]}-{lab[b]} {c['matrix'][c['names'].index(a)][c['names'].index(b)]:+.2f}" for a, b in pairs)
        con.print(f"  correlation: {txt}", highlight=False)
    d = w.get("detrend", {})
    if d.get("method", "none") != "none":
        con.print(f"  trend ({d['method']}): {_fmt(d.get('rate_mu_per_mm'), 3)} ± {_fmt(d.get('rate_sd_mu_per_mm'), 2)} "
                  f"mu per mm of slip" + (f"; {d['note']}" if d.get("note") else ""), highlight=False)
    if w.get("stiffness_source") == "metadata":
        con.print("  stiffness held at the file's machine_stiffness_kN_per_m", highlight=False)


def _print_laws(con, fits: dict, c, names: str, label: str | None) -> None:
    """--law both: the slip- and aging-law fits side by side and the law the record prefers (``c``, a
    :class:`~rig.analysis.identify.LawComparison`; ``label``: the file's name when several are identified)."""
    for lw in ("slip", "aging"):
        con.print(f"[bold]{lw} law[/bold]" + (f" ({label})" if label else "") + ":", highlight=False)
        _print_whole(con, fits[lw], names)
    if c.reason:
        con.print(f"preferred law: {c.preferred_law} ({c.reason})", highlight=False)
        return
    con.print(f"preferred law: {c.preferred_law} (BIC on n_eff {_fmt(c.n_eff, 4)}: slip "
              f"{_fmt(c.bic.get('slip'), 6)}, aging {_fmt(c.bic.get('aging'), 6)}; difference {_fmt(c.delta_bic, 3)}, "
              "6 or more decides)", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("identify")(identify_cmd)
    for name in ("stribeck", "stability", "reproduce"):
        mod_cmd = _optional(name)
        if mod_cmd is not None:
            app.command(name)(mod_cmd)


def _optional(name: str):
    return globals().get(f"{name}_cmd")


def stribeck_cmd(
    data: list[Path] = typer.Argument(..., help="Stepped-velocity pass(es), .csv or .mcap.", show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.stribeck/1)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG like Figs. 6 and 7."),
    events: bool = typer.Option(True, "--events/--no-events", help="Use the log's level events when present."),
    window_um: float = typer.Option(50.0, "--window-um", help="Average over the last this many µm of each level."),
):
    """Steady-state friction per velocity level, up and down branches, and A - B by eq. (7)."""
    from rig.analysis.stribeck import plot_stribeck, stribeck_result

    con = _con(json_out)
    if not window_um > 0:
        _fail(f"--window-um must be positive (got {window_um:g})")
    _outputs(json=json_out, plot=plot)

    trials = _load(data)
    try:
        res = stribeck_result(trials, use_events=events, window_um=window_um, names=[str(p) for p in data])
    except ValueError as exc:
        _fail(_named(str(exc), data))
    if not res.levels:
        _fail(f"{', '.join(map(str, data))}: no velocity levels found")
    table = Table(title=f"steady-state friction (last {window_um:g} µm of each level)")
    for c in ("branch", "v (µm/s)", "mu", "sd over trials", "trials"):
        table.add_column(c, justify="right")
    for d in ("up", "down"):
        for b in res.branches[d]:
            table.add_row(d, _fmt(b["v_um_s"]), _fmt(b["mu"], 5), _fmt(b["mu_sd"], 2), str(b["n_trials"]))
    con.print(table)
    src = " and ".join({"events": "the log's level events", "data": "velocity steps detected in the data"}[x]
                       for x in res.level_source)
    con.print(f"{len(res.levels)} level(s) found (from {src}, at 25 Hz)"
              + (f"; {len(res.rejected)} not counted:" if res.rejected else ""), highlight=False)
    for r in res.rejected:
        con.print(f"  level at {_fmt(r['v_um_s'])} µm/s (t = {_fmt(r['t_s'], 6)} s): {r['reason']}", highlight=False,
                  markup=False)
    for f, label in ((res.fit, "all levels"), (res.fit_up, "up branch"), (res.fit_down, "down branch")):
        con.print(f"eq. (7), {label}: A - B = {_fmt(f.A_minus_B, 4)} ± {_fmt(f.A_minus_B_err, 2)}, "
                  f"mu0 = {_fmt(f.mu0, 5)} (n={f.n})")
    rep = res.report()
    emit_outputs(con, json_out, rep, plot, lambda path: plot_stribeck(rep, path))


def stability_cmd(
    lubricant: Optional[Lubricant] = typer.Option(None, "--lubricant", help="Table 2's values of this lubricant "
                                                                           "(default: all three)."),
    params: Optional[Path] = typer.Option(None, "--params", help="A rig identify JSON report (its mean A, B, L)."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="Rig profile (mass, gains, actuator, sensors); "
                                                                   "default config/rigs/sim.yaml."),
    margin: float = typer.Option(2.0, "--margin", help="Advice: kp >= margin x k_cr (the rig's loop)."),
    v0: float = typer.Option(1.0, "--v0", help="Sliding velocity V0 (µm/s)."),
    simulate: bool = typer.Option(False, "--simulate", help="Check by a kp scan on the full simulated rig "
                                                            "(criterion: stuck fraction, velocity spread)."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="With --simulate: write the stability map PNG."),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.stability/2)"),
    jobs: Optional[int] = typer.Option(None, "--jobs", help="With --simulate: checks on N worker processes "
                                                            "(Dask; default: all cores; 1: serially)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="With --simulate: an existing Dask "
                                                                      "cluster, tcp://HOST:PORT."),
):
    """Critical stiffness of the moving test piece: the paper's eqs. (8)/(13), the rig's PID
    loop (1 kHz, zero-order hold), PD and PID, and optionally the simulated boundary."""
    from rig.analysis import stability as S

    con = _con(json_out)
    lubricant = lubricant.value if lubricant is not None else None
    _outputs(json=json_out, plot=plot)
    if lubricant and params:
        _fail("give --lubricant or --params, not both")
    if not (margin > 0 and math.isfinite(margin)):
        _fail(f"--margin must be a positive number (got {margin:g})")
    if not (v0 > 0 and math.isfinite(v0)):
        _fail(f"--v0 must be a positive number of µm/s (got {v0:g})")
    if plot and not simulate:
        _fail("--plot needs --simulate (the map shows the scanned runs)")
    if simulate and jobs is not None and jobs < 1:
        _fail(f"--jobs must be at least 1 (got {jobs})")
    prof, ppath = _stability_profile(profile)
    mass, kd, N = ((prof.actuator.moving_mass_kg, prof.controller.kd_N_s_per_um, prof.normal.nominal_force_N)
                   if prof is not None else (S.DEFAULT_MASS_KG, S.DEFAULT_KD_N_S_PER_UM, 100.0))
    sets, N = _stability_sets(lubricant, params, N)
    ki = prof.controller.ki_N_per_um_s if prof is not None else 0.0
    res = S.StabilityReport(v0, mass, kd, ki, N, {}, [])
    for nm, p in sets.items():
        res.analyses[nm] = S.analyse_set(nm, p, S.StabilityInputs(p["A_mu"], p["B_mu"], p["L_um"], N, mass, kd, v0),
                                         margin, prof, from_table2=not params)
    _print_stability(con, res, margin)
    if simulate:
        if prof is None:
            _fail("--simulate needs the simulated rig (rig.sim) and a profile")
        from rig.catalog.batch import mapper

        with progress_bar(json_out, "kp scan", unit="simulated runs") as bar, \
                mapper(jobs, scheduler, progress=bar.advance) as map_fn:
            res.checks = S.simulated_checks(res.analyses, prof, ppath, v0, map_fn, con.print, bar,
                                            from_table2=not params)
        con.print(f"[dim]criterion: {S.STUCK_FRACTION_MAX:.0%} stuck / spread {S.SPREAD_MAX:g} V0 "
                  f"({res.checks[0]['criterion'] if res.checks else ''})[/dim]")
    emit_outputs(con, json_out, res.report(), plot, lambda path: S.plot_map(res.checks, path))


def _stability_profile(profile: Path | None):
    """The rig profile (the default one unless --profile) and its path; (None, path) without rig.config."""
    try:
        from rig.config.profile import default_profile_path, load_profile
    except ImportError:
        return None, None
    ppath = profile or default_profile_path()
    if profile is not None and not Path(profile).exists():
        _fail(f"{profile}: no such profile")
    try:
        return load_profile(ppath), ppath
    except Exception as exc:  # noqa: BLE001 - ProfileError names file/field/line
        _fail(str(exc))


def _stability_sets(lubricant: str | None, params: Path | None, N: float) -> tuple[dict, float]:
    """The parameter sets to analyse: an identify report's mean (--params; its normal force), or Table 2's
    lubricants (one with --lubricant)."""
    from rig.analysis.stability import params_from_report
    from rig.model.paper import TABLE2

    if params:
        if not params.is_file():
            _fail(f"{params}: no such file" if not params.exists() else f"{params}: not a file")
        try:
            text = params.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            _fail(f"{params}: cannot read: {getattr(exc, 'strerror', None) or exc}")
        try:
            doc = json.loads(text)
        except ValueError as exc:
            _fail(f"{params}, line {getattr(exc, 'lineno', '?')}: not JSON ({getattr(exc, 'msg', exc)}); expected a "
                  "`rig identify --json` report")
        try:
            p, N = params_from_report(doc, N)
        except ValueError as exc:
            _fail(f"{params}: {exc}")
        return {params.stem: p}, N
    names = [lubricant] if lubricant else list(TABLE2)
    for nm in names:
        if nm not in TABLE2:
            _fail(f"unknown lubricant {nm!r}; known: {', '.join(TABLE2)}")
    return {nm: {k: TABLE2[nm][k][0] for k in ("A_mu", "B_mu", "L_um")} for nm in names}, N


def _print_stability(con, res, margin: float) -> None:
    """The k_cr table of every set, its statement and advice."""
    table = Table(title=f"critical stiffness at V0 = {res.V0_um_s:g} µm/s (m = {res.mass_kg:g} kg, kd = "
                        f"{res.kd_N_s_per_um:g} N s/µm, ki = {res.ki_N_per_um_s:g} N/(µm s), N = "
                        f"{res.normal_force_N:g} N per rider)")
    for c in ("set", "eq.13 per rider (N; Table 2)", "moving piece eq.13 (2N)", "eq.8 (2N, kd, m)",
              "rig loop PD", "rig loop PID", f"kp min (x{margin:g})"):
        table.add_column(c, justify="right")

    def k(x):
        return "none (stable at every kp)" if x == 0 else (_fmt(x) if x is not None else "-")

    for nm, a in res.analyses.items():
        table.add_row(nm, _fmt(a["k_cr_eq13_kN_per_m"]), _fmt(a["k_cr_eq13_fixture_kN_per_m"]),
                      _fmt(a["k_cr_eq8_kN_per_m"]) if a["k_cr_eq8_kN_per_m"] else "inf",
                      k(a.get("k_cr_loop_PD_kN_per_m")), k(a.get("k_cr_loop_PID_kN_per_m")),
                      _fmt(a["kp_min_N_per_um"] * 1e3 if a["kp_min_N_per_um"] else None) + " kN/m")
    con.print(table)
    for nm, a in res.analyses.items():
        con.print(f"{nm}: {a['statement']}")
        con.print(f"{nm}: {a['advice']}")
    con.print("[dim]All stiffnesses in kN/m. The stiffness the controller must provide is the moving test piece's "
              "(2 N); Table 2 prints (B - A) N / L per rider interface, half of it. The rig loop columns: "
              "eq. (8)'s system with the rig's discrete PID (1 kHz, zero-order hold, backward-difference D), "
              "actuator, compliance and LVDT filter (rig.analysis.stability.k_cr_loop).[/dim]")


def reproduce_cmd(
    trials: int = typer.Option(8, "--trials", min=2, help="Simulated trials per lubricant (the paper: >= 8)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the parameter draws and the sensor noise."),
    lubricant: Optional[list[Lubricant]] = typer.Option(None, "--lubricant", help="Only this lubricant (repeat "
                                                                                  "for several; default all)."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="Rig profile (default config/rigs/sim.yaml)."),
    whole: bool = typer.Option(False, "--whole/--no-whole", help="Also the whole-record fit of every trial."),
    engine: Engine = typer.Option(Engine.sim, "--engine", help="sim: the full simulated rig; synth: the "
                                                                "kinematic generator."),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.reproduce/1)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG (paper vs recovered vs truth)."),
    jobs: Optional[int] = typer.Option(None, "--jobs", help="Trials on N processes (this one and N-1 workers; "
                                                            "default: all cores; 1: serially in this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run the trials on an existing Dask "
                                                                      "cluster, tcp://HOST:PORT."),
):
    """Simulated trials in the paper's protocol, identified: our Table 2 beside the paper's."""
    from rig.analysis.plots import plot_reproduce
    from rig.analysis.reproduce import reproduce_result
    from rig.model.paper import TABLE2

    con = _con(json_out)
    lubs = [lb.value for lb in lubricant] if lubricant else list(TABLE2)
    engine = engine.value
    _outputs(json=json_out, plot=plot)
    for nm in lubs:
        if nm not in TABLE2:
            _fail(f"unknown lubricant {nm!r}; known: {', '.join(TABLE2)}")
    if profile is not None:
        from rig.config.profile import ProfileError, load_profile

        try:
            load_profile(profile)
        except ProfileError as exc:
            _fail(str(exc))
    from rig.catalog.batch import BatchError, mapper

    if jobs is not None and jobs < 1:
        _fail(f"--jobs must be at least 1 (got {jobs})")
    with progress_bar(json_out, "simulating and identifying", total=trials * len(lubs), unit="trials") as bar:
        try:
            with mapper(jobs, scheduler, progress=bar.advance) as map_fn:
                res = reproduce_result(trials, seed=seed, lubricants=lubs, profile=profile, whole_record=whole,
                                       engine=engine, map_fn=map_fn)
        except BatchError as exc:
            _fail(str(exc), 1)
    con.print(_reproduce_table(res, trials))
    _print_reproduce(con, res)
    res.warnings = _reproduce_warnings(res)
    for w in res.warnings:
        con.print(f"[yellow]warning (!):[/yellow] {w['where']}: {w['message']}", highlight=False)
    rep = res.report()
    emit_outputs(con, json_out, rep, plot, lambda path: plot_reproduce(rep, path, res.warnings))


_REPRO_SCALE = {"A_mu": 1e3, "B_mu": 1e3, "L_um": 1.0, "k_cr_kN_per_m": 1.0}
_REPRO_LABEL = {"A_mu": "A_mu x 10^3", "B_mu": "B_mu x 10^3", "L_um": "L (µm)", "k_cr_kN_per_m": "k_cr (kN/m)"}


def _reproduce_table(res, trials: int) -> Table:
    """Table 2 beside ours and the trials' truth (mean ± s.e. of the mean), the whole-record fit's too."""
    table = Table(title=f"Table 2, paper vs {trials} simulated trials per lubricant (mean ± s.e. of the mean)")
    table.add_column("parameter")
    for lub in res.lubricants:
        table.add_column(f"{lub}: paper", justify="right")
        table.add_column(f"{lub}: ours", justify="right")
        table.add_column(f"{lub}: trials' truth", justify="right")
    for k, s in _REPRO_SCALE.items():

        def pm(m, e):
            return f"{m * s:.3g} ± {e * s:.2g}" if m is not None and e is not None else "-"

        row = [_REPRO_LABEL[k]]
        for r in res.lubricants.values():
            ok = r.checks.get(k, {}).get("ok", True)
            row += [pm(r.paper[k]["mean"], r.paper[k]["sem"]),
                    ("" if ok else "[red]") + pm(r.recovered.mean[k], r.recovered.sem[k]),
                    pm(r.truth.mean[k], r.truth.sem[k])]
        table.add_row(*row)
    if all(r.whole_record is not None for r in res.lubricants.values()):
        for k in ("A_mu", "B_mu", "L_um"):
            row = [f"{_REPRO_LABEL[k]} (whole-record)"]
            for r in res.lubricants.values():
                w = r.whole_record
                row += ["", f"{w.mean[k] * _REPRO_SCALE[k]:.3g} ± {w.sem[k] * _REPRO_SCALE[k]:.2g}", ""]
            table.add_row(*row)
    return table


def _print_reproduce(con, res) -> None:
    """Per lubricant: the identification's bias, eq. (13) on the recovered means, the check against the truth."""
    from rig.analysis.stability import per_interface_statement

    for lub, r in res.lubricants.items():
        b = r.bias
        con.print(f"{lub}: identification bias, recovered/true - 1 (mean ± s.e. over trials): "
                  + ", ".join(f"{k} {_pct(b[k]['recovered_vs_true_rel']):+.1f} ± "
                              f"{_pct(b[k]['recovered_vs_true_rel_sem']):.1f} %" for k in b)
                  + "; recovered mean vs Table 2 (in the paper's s.e.): "
                  + ", ".join(f"{k} {b[k]['vs_paper_z']:+.2f}" for k in b))
    for lub, r in res.lubricants.items():
        m = r.recovered.mean
        con.print(f"{lub}: the k_cr column is {per_interface_statement(m['A_mu'], m['B_mu'], m['L_um'])}")
    for lub, r in res.lubricants.items():
        bad = [k for k, v in r.checks.items() if not v["ok"]]
        con.print(f"{lub}: recovered - truth within the paper's s.e.: "
                  + ("all" if not bad else f"[red]not for {', '.join(bad)}[/red]") + f" ({r.engine})")


def _pct(x) -> float:
    """A fraction in %, 0 when there is none (fewer than two trials)."""
    return 100 * x if x is not None and math.isfinite(x) else 0.0


def _reproduce_warnings(res) -> list[dict]:
    """Values that hit a bound or are not physical (rig.model.checks): each lubricant's recovered mean,
    then each trial's recovered values (a trial's A below zero is no direct effect: it is said)."""
    from rig.model.checks import check_params

    warns = []
    for lub, r in res.lubricants.items():
        warns += check_params(r.recovered.mean, r.recovered.sem, where=f"{lub}: recovered mean")
    for lub, r in res.lubricants.items():
        for i, t in enumerate(r.trials):
            warns += [w for w in check_params(t["recovered"], where=f"{lub}: trial {i} recovered")
                      if w["kind"] == "not_physical"]
    return warns
