"""``rig tune step|frf|autotune``: measured loop tuning (:mod:`rig.analysis.tuning`).

``step`` and ``frf`` read a trial log with a ``square`` / ``sine_sweep`` segment (its 1 kHz raw
channel); the profile and the recipe's switches come from the log itself. ``autotune`` runs a
bounded sweep through the normal ``rig run --hardware`` path (its own process, every
interlock armed), fits the plant to the measured response and writes the proposed gains as an
overlay profile that ``extends:`` the original (never the original itself).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from rig.commands.analysis import _con, _fail, _outputs
from rig.commands.common import EXIT_FAILED, JSON_HELP, check_output_path, write_json

tune_app = typer.Typer(help="Loop tuning: step response, frequency response, autotune.", no_args_is_help=True)

# autotune's sweep: bounded in amplitude, time and force (docs/hardware.md, "Commissioning")
SWEEP = {"f0_hz": 2.0, "f1_hz": 70.0, "amplitude_um": 0.35, "duration_s": 20.0, "velocity_um_s": 160.0}
MAX_AMPLITUDE_UM = 2.0
MAX_SWEEP_S = 60.0
SWEEP_FORCE_N = 250.0   # the controller's output clamp during the sweep (overlay): ~10 x the friction
MAX_REL_ERR = 0.25      # the plant fit's relative standard error beyond which no gains are proposed
MIN_SEGMENTS = 15       # ... and the least number of clean Welch segments of the sweep


def _log_context(path: Path):
    """(raw TrialData, RigProfile, FrictionModel, controller switches) of a trial log."""
    from rig.config.profile import RigProfile
    from rig.data import DataFormatError
    from rig.log import read_metadata, read_trial

    if path.suffix.lower() != ".mcap":
        _fail(f"{path}: rig tune reads a trial log (.mcap) with its 1 kHz raw channel and its profile")
    try:
        trial = read_trial(path, channel="raw")
        meta = read_metadata(path)
    except DataFormatError as exc:
        _fail(str(exc))
    try:
        prof = RigProfile.model_validate(json.loads(meta["rig_profile"]["json"]))
        rec = json.loads(meta["recipe"]["json"])
    except (KeyError, ValueError) as exc:
        _fail(f"{path}: the log carries no readable rig profile or recipe ({exc}); was it written by rig run?")
    lub = rec.get("lubricant", "boundary")
    if lub not in prof.lubricants:
        _fail(f"{path}: lubricant {lub!r} is not in the log's profile ({', '.join(prof.lubricants)})")
    return trial, prof, prof.friction_model(lub), rec.get("controller") or {}


def _g(v, fmt=".4g") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


@tune_app.command("step")
def step_cmd(
    data: Path = typer.Argument(..., help="Trial log (.mcap) with a square segment.", show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.tune.step/1)"),
):
    """Step response of the last square segment: rise time (10-90 %), overshoot, settling time
    (5 % band) per edge, and the following error."""
    from rig.analysis.tuning import step_response

    con = _con(json_out)
    _outputs(json=json_out)
    trial, *_ = _log_context(data)
    try:
        rep = step_response(trial)
    except ValueError as exc:
        _fail(str(exc))
    seg = rep["segment"]
    tab = Table(title=f"step response: square {seg['amplitude_um']:g} µm at {seg['frequency_hz']:g} Hz"
                      + (f" on a {seg['velocity_um_s']:g} µm/s slide" if seg.get("velocity_um_s") else ""))
    for c in ("edge", "t (s)", "step (µm)", "rise 10-90 % (ms)", "overshoot (%)", "settling (ms)"):
        tab.add_column(c, justify="right")
    for r in rep["edges"]:
        tab.add_row(str(r["edge"] + 1) + (" (reverses the slide)" if r["reverses"] else ""), f"{r['t_s']:.3f}",
                    f"{r['delta_um']:+.3g}",
                    _g(None if r["rise_s"] is None else 1e3 * r["rise_s"], ".3g"), f"{100 * r['overshoot']:.1f}",
                    _g(None if r["settling_s"] is None else 1e3 * r["settling_s"], ".3g"))
    con.print(tab)
    con.print(f"mean over edges {', '.join(str(i + 1) for i in rep['edges_in_means'])}: rise {_g(rep['rise_s'] and 1e3 * rep['rise_s'], '.3g')} ms, overshoot "
              f"{_g(rep['overshoot'] and 100 * rep['overshoot'], '.3g')} %, settling "
              f"{_g(rep['settling_s'] and 1e3 * rep['settling_s'], '.3g')} ms (not settled: -); following error "
              f"rms {rep['following_error_rms_um']:.3g} µm, max {rep['following_error_max_um']:.3g} µm")
    if json_out:
        write_json(rep, json_out)


def _print_frf(con, rep: dict) -> None:
    c = rep.get("compare")
    con.print(f"H1 over {rep['segments_used']} Welch segments of {rep['nperseg']} samples"
              f" (left out: those with {rep['stalls_in_sweep']} loop stall(s) and {rep['stale_position_runs']} stale "
              "position stretch(es) of the sweep); coherence >= 0.8 on "
              f"{100 * rep['coherent_fraction']:.0f} % of {rep['segment']['f0_hz']:g}-{rep['segment']['f1_hz']:g} Hz")
    con.print(f"-3 dB bandwidth {_g(rep['bandwidth_3db_hz'], '.3g')} Hz; crossover {_g(rep['crossover_hz'], '.3g')} Hz, "
              f"phase margin {_g(rep['phase_margin_deg'], '.3g')} deg, gain margin {_g(rep['gain_margin_db'], '.3g')} dB "
              f"(at {_g(rep['gain_margin_hz'], '.3g')} Hz; open loop from the measured closed loop and the known PID)")
    if c:
        verdict = "within" if c["within_1db_5deg"] else "NOT within"
        con.print(f"measured vs rig stability's loop model up to {c['max_hz']:g} Hz ({c['n']} coherent frequencies in "
                  f"{c['n_bands']} 1/6-octave bands): gain max {c['gain_db_max_abs']:.2f} dB, phase max "
                  f"{c['phase_deg_max_abs']:.1f} deg: {verdict} 1 dB and 5 deg (single bins: max "
                  f"{c['bin_gain_db_max_abs']:.2f} dB, {c['bin_phase_deg_max_abs']:.1f} deg, rms {c['gain_db_rms']:.2f} dB, "
                  f"{c['phase_deg_rms']:.1f} deg; a bin's own random error about {c['bin_random_error_db_median']:.2f} dB)"
                  + (f"; the phase difference grows as a delay of {c['delay_ms']:.2f} ms" if "delay_ms" in c else ""))
    for note in rep["notes"]:
        con.print(f"[yellow]note:[/yellow] {note}", highlight=False)


@tune_app.command("frf")
def frf_cmd(
    data: Path = typer.Argument(..., help="Trial log (.mcap) with a sine_sweep segment.", show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.tune.frf/1: arrays "
                                                                          "frequency_hz, gain_db, phase_deg, coherence)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a Bode plot (PNG) with the loop model beside it."),
    nperseg: int = typer.Option(1024, "--nperseg", help="Welch segment length (samples)."),
):
    """Frequency response of the position loop from the last sine sweep: H1 with coherence, gain and
    phase margins, -3 dB bandwidth, and rig stability's loop model of the same profile."""
    from rig.analysis.tuning import frf, plot_frf

    con = _con(json_out)
    if nperseg < 64:
        _fail(f"--nperseg must be at least 64 (got {nperseg})")
    _outputs(json=json_out, plot=plot)
    trial, prof, model, switches = _log_context(data)
    try:
        rep = frf(trial, prof, model, switches, nperseg=nperseg)
    except ValueError as exc:
        _fail(str(exc))
    _print_frf(con, rep)
    if json_out:
        write_json(rep, json_out)
    if plot:
        plot_frf(rep, plot)
        con.print(f"wrote {plot}", markup=False)


