"""``rig identify``, ``rig stribeck``, ``rig stability``, ``rig reproduce``."""

from __future__ import annotations

import json
import math
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from rig.commands.common import (EXIT_BAD_INPUT, JSON_HELP, Lubricant, check_output_path, err_console, fail,
                                 json_to_stdout, progress_bar, write_json)

console = Console(width=None if Console().is_terminal else 140, highlight=False)

#: fewer samples than this are no record to analyse (a 1-row file divided by zero in identify)
MIN_SAMPLES = 3


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
    from rig.data import DataFormatError
    from rig.log import load_trial

    trials = []
    for p in paths:
        try:
            trials.append(load_trial(p))
        except DataFormatError as exc:
            _fail(str(exc))
        if len(trials[-1]) < MIN_SAMPLES:
            _fail(f"{p}: {len(trials[-1])} sample(s): too few samples to analyse (at least {MIN_SAMPLES})")
    return trials


def _named(msg: str, data) -> str:
    """An analysis error with the file(s) named."""
    return msg if any(str(p) in msg for p in data) else f"{', '.join(map(str, data))}: {msg}"


def _fmt(v, nd=4):
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.{nd}g}"
    return str(v)


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
    from rig.analysis.identify import identify_trials

    con = _con(json_out)
    if not min_ratio > 1:
        _fail(f"--min-ratio must be more than 1 (got {min_ratio:g})")
    _outputs(json=json_out, plot=plot)
    velocity, whole_velocity, direction = velocity.value, whole_velocity.value, direction.value
    law, detrend, names = law.value, detrend.value, names.value
    from rig.fitting.stats import parse_uncertainty

    try:
        unc_method, unc_n = parse_uncertainty(uncertainty)
    except ValueError as exc:
        _fail(str(exc))
    if unc_method == "mcmc":
        try:
            import emcee  # noqa: F401
        except ImportError:
            _fail(f"--uncertainty {uncertainty}: needs emcee, an optional extra: pip install 'rig[mcmc]'")
    from rig.commands.catalog import identify_summary, is_batch, run_batch

    if is_batch([str(p) for p in data], jobs, scheduler, db):
        if json_out or plot:
            _fail("--json and --plot are for single runs; a batch writes its results into the catalogue")
        run_batch("identify", [str(p) for p in data],
                  {"use_events": events, "velocity_method": velocity, "whole_record": whole,
                   "whole_velocity": whole_velocity, "stiffness": stiffness, "directions": direction,
                   "min_ratio": min_ratio, "law": law, "detrend": detrend, "uncertainty": uncertainty},
                  jobs=jobs, scheduler=scheduler, db=db, summarize=identify_summary)
        return
    trials = _load(data)

    from rig.commands.warmup import IDENTIFY_KERNELS, cold_kernels
    cold = cold_kernels(IDENTIFY_KERNELS)  # the first identify compiles for seconds: say so
    compiling = ("compiling the identification kernels (first run after an install or a change, once; "
                 "`rig warmup` does it ahead)...")
    n_fits = len(trials) * (2 if law == "both" else 1)
    with_bar = bool(unc_n and whole)
    if cold and with_bar:  # one live display at a time: the bar, after a line that says it compiles first
        err_console.print(compiling, markup=False)
    with progress_bar(json_out, f"{unc_method} ({uncertainty})", total=n_fits * unc_n,
                      unit="refits" if unc_method == "bootstrap" else "steps") if with_bar \
            else (err_console.status(compiling) if cold else _no_bar()) as bar:
        try:
            idn = identify_trials(trials, use_events=events, velocity_method=velocity, whole_record=whole,
                                  whole_velocity=whole_velocity, stiffness=stiffness, directions=direction,
                                  min_ratio=min_ratio, names=[str(p) for p in data], law=law, detrend=detrend,
                                  uncertainty=uncertainty, progress=getattr(bar, "advance", None))
        except ValueError as exc:
            _fail(_named(str(exc), data))
    rep = idn.report
    if not rep["steps"]:
        _fail(f"{', '.join(map(str, data))}: no velocity steps found (ratio >= {min_ratio:g})")
    from rig.analysis.identify import step_where
    from rig.model.checks import MARK, flagged

    rep.setdefault("warnings", []).extend(_calibration_warnings(trials, rep))  # issue 21
    warns = rep.get("warnings", [])
    table = Table(title="velocity steps (eqs. 10-12)")
    for c in ("trial", "t (s)", "v1 (µm/s)", "v2 (µm/s)", _rsf_label("A_mu", names), _rsf_label("B_mu", names),
              f"{_rsf_label('L', names)} (µm)", "r2", "window (µm)", "t_r (s)"):
        table.add_column(c, justify="right")
    table.add_column("accepted", justify="left", overflow="fold")
    for s in rep["steps"]:
        fl = flagged(warns, step_where(s, rep["n_trials"]))

        def cell(k, nd, s=s, fl=fl):
            return _fmt(s[k], nd) + (f" [yellow]{MARK}[/yellow]" if k in fl else "")

        table.add_row(str(s["trial"]), _fmt(s["t_s"], 6), _fmt(s["v1_um_s"]), _fmt(s["v2_um_s"]), cell("A_mu", 3),
                      cell("B_mu", 3), cell("L_um", 3), _fmt(s["r2"], 2), _fmt(s["window_um"]), _fmt(s.get("t_r_s"), 3),
                      f"[red]no: {s['rejected']}[/red]" if "rejected" in s else "yes")
    con.print(table)
    m, e = rep["mean"], rep["sem"]
    fl = flagged(warns, f"mean over {rep['sem_over']}")

    def mk(k):
        return f" [yellow]{MARK}[/yellow]" if k in fl else ""

    n_rej = len(rep.get("rejected_steps", []))
    con.print(f"mean ± s.e. over {rep['sem_over']} (n={rep['n_steps'] if rep['sem_over'] == 'steps' else rep['n_trials']}"
              + (f"; {n_rej} step(s) rejected" if n_rej else "") + "): "
              f"{_rsf_label('A_mu', names)} = {_fmt(m['A_mu'], 3)} ± {_fmt(e['A_mu'], 2)}{mk('A_mu')}, "
              f"{_rsf_label('B_mu', names)} = {_fmt(m['B_mu'], 3)} ± {_fmt(e['B_mu'], 2)}{mk('B_mu')}, "
              f"{_rsf_label('L', names)} = {_fmt(m['L_um'], 3)} ± {_fmt(e['L_um'], 2)} µm{mk('L_um')}, "
              f"k_cr (eq. 13) = {_fmt(m['k_cr_kN_per_m'], 3)} ± {_fmt(e['k_cr_kN_per_m'], 2)} kN/m{mk('k_cr_kN_per_m')}, "
              f"t_r (eq. 14) = {_fmt(m['t_r_s'], 3)} s")
    wr = rep.get("whole_record")
    wrs = [wr] if isinstance(wr, dict) else (wr or [])
    if law == "both":
        lw = rep.get("laws")
        lws = [lw] if isinstance(lw, dict) else (lw or [])
        for i, both in enumerate(lws):
            _print_laws(con, both, names, i if len(lws) > 1 else None)
    else:
        for i, w in enumerate(wrs):
            if not w.get("ok", True) and "params" not in w:
                con.print(f"whole-record fit failed: {w.get('reason')}")
                continue
            fl = flagged(warns, "whole-record fit" + (f" (trial {i})" if len(wrs) > 1 else ""))
            _print_whole(con, w, names, fl, MARK)
    for r in rep.get("rejected_steps", []):
        con.print(f"rejected step at t = {_fmt(r['t_s'], 6)} s: {r['reason']}", markup=False, highlight=False)
    for w in warns:
        con.print(f"[yellow]warning {MARK}:[/yellow] {w['where']}: {w['message']}", highlight=False)
    for note in rep.get("notes", []):
        con.print(f"[yellow]note:[/yellow] {note}", highlight=False)
    if json_out:
        write_json(rep, json_out)
    if plot:
        from rig.analysis.plots import plot_identification

        plot_identification(idn, plot)
        con.print(f"wrote {plot}", markup=False)


