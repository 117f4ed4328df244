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
    err_console.print(f"[red]error:[/red] {msg}")
    raise typer.Exit(code)


def _load(paths: list[Path]):
    from rig.data import DataFormatError, load_trial

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