def _sweep_recipe(lubricant: str, sweep: dict) -> str:
    seg = ", ".join(f"{k}: {v:g}" for k, v in sweep.items())
    return (f"name: autotune-sweep\ndescription: rig tune autotune's bounded sweep\nlubricant: {lubricant}\n"
            "accel_um_s2: 500\nlog: {raw_rate_hz: 1000, decimated_rate_hz: 25}\n"
            "controller: {ff1: on, friction_ff: on}\nsegments:\n  - {kind: hold, duration_s: 1}\n"
            f"  - {{kind: sine_sweep, label: autotune sweep, {seg}}}\n  - {{kind: hold, duration_s: 1}}\n")


def _overlay_text(base: Path, out: Path, name: str, gains: dict, header: list[str]) -> str:
    try:
        ext = os.path.relpath(base.resolve(), out.resolve().parent)
    except ValueError:
        ext = str(base.resolve())
    lines = [f"# {h}" for h in header] + [f"extends: {ext}", f"name: {name}", "controller:"]
    for k in ("kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um", "ff1_N_s_per_um"):
        lines.append(f"  {k}: {gains[k]:.4g}")
    return "\n".join(lines) + "\n"


@tune_app.command("autotune")
def autotune_cmd(
    hardware: Path = typer.Option(..., "--hardware", help="Rig profile of the real (or emulated) rig.",
                                  show_default=False, metavar="PROFILE"),
    out: Path = typer.Option(..., "--out", "-o", help="Overlay profile to write (extends PROFILE).",
                             show_default=False),
    lubricant: str = typer.Option("boundary", "--lubricant", help="Lubricant of the profile on the rig."),
    amplitude_um: float = typer.Option(SWEEP["amplitude_um"], "--amplitude-um",
                                       help=f"Sweep amplitude (at most {MAX_AMPLITUDE_UM:g} µm)."),
    duration_s: float = typer.Option(SWEEP["duration_s"], "--duration-s", help=f"Sweep duration (at most "
                                                                              f"{MAX_SWEEP_S:g} s)."),
    from_log: Optional[Path] = typer.Option(None, "--from-log", help="Skip the sweep: fit an existing sweep log "
                                                                     "(.mcap) of this profile.", show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP),
    yes: bool = typer.Option(False, "--yes", help="Do not ask before moving the actuator."),
):
    """Measure the loop with a bounded sine sweep on a slide (through rig run --hardware, every
    interlock armed), fit the plant, and propose kp, ki, kd and FF1 with the margin to k_cr,
    beside the same rule's analytic advice; writes them as an overlay profile."""
    from rig.analysis.tuning import RULE, fit_plant, frf, propose_gains
    from rig.config.loader import ConfigError
    from rig.config.profile import load_profile

    con = _con(json_out)
    check_output_path(out, "--out", (".yaml", ".yml"))
    _outputs(json=json_out)
    try:
        prof = load_profile(hardware)
    except ConfigError as exc:
        _fail(str(exc))
    if out.exists() and out.resolve() == hardware.resolve():
        _fail(f"--out {out}: that is the profile itself; autotune writes an overlay beside it, never in place")
    if lubricant not in prof.lubricants:
        _fail(f"--lubricant {lubricant!r}: not in profile {hardware} ({', '.join(prof.lubricants)})")
    if not (0 < amplitude_um <= MAX_AMPLITUDE_UM):
        _fail(f"--amplitude-um must be in (0, {MAX_AMPLITUDE_UM:g}] µm (got {amplitude_um:g})")
    if not (0 < duration_s <= MAX_SWEEP_S):
        _fail(f"--duration-s must be in (0, {MAX_SWEEP_S:g}] s (got {duration_s:g})")
    sweep = {**SWEEP, "amplitude_um": amplitude_um, "duration_s": duration_s}
    sweep["velocity_um_s"] = max(SWEEP["velocity_um_s"], 1.05 * 2 * math.pi * sweep["f1_hz"] * amplitude_um)
    if from_log is None:
        from_log = _run_sweep(con, hardware, prof, lubricant, sweep, yes, json_out)
    trial, prof_log, model, switches = _log_context(from_log)
    try:
        rep = frf(trial, prof_log, model, switches)
        plant = fit_plant(rep, prof_log, model)
        V = rep["slide_um_s"]
        tuned = propose_gains(prof_log, model, plant, V_um_s=V)
        advice = propose_gains(prof_log, model, None, V_um_s=V)
    except ValueError as exc:
        _fail(f"{from_log}: {exc}")
    _print_frf(con, rep)
    pp, pe = plant["params"], plant["rel_err"]
    con.print(f"plant fit ({plant['n_freq']} frequencies, {plant['band_hz'][0]:.3g}-{plant['band_hz'][1]:.3g} Hz): "
              f"leakage tau_L {1e3 * pp['tau_leak_s']:.3g} ms (±{100 * pe['tau_leak_s']:.0f} %), delay "
              f"{1e3 * pp['delay_s']:.3g} ms; mass {plant['mass_kg']:g} kg ({plant['mass_note']}), force gain "
              f"{pp['gain']:g} ({plant['gain_note']})", highlight=False)
    worst = pe["tau_leak_s"]
    if not math.isfinite(worst) or worst > MAX_REL_ERR or rep["segments_used"] < MIN_SEGMENTS:
        _fail(f"the plant is not determined well enough to tune on: the leakage is known to "
              f"±{100 * pe['tau_leak_s']:.0f} % (at most {100 * MAX_REL_ERR:.0f} %) from "
              f"{rep['segments_used']} clean Welch segments (at least {MIN_SEGMENTS}; {rep['stalls_in_sweep']} loop stall(s), "
              f"{rep['stale_position_runs']} stale position stretch(es) in the sweep); repeat on a quieter machine or "
              f"with a longer --duration-s; no gains proposed (log {from_log})", EXIT_FAILED)
    diffs = _print_gains(con, tuned, advice, prof_log)
    m = tuned["margin_to_k_cr"]
    header = [f"written by rig tune autotune from {from_log} (sweep {rep['segment']['f0_hz']:g}-"
              f"{rep['segment']['f1_hz']:g} Hz, {rep['segment']['amplitude_um']:g} µm on {V:g} µm/s)",
              f"margin to k_cr: {m:.3g} x" if m else "no finite k_cr with these gains",
              "rule: " + RULE]
    _write_overlay(out, _overlay_text(hardware, out, f"{prof.name}-tuned", tuned, header))
    con.print(f"wrote {out} (extends {hardware}; the profile itself is unchanged)", markup=False)
    if json_out:
        write_json({"schema": "rig.tune.autotune/1", "log": str(from_log), "plant": plant, "proposed": tuned,
                    "analytic_advice": advice, "relative_difference": diffs, "overlay": str(out),
                    "frf": {k: rep[k] for k in ("bandwidth_3db_hz", "phase_margin_deg", "gain_margin_db",
                                                "crossover_hz", "coherent_fraction")}}, json_out)