def _calibration_warnings(trials, rep: dict) -> list[dict]:
    """Forces outside a channel's verified range; step effects (eqs. 10-12, in N of friction at the smallest
    velocity ratio: A ln(v2/v1) 2N, B ln(v2/v1) 2N, (A - B) ln(v2/v1) 2N) below its stated uncertainty."""
    import math

    from rig.data import calibration_warnings

    m = rep["mean"]
    ratios = [s["v2_um_s"] / s["v1_um_s"] for s in rep["steps"] if s.get("v1_um_s")]
    out = []
    for tr in trials:
        try:
            lnr, n2 = math.log(max(min(ratios), 1.0 / min(ratios))), 2.0 * tr.normal_force_N
        except (ValueError, TypeError):
            continue
        effects = {"the direct effect A ln(v2/v1) 2N": m["A_mu"] * lnr * n2 if m.get("A_mu") is not None else None,
                   "the evolution effect B ln(v2/v1) 2N": m["B_mu"] * lnr * n2 if m.get("B_mu") is not None else None,
                   "the steady-state change (A - B) ln(v2/v1) 2N": (m["A_mu"] - m["B_mu"]) * lnr * n2
                   if m.get("A_mu") is not None and m.get("B_mu") is not None else None}
        out += calibration_warnings(tr, effects)
    return out