def _run_sweep(con, hardware: Path, prof, lubricant: str, sweep: dict, yes: bool, json_out) -> Path:
    """The bounded sweep trial through ``rig run --hardware`` (after asking, unless --yes); its log."""
    from rig.config.recipe import compile_recipe, parse_recipe
    from trajectories import PlanError

    if prof.hardware is None:
        _fail(f"{hardware}: no hardware section: autotune runs on a rig (give --from-log for a sim sweep)")
    if not yes and sys.stdin.isatty() and not typer.confirm(
            f"autotune moves the actuator: a {sweep['duration_s']:g} s sine sweep of {sweep['amplitude_um']:g} µm "
            f"on a {sweep['velocity_um_s']:.0f} µm/s slide, force clamped at {SWEEP_FORCE_N:g} N. Go on?"):
        raise typer.Exit(1)
    text = _sweep_recipe(lubricant, sweep)
    try:  # the sweep must fit this rig's stroke and speed before anything moves
        compile_recipe(parse_recipe(text, "autotune sweep"), prof)
    except PlanError as exc:
        _fail(f"the autotune sweep does not fit {hardware}: {exc}; lower --duration-s")
    tmp = Path(tempfile.mkdtemp(prefix="rig-autotune-"))
    (tmp / "sweep.yaml").write_text(text)
    (tmp / "bounded.yaml").write_text(f"extends: {hardware.resolve()}\ncontroller:\n"
                                      f"  output_max_N: {SWEEP_FORCE_N:g}\n")
    log = tmp / "sweep.mcap"
    cmd = [sys.executable, "-m", "rig.cli", "run", str(tmp / "sweep.yaml"), "--hardware",
           str(tmp / "bounded.yaml"), "--out", str(log)]
    con.print(f"sweep through rig run --hardware (log {log})", highlight=False)
    rc = subprocess.call(cmd, stdout=sys.stderr if json_out and str(json_out) == "-" else None)
    if rc != 0:
        _fail(f"the sweep trial ended with exit status {rc} (a trip or a device fault: see above; log {log}); "
              "no gains proposed", EXIT_FAILED)
    return log


def _print_gains(con, tuned: dict, advice: dict, prof_log) -> dict:
    """The proposed gains beside the analytic advice and the profile's; their relative differences."""
    tab = Table(title="proposed gains (the rule on the fitted plant) vs the analytic advice (the rule on the "
                      "profile's model)")
    for c in ("gain", "proposed", "analytic advice", "difference", "profile now"):
        tab.add_column(c, justify="right")
    diffs = {}
    for k in ("kp_N_per_um", "ki_N_per_um_s", "kd_N_s_per_um", "ff1_N_s_per_um"):
        diffs[k] = tuned[k] / advice[k] - 1.0 if advice[k] else None
        tab.add_row(k, f"{tuned[k]:.4g}", f"{advice[k]:.4g}", _g(diffs[k] and 100 * diffs[k], "+.1f") + " %",
                    f"{getattr(prof_log.controller, k):.4g}")
    con.print(tab)
    return diffs


def _write_overlay(out: Path, text: str) -> None:
    """The overlay profile, atomically, and only if it loads (exit 1 naming ``out`` otherwise)."""
    from rig.config.loader import ConfigError
    from rig.config.profile import load_profile
    from rig.data import atomic_path

    try:
        with atomic_path(out) as tmp_out:
            tmp_out.write_text(text)
            try:
                load_profile(tmp_out)
            except ConfigError as exc:
                raise ValueError(str(exc)) from exc
    except ValueError as exc:
        _fail(f"internal check of the overlay failed: {exc}", EXIT_FAILED)
    except OSError as exc:
        _fail(f"cannot write {out}: {exc.strerror or exc}", EXIT_FAILED)


def register(app: typer.Typer) -> None:
    app.add_typer(tune_app, name="tune")