class _no_bar:
    """No progress bar (a plain Jacobian fit is quick)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def advance(self, *a, **k):
        pass


_SPEC_KEYS = ("mu0", "A_mu", "B_mu", "L_um", "k_mu_per_um", "stiffness_kN_per_m", "rate_mu_per_mm")
_RSF_KEYS = ("mu0", "a", "b", "Dc_um", "a_minus_b", "k_per_um", "stiffness_kN_per_m", "rate_mu_per_mm")


def _print_whole(con, w: dict, names: str, fl=(), mark: str = "") -> None:
    """One whole-record fit: each parameter with its s.e. and its 68 % interval where that is
    asymmetric (L), the correlation of A, B, L, the trend and the information criterion."""
    keys = _RSF_KEYS if names == "rsf" else _SPEC_KEYS
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
    unc = w.get("uncertainty", {}).get("method", "jacobian")
    con.print(f"whole-record fit ({w['model']}, velocity {w['velocity']}, {unc} errors, n_eff {_fmt(w.get('n_eff'), 4)} "
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


def _print_laws(con, both: dict, names: str, trial: int | None) -> None:
    """--law both: the slip- and aging-law fits side by side and the law the record prefers."""
    c = both["comparison"]
    for lw in ("slip", "aging"):
        con.print(f"[bold]{lw} law[/bold]" + (f" (trial {trial})" if trial is not None else "") + ":", highlight=False)
        _print_whole(con, both[lw], names)
    bic = c.get("bic", {})
    con.print(f"preferred law: {c['preferred_law']} (BIC on n_eff {_fmt(c.get('n_eff'), 4)}: slip "
              f"{_fmt(bic.get('slip'), 6)}, aging {_fmt(bic.get('aging'), 6)}; difference {_fmt(c.get('delta_bic'), 3)}, "
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
    from rig.analysis.stribeck import plot_stribeck, stribeck

    con = _con(json_out)
    if not window_um > 0:
        _fail(f"--window-um must be positive (got {window_um:g})")
    _outputs(json=json_out, plot=plot)

    trials = _load(data)
    try:
        rep = stribeck(trials, use_events=events, window_um=window_um, names=[str(p) for p in data])
    except ValueError as exc:
        _fail(_named(str(exc), data))
    if not rep["levels"]:
        _fail(f"{', '.join(map(str, data))}: no velocity levels found")
    table = Table(title=f"steady-state friction (last {window_um:g} µm of each level)")
    for c in ("branch", "v (µm/s)", "mu", "sd over trials", "trials"):
        table.add_column(c, justify="right")
    for d in ("up", "down"):
        for b in rep["branches"][d]:
            table.add_row(d, _fmt(b["v_um_s"]), _fmt(b["mu"], 5), _fmt(b["mu_sd"], 2), str(b["n_trials"]))
    con.print(table)
    src = " and ".join({"events": "the log's level events", "data": "velocity steps detected in the data"}[x]
                       for x in rep["level_source"])
    con.print(f"{rep['n_levels']} level(s) found (from {src}, at 25 Hz)"
              + (f"; {len(rep['rejected_levels'])} not counted:" if rep["rejected_levels"] else ""), highlight=False)
    for r in rep["rejected_levels"]:
        con.print(f"  level at {_fmt(r['v_um_s'])} µm/s (t = {_fmt(r['t_s'], 6)} s): {r['reason']}", highlight=False,
                  markup=False)
    for key, label in (("fit", "all levels"), ("fit_up", "up branch"), ("fit_down", "down branch")):
        f = rep[key]
        con.print(f"eq. (7), {label}: A - B = {_fmt(f['A_minus_B'], 4)} ± {_fmt(f['A_minus_B_err'], 2)}, "
                      f"mu0 = {_fmt(f['mu0'], 5)} (n={f['n']})")
    if json_out:
        write_json(rep, json_out)
    if plot:
        plot_stribeck(rep, plot)
        con.print(f"wrote {plot}", markup=False)


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
    from rig.model.paper import TABLE2
    from rig.model.spec import FrictionModel

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
    mass, kd, N = S.DEFAULT_MASS_KG, S.DEFAULT_KD_N_S_PER_UM, 100.0
    prof = None
    ppath = None
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
        if not params.is_file():
            _fail(f"{params}: no such file" if not params.exists() else f"{params}: not a file")
        try:
            text = params.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            _fail(f"{params}: cannot read: {getattr(exc, 'strerror', None) or exc}")
        try:
            rep = json.loads(text)
        except ValueError as exc:
            _fail(f"{params}, line {getattr(exc, 'lineno', '?')}: not JSON ({getattr(exc, 'msg', exc)}); expected a "
                  "`rig identify --json` report")
        try:
            m = rep["mean"]
            sets[params.stem] = {"A_mu": float(m["A_mu"]), "B_mu": float(m["B_mu"]), "L_um": float(m["L_um"])}
            N = float(rep.get("normal_force_N", N))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            _fail(f"{params}: not a rig identify report with mean A_mu, B_mu, L_um ({type(exc).__name__}: {exc})")
        bad = [k for k, v in sets[params.stem].items() if not math.isfinite(v)] + ([] if N > 0 else ["normal_force_N"])
        if bad or not sets[params.stem]["L_um"] > 0:
            _fail(f"{params}: mean {', '.join(bad) or 'L_um'} is not a usable number (L_um must be positive, "
                  "all finite)")
    else:
        names = [lubricant] if lubricant else list(TABLE2)
        for nm in names:
            if nm not in TABLE2:
                _fail(f"unknown lubricant {nm!r}; known: {', '.join(TABLE2)}")
            sets[nm] = {k: TABLE2[nm][k][0] for k in ("A_mu", "B_mu", "L_um")}
    ki = prof.controller.ki_N_per_um_s if prof is not None else 0.0
    analyses = {}
    table = Table(title=f"critical stiffness at V0 = {v0:g} µm/s (m = {mass:g} kg, kd = {kd:g} N s/µm, "
                        f"ki = {ki:g} N/(µm s), N = {N:g} N per rider)")
    for c in ("set", "eq.13 per rider (N; Table 2)", "moving piece eq.13 (2N)", "eq.8 (2N, kd, m)",
              "rig loop PD", "rig loop PID", f"kp min (x{margin:g})"):
        table.add_column(c, justify="right")
    for nm, p in sets.items():
        a = S.analyse(S.StabilityInputs(p["A_mu"], p["B_mu"], p["L_um"], N, mass, kd, v0), margin)
        if prof is not None:
            model = (prof.friction_model(nm) if nm in getattr(prof, "lubricants", {}) and not params
                     else FrictionModel(params={"mu0": 0.12, **p}))
            loop = {}
            for label, k_i in (("PD", 0.0), ("PID", ki)):
                try:
                    lm = S.LoopModel.from_profile(prof, model, ki_N_per_um_s=k_i, V0_um_s=v0)
                    k = S.k_cr_loop(lm)
                except ValueError as exc:
                    k, loop[f"{label}_note"] = None, str(exc)
                loop[label] = k
            a["k_cr_loop_PD_kN_per_m"] = loop["PD"] * 1e3 if loop["PD"] is not None else None
            a["k_cr_loop_PID_kN_per_m"] = loop["PID"] * 1e3 if loop["PID"] is not None else None
            k_use = loop["PID"] if ki > 0 else loop["PD"]
            if k_use == 0.0:
                a["kp_min_N_per_um"] = margin * loop["PD"] if loop["PD"] else None
                a["advice"] = ("the rig's PID loop has no finite k_cr (the integral term holds the slow friction "
                               "mode); without the I term (PD) kp >= "
                               f"{_fmt(a['kp_min_N_per_um'] * 1e3 if a['kp_min_N_per_um'] else None)} kN/m "
                               f"= {margin:g} x k_cr")
            elif k_use is not None:
                a["kp_min_N_per_um"] = margin * k_use
                a["advice"] = (f"kp >= {margin * k_use * 1e3:.4g} kN/m = {margin:g} x k_cr of the rig's loop "
                               f"({'PID' if ki > 0 else 'PD'}, 1 kHz)")
        a["statement"] = S.fixture_statement(p["A_mu"], p["B_mu"], p["L_um"], N)
        analyses[nm] = a

        def k(x):
            return "none (stable at every kp)" if x == 0 else (_fmt(x) if x is not None else "-")

        table.add_row(nm, _fmt(a["k_cr_eq13_kN_per_m"]), _fmt(a["k_cr_eq13_fixture_kN_per_m"]),
                      _fmt(a["k_cr_eq8_kN_per_m"]) if a["k_cr_eq8_kN_per_m"] else "inf",
                      k(a.get("k_cr_loop_PD_kN_per_m")), k(a.get("k_cr_loop_PID_kN_per_m")),
                      _fmt(a["kp_min_N_per_um"] * 1e3 if a["kp_min_N_per_um"] else None) + " kN/m")
    con.print(table)
    for nm, a in analyses.items():
        con.print(f"{nm}: {a['statement']}")
        con.print(f"{nm}: {a['advice']}")
    con.print("[dim]All stiffnesses in kN/m. The stiffness the controller must provide is the moving test piece's "
                  "(2 N); Table 2 prints (B - A) N / L per rider interface, half of it. The rig loop columns: "
                  "eq. (8)'s system with the rig's discrete PID (1 kHz, zero-order hold, backward-difference D), "
                  "actuator, compliance and LVDT filter (rig.analysis.stability.k_cr_loop).[/dim]")
    checks = []
    if simulate:
        if prof is None:
            _fail("--simulate needs the simulated rig (rig.sim) and a profile")
        if jobs is not None and jobs < 1:
            _fail(f"--jobs must be at least 1 (got {jobs})")
        from contextlib import ExitStack

        from rig.catalog.batch import mapper

        stack = ExitStack()
        bar = stack.enter_context(progress_bar(json_out, "kp scan", unit="simulated runs"))
        map_fn = stack.enter_context(mapper(jobs, scheduler, progress=bar.advance))
        for nm in sets:
            if params or nm not in prof.lubricants:
                con.print(f"{nm}: not a lubricant of the profile; simulation skipped")
                continue
            for k_i in (0.0, ki) if ki > 0 else (0.0,):
                lm = S.LoopModel.from_profile(prof, prof.friction_model(nm), ki_N_per_um_s=k_i, V0_um_s=v0)
                k_lin = S.k_cr_loop(lm)
                if not k_lin:
                    con.print(f"{nm} ({'PID' if k_i else 'PD'}): no finite k_cr in the analysis; scan skipped")
                    continue
                bar.update(description=f"{nm} ({'PID' if k_i else 'PD'}): kp scan")
                if True:
                    r = S.scan_boundary(nm, profile=ppath, ki_N_per_um_s=k_i, V0_um_s=v0,
                                        factors=(0.8, 0.9, 0.95, 1.05, 1.1, 1.25), map_fn=map_fn)
                r["k_cr_eq8_N_per_um"] = analyses[nm]["k_cr_eq8_N_per_um"]
                checks.append(r)
                lo, hi = r["bracket_N_per_um"]
                inside = r["analysis_in_bracket"]
                con.print(f"{nm} ({'PID' if k_i else 'PD'}): simulated boundary in "
                          f"[{_fmt(lo * 1e3 if lo else None)}, {_fmt(hi * 1e3 if hi else None)}] kN/m "
                          f"(stick-slip at the low end, steady at the high end) vs the rig loop's "
                          f"{_fmt(k_lin * 1e3)} kN/m"
                          + ("" if inside is None else " (inside the bracket)" if inside else
                             " (OUTSIDE the bracket)"))
        stack.close()
        con.print(f"[dim]criterion: {S.STUCK_FRACTION_MAX:.0%} stuck / spread {S.SPREAD_MAX:g} V0 "
                      f"({checks[0]['criterion'] if checks else ''})[/dim]")
    if json_out:
        doc = {"schema": "rig.stability/2", "V0_um_s": v0, "mass_kg": mass, "kd_N_s_per_um": kd,
               "ki_N_per_um_s": ki, "normal_force_N": N, "analyses": analyses, "checks": checks}
        write_json(doc, json_out)
    if plot:
        S.plot_map(checks, plot)
        con.print(f"wrote {plot}", markup=False)


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
    jobs: Optional[int] = typer.Option(None, "--jobs", help="Trials on N worker processes (Dask; default: all "
                                                            "cores; 1: serially in this process)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run the trials on an existing Dask "
                                                                      "cluster, tcp://HOST:PORT."),
):
    """Simulated trials in the paper's protocol, identified: our Table 2 beside the paper's."""
    from rig.analysis.plots import plot_reproduce
    from rig.analysis.reproduce import reproduce
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
                rep = reproduce(trials, seed=seed, lubricants=lubs, profile=profile, whole_record=whole,
                                engine=engine, map_fn=map_fn)
        except BatchError as exc:
            _fail(str(exc), 1)
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
    con.print(table)
    for lub in lubs:
        b = rep["lubricants"][lub]["bias"]
        con.print(f"{lub}: identification bias, recovered/true - 1 (mean ± s.e. over trials): "
                      + ", ".join(f"{k} {100 * (b[k]['recovered_vs_true_rel'] or 0):+.1f} ± "
                                  f"{100 * (b[k]['recovered_vs_true_rel_sem'] or 0):.1f} %" for k in b)
                      + "; recovered mean vs Table 2 (in the paper's s.e.): "
                      + ", ".join(f"{k} {b[k]['vs_paper_z']:+.2f}" for k in b))
    from rig.analysis.stability import fixture_statement

    for lub in lubs:
        m = rep["lubricants"][lub]["recovered"]["mean"]
        con.print(f"{lub}: k_cr column = eq. (13) per rider; {fixture_statement(m['A_mu'], m['B_mu'], m['L_um'])}")
    for lub in lubs:
        c = rep["lubricants"][lub]["checks"]
        bad = [k for k, v in c.items() if not v["ok"]]
        con.print(f"{lub}: recovered - truth within the paper's s.e.: "
                      + ("all" if not bad else f"[red]not for {', '.join(bad)}[/red]")
                      + f" ({rep['lubricants'][lub]['engine']})")
    from rig.model.checks import check_params

    warns = []
    for lub in lubs:
        warns += check_params(rep["lubricants"][lub]["recovered"]["mean"], rep["lubricants"][lub]["recovered"]["sem"],
                              where=f"{lub}: recovered mean")
    rep["warnings"] = warns
    for w in warns:
        con.print(f"[yellow]warning (!):[/yellow] {w['where']}: {w['message']}", highlight=False)
    if json_out:
        write_json(rep, json_out)
    if plot:
        plot_reproduce(rep, plot, warns)
        con.print(f"wrote {plot}", markup=False)
