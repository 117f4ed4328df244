"""Trial commands: ``rig run``, ``rig info``, ``rig export``, ``rig import``, ``rig recover``.

``rig run RECIPE --sim`` loads and validates the recipe (:mod:`rig.recipe`),
the rig profile and the friction model, compiles the reference
(:mod:`trajectories`) and checks it against the stroke and the actuator BEFORE
anything moves, then runs the closed loop (:class:`rig.sim.SimRig`) block by
block and logs every block to one MCAP per trial (:mod:`rig.log`).
``--hardware PROFILE`` hands the same plan and log writer to
``rig.hardware.runner.run_hardware_trial``.

Exit status: 0 success; 2 bad input (recipe, profile, plan, CSV; nothing is
written); 1 a failure while running; 130 interrupted by Ctrl-C (the MCAP is
finished with what was logged and marked ``interrupted``).
"""

from __future__ import annotations

import json
import math
import time
import warnings
from enum import Enum
from pathlib import Path
from typing import Any, Callable, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

EXIT_BAD_INPUT = 2
EXIT_FAILURE = 1
EXIT_INTERRUPTED = 130

err_console = Console(stderr=True, soft_wrap=True)
console = Console(soft_wrap=True)


def _fail(message: str, code: int = EXIT_BAD_INPUT) -> None:
    err_console.print(f"[bold red]error:[/] {message}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


# ---------------------------------------------------------------------------
# Progress reporting (shared with the hardware runner)
# ---------------------------------------------------------------------------

class TrialProgress:
    """Progress of one trial: a rich bar with the segment, simulated time and real-time factor.

    Call ``progress(t_s)`` or ``progress.update(t_s, segment=..., **fields)`` as
    the loop advances (cheap: redraws at most ~8 times a second).
    ``plan`` gives the total duration and the segment names.
    """

    def __init__(self, plan, title: str = "", enabled: bool = True, console_: Console | None = None):
        self.plan = plan
        self.title = title
        self.enabled = enabled
        self.t_s = 0.0
        self._t0 = time.perf_counter()
        self._last_draw = 0.0
        self._progress: Progress | None = None
        self._task = None
        self._console = console_ or err_console

    def __enter__(self) -> "TrialProgress":
        self._t0 = time.perf_counter()
        if self.enabled:
            self._progress = Progress(
                TextColumn("[bold]{task.description}"), BarColumn(),
                TextColumn("{task.fields[simt]}"), TextColumn("{task.fields[rtf]}"), TimeElapsedColumn(),
                console=self._console, transient=False, refresh_per_second=8)
            self._progress.__enter__()
            self._task = self._progress.add_task(self._describe(0.0), total=max(self.plan.duration_s, 1e-9),
                                                 simt=self._simt(0.0), rtf="")
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._draw(self.t_s)
            self._progress.__exit__(*exc)
            self._progress = None

    @property
    def wall_s(self) -> float:
        return time.perf_counter() - self._t0

    @property
    def realtime_factor(self) -> float:
        w = self.wall_s
        return self.t_s / w if w > 0 else float("nan")

    def _describe(self, t_s: float) -> str:
        seg = self.plan.segment_at(t_s)
        name = seg["label"] or seg["kind"]
        n = sum(1 for s in self.plan.segments if s["index"] >= 0)
        if seg["index"] < 0:
            return f"{self.title}{name}"
        return f"{self.title}segment {seg['index'] + 1}/{n} {name}"

    def _simt(self, t_s: float) -> str:
        return f"{t_s:8.1f}/{self.plan.duration_s:.1f} s"

    def _draw(self, t_s: float) -> None:
        if self._progress is None:
            return
        self._progress.update(self._task, completed=t_s, description=self._describe(t_s), simt=self._simt(t_s),
                              rtf=f"{self.realtime_factor:7.1f}x real time")

    def update(self, t_s: float, **_: Any) -> None:
        self.t_s = float(t_s)
        now = time.perf_counter()
        if now - self._last_draw >= 0.125:
            self._last_draw = now
            self._draw(self.t_s)

    __call__ = update


# ---------------------------------------------------------------------------
# Running a simulated trial
# ---------------------------------------------------------------------------

def run_sim_trial(plan, recipe, profile, writer, progress: Callable | None = None, *, friction_model=None,
                  seed: int = 0, normal_force_N: float | None = None, stats_every_s: float = 1.0) -> dict:
    """Run ``plan`` on the simulated rig, logging every block to ``writer``.

    Planned events are logged as the loop reaches them; loop statistics (ticks,
    wall time, real-time factor, tracking error) every ``stats_every_s`` of
    simulated time. A KeyboardInterrupt propagates after logging an
    ``interrupted`` event (the caller closes the log).
    """
    from rig.sim import SimRig

    lubricant = recipe.lubricant
    fm = friction_model if friction_model is not None else profile.friction_model(lubricant)
    nf = float(normal_force_N if normal_force_N is not None else recipe.normal_force_N)
    rig = SimRig(profile, fm, nf, seed)
    block_ticks = max(1, int(round(recipe.log.block_s * plan.loop_rate_hz)))
    writer.schedule_events(plan.events)
    writer.event(0.0, "trial_start", recipe=recipe.name, lubricant=lubricant, normal_force_N=nf, seed=seed,
                 duration_s=plan.duration_s, n_ticks=plan.n_ticks, backend="sim")
    t_wall0 = time.perf_counter()
    dt_half = 0.5 / plan.loop_rate_hz
    next_stats = stats_every_s
    # window of the loop statistics: differences of the writer's running sums
    w0 = (t_wall0, writer.ticks, writer.sum_err2_um2, writer.n_err, writer.n_valve_saturated)
    t_last = 0.0
    try:
        for block in rig.run_blocks(plan.x_ref_um, block_ticks=block_ticks):
            writer.write_block(block)
            t_last = float(block["t_s"][-1])
            if t_last >= next_stats - dt_half:
                now = time.perf_counter()
                dw = now - w0[0]
                ticks = writer.ticks - w0[1]
                n_err = writer.n_err - w0[3]
                writer.loop_stats(t_last, {
                    "ticks": ticks, "wall_s": dw, "ticks_per_s": ticks / dw if dw > 0 else None,
                    "realtime_factor": (ticks / plan.loop_rate_hz) / dw if dw > 0 else None,
                    "tracking_error_rms_um": math.sqrt((writer.sum_err2_um2 - w0[2]) / n_err) if n_err else None,
                    "valve_saturated_fraction": (writer.n_valve_saturated - w0[4]) / ticks if ticks else None})
                w0 = (now, writer.ticks, writer.sum_err2_um2, writer.n_err, writer.n_valve_saturated)
                next_stats += stats_every_s
            if progress is not None:
                progress(t_last)
    except KeyboardInterrupt:
        writer.event(t_last, "interrupted", reason="KeyboardInterrupt (Ctrl-C)")
        raise
    wall = time.perf_counter() - t_wall0
    return {"ticks": writer.ticks, "duration_s": t_last, "wall_s": wall}


def _summary_table(result: dict, writer, out: Path, status: str) -> Table:
    ticks = writer.ticks
    wall = result.get("wall_s") or float("nan")
    dur = writer.last_t_s
    tab = Table(title=f"trial {status}: {out}", show_header=False, box=None)
    tab.add_row("simulated/trial time", f"{dur:.2f} s")
    tab.add_row("wall time", f"{wall:.2f} s")
    tab.add_row("loop ticks", f"{ticks} ({ticks / wall:,.0f} ticks/s, {dur / wall:.1f}x real time)"
                if wall and wall > 0 else str(ticks))
    tab.add_row("tracking error rms", f"{writer.tracking_error_rms_um:.3f} µm (max {writer.max_abs_err_um:.2f} µm)")
    tab.add_row("mean friction", f"{writer.mean_friction_N:.3f} N (mu {writer.mean_mu:.4f}); "
                                 f"mean |friction| {writer.mean_abs_friction_N:.3f} N")
    size = out.stat().st_size if out.exists() else 0
    tab.add_row("file written", f"{out} ({size / 1e6:.2f} MB)")
    return tab


def _trial_paths(out: Path, n: int) -> list[Path]:
    if n == 1:
        return [out]
    return [out.with_name(f"{out.stem}-{k + 1:02d}{out.suffix}") for k in range(n)]


def _git_describe() -> str:
    """The repository's commit (and '-dirty'), for the trial metadata; '' outside a git checkout."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(repo), "describe", "--always", "--dirty", "--abbrev=12"],
                             capture_output=True, text=True, timeout=3)
        return out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        return ""


def _profile_dict(profile) -> dict:
    try:
        return profile.model_dump(mode="json")
    except Exception:  # pragma: no cover - a non-pydantic profile
        return {"repr": repr(profile)}


def run_command(
    recipe_path: Path = typer.Argument(..., help="Recipe YAML (config/recipes/*.yaml).", show_default=False,
                                     metavar="RECIPE"),
    sim: bool = typer.Option(False, "--sim", help="Run on the simulated rig (rig.sim.SimRig)."),
    hardware: Optional[Path] = typer.Option(None, "--hardware", metavar="PROFILE",
                                            help="Run on the real rig described by this hardware profile YAML "
                                                 "(rig.hardware.runner)."),
    lubricant: Optional[str] = typer.Option(None, "--lubricant",
                                            help="Override the recipe's lubricant: dry, paraffin or boundary."),
    out: Optional[Path] = typer.Option(None, "--out", "-o",
                                       help="MCAP file to write (default out/<recipe name>.mcap); with "
                                            "trials > 1 the files are numbered NAME-01.mcap, NAME-02.mcap, ..."),
    profile_path: Optional[Path] = typer.Option(None, "--profile",
                                                help="Rig profile YAML for --sim (default: the recipe's "
                                                     "'profile', else config/rigs/sim.yaml)."),
    friction_model: Optional[Path] = typer.Option(None, "--friction-model", metavar="MODEL.yaml",
                                                  help="Friction model YAML (e.g. from `rig diagnose "
                                                       "--model-out`) replacing the profile's lubricant model."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (default: the recipe's); trial k "
                                                            "of several uses seed + k - 1."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    plan_only: bool = typer.Option(False, "--plan-only", help="Validate and compile the plan, print its "
                                                              "segment table, run nothing."),
):
    """Run a trial recipe on the simulated (--sim) or real (--hardware PROFILE) rig; log it to MCAP.

    Everything is checked before anything moves: the recipe (file, field, line
    in the error), the profile, the friction model, and the compiled reference
    against the stroke and the actuator's speed. Ctrl-C stops the run, finishes
    the MCAP with what was logged (status 'interrupted') and exits with 130.

    Exit status: 0 done; 2 bad input (nothing written); 1 failure while running; 130 interrupted.
    """
    from rig.log import TrialLogWriter
    from rig.recipe import LUBRICANTS, RecipeError, load_recipe
    from trajectories import PlanError, compile_recipe

    if sim == (hardware is not None) and not plan_only:
        _fail("choose exactly one of --sim or --hardware PROFILE")
    try:
        recipe = load_recipe(recipe_path)
    except RecipeError as exc:
        _fail(str(exc))
    if lubricant is not None:
        if lubricant not in LUBRICANTS:
            _fail(f"--lubricant {lubricant!r}: expected one of {', '.join(LUBRICANTS)}")
        recipe.lubricant = lubricant

    from rig.profile import ProfileError, default_profile_path, load_profile

    if hardware is not None:
        ppath = hardware
    else:
        ppath = profile_path or recipe.profile_path() or default_profile_path()
    try:
        profile = load_profile(ppath)
    except ProfileError as exc:
        _fail(str(exc))
    if recipe.lubricant not in profile.lubricants:
        _fail(f"{recipe_path}: lubricant {recipe.lubricant!r} is not in the profile {ppath} "
              f"(it has: {', '.join(profile.lubricants)})")
    fm = None
    if friction_model is not None:
        from rig.model.spec import FrictionModel
        try:
            fm = FrictionModel.from_yaml(friction_model)
        except FileNotFoundError:
            _fail(f"{friction_model}: no such file")
        except Exception as exc:  # pydantic / yaml
            _fail(f"{friction_model}: not a valid friction model: {exc}")
    try:
        plan = compile_recipe(recipe, profile)
    except PlanError as exc:
        _fail(f"{recipe_path}: {exc}")
    if plan_only:
        typer.echo(plan.summary())
        return

    run_hw = None
    aborted_types: tuple = (KeyboardInterrupt,)
    if hardware is not None:
        try:
            from rig.hardware import runner as hw_runner
        except ModuleNotFoundError as exc:
            if exc.name and (exc.name == "rig.hardware" or exc.name.startswith("rig.hardware.")):
                _fail("hardware support is not installed (rig.hardware.runner is missing); use --sim", EXIT_FAILURE)
            raise
        run_hw = getattr(hw_runner, "run_hardware_trial", None)
        if run_hw is None:
            _fail("rig.hardware.runner has no run_hardware_trial(); hardware support incomplete", EXIT_FAILURE)
        aborted = getattr(hw_runner, "HardwareTrialAborted", None)
        if isinstance(aborted, type):
            aborted_types = (KeyboardInterrupt, aborted)

    out = out or Path("out") / f"{recipe.name}.mcap"
    if out.suffix.lower() != ".mcap":
        _fail(f"--out {out}: the trial log is an MCAP file (use a .mcap name)")
    paths = _trial_paths(out, recipe.trials)
    base_seed = recipe.seed if seed is None else seed
    recipe_json = recipe.model_dump(mode="json")
    profile_json = _profile_dict(profile)
    git_commit = _git_describe()
    exit_code = 0
    for k, path in enumerate(paths):
        trial_seed = base_seed + k
        meta = {"recipe": recipe.name, "recipe_file": str(recipe_path), "lubricant": recipe.lubricant,
                "normal_force_N": recipe.normal_force_N, "seed": trial_seed, "trial": k + 1,
                "trials": len(paths), "profile": str(ppath), "profile_name": getattr(profile, "name", ""),
                "backend": "hardware" if hardware is not None else "sim",
                "friction_model": str(friction_model) if friction_model else f"profile:{recipe.lubricant}",
                "plan_duration_s": plan.duration_s, "git_commit": git_commit}
        if fm is not None:
            meta["friction_model_json"] = fm.model_dump_json()
        try:
            writer = TrialLogWriter(path, loop_rate_hz=plan.loop_rate_hz,
                                    decimated_rate_hz=recipe.log.decimated_rate_hz,
                                    raw_rate_hz=recipe.log.raw_rate_hz, metadata=meta,
                                    recipe_yaml=recipe.source_text, recipe=recipe_json, profile=profile_json,
                                    raw_encoding=recipe.log.raw_encoding, raw_dtype=recipe.log.raw_dtype)
        except OSError as exc:
            _fail(f"cannot write {path}: {exc.strerror or exc}", EXIT_FAILURE)
        title = f"trial {k + 1}/{len(paths)} " if len(paths) > 1 else ""
        status = "completed"
        result: dict = {}
        t0 = time.perf_counter()
        try:
            with TrialProgress(plan, title=title, enabled=not quiet) as prog:
                if run_hw is not None:
                    result = run_hw(plan, recipe, profile, writer, prog) or {}
                else:
                    result = run_sim_trial(plan, recipe, profile, writer, prog, friction_model=fm,
                                           seed=trial_seed, normal_force_N=recipe.normal_force_N)
        except aborted_types:
            status = "interrupted"
            exit_code = EXIT_INTERRUPTED
        except Exception as exc:  # a failure while running: keep what was logged
            status = "failed"
            exit_code = EXIT_FAILURE
            err_console.print(f"[bold red]error:[/] trial {k + 1} failed: {type(exc).__name__}: {exc}",
                              highlight=False)
        result.setdefault("wall_s", time.perf_counter() - t0)
        wall = result["wall_s"]
        try:
            writer.close(status, wall_s=wall, ticks_per_s=writer.ticks / wall if wall > 0 else 0.0,
                         realtime_factor=writer.last_t_s / wall if wall > 0 else 0.0,
                         tracking_error_rms_um=writer.tracking_error_rms_um,
                         mean_friction_N=writer.mean_friction_N, mean_abs_friction_N=writer.mean_abs_friction_N)
        except Exception as exc:  # e.g. disk full: the file cannot be finished
            _fail(f"cannot finish {path}: {exc}; `rig recover {path} --out FIXED.mcap` keeps what reached "
                  f"the disk", EXIT_FAILURE)
        console.print(_summary_table(result, writer, path, status))
        if exit_code:
            if status == "interrupted":
                err_console.print(f"interrupted: {path} holds what was logged (status 'interrupted')")
            raise typer.Exit(exit_code)


# ---------------------------------------------------------------------------
# info / export / import / recover
# ---------------------------------------------------------------------------

def info_command(
    path: Path = typer.Argument(..., help="Trial log (.mcap).", show_default=False, metavar="FILE.mcap"),
    events: int = typer.Option(20, "--events", "-n", help="How many events to list (0: none, -1: all)."),
    as_json: bool = typer.Option(False, "--json", help="Print everything as JSON instead of tables."),
):
    """Show a trial log: channels with message counts, duration, metadata, events, recovered or damaged."""
    from rig.data import DataFormatError
    from rig.log import trial_info

    try:
        info = trial_info(path)
    except DataFormatError as exc:
        _fail(str(exc))
    if as_json:
        typer.echo(json.dumps(info, indent=2, allow_nan=False, default=str))
        return
    state = "complete" if info["complete"] else f"DAMAGED/TRUNCATED ({info['damage']}) -- run `rig recover`"
    console.print(f"[bold]{info['path']}[/]  {info['size_bytes'] / 1e6:.2f} MB  {state}", highlight=False)
    rec = info["metadata"].get("recovery")
    if info["recovered"]:
        console.print(f"[yellow]recovered[/] from {rec.get('recovered_from')} "
                      f"(damage: {rec.get('recovery_error')}; {rec.get('messages')} messages kept)", highlight=False)
    else:
        console.print("recovered: no")
    dur = info["duration_s"]
    console.print(f"duration: {dur:.3f} s" if dur is not None else "duration: (no samples)")
    tab = Table(title="channels")
    for col in ("topic", "schema", "encoding", "messages"):
        tab.add_column(col)
    for c in info["channels"]:
        tab.add_row(c["topic"], c["schema"], c["encoding"], str(c["messages"]))
    console.print(tab)
    mt = Table(title="metadata")
    mt.add_column("record")
    mt.add_column("key")
    mt.add_column("value", overflow="fold")
    for name, rec_ in info["metadata"].items():
        for key, value in rec_.items():
            if key == "json" and len(value) > 80:
                value = value[:77] + "..."
            mt.add_row(name, key, value)
    console.print(mt)
    if info["attachments"]:
        console.print("attachments: " + ", ".join(f"{a['name']} ({a['bytes']} B)" for a in info["attachments"]))
    evs = info["events"]
    kinds: dict[str, int] = {}
    for e in evs:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    console.print(f"events: {len(evs)} (" + ", ".join(f"{k} {n}" for k, n in kinds.items()) + ")")
    shown = evs if events < 0 else evs[:events]
    for e in shown:
        rest = {k: v for k, v in e.items() if k not in ("t_s", "kind")}
        console.print(f"  {e['t_s']:10.3f} s  {e['kind']:<14} " + " ".join(
            f"{k}={(round(v, 4) if isinstance(v, float) else v)}" for k, v in rest.items()), highlight=False)
    if len(shown) < len(evs):
        console.print(f"  ... {len(evs) - len(shown)} more (--events -1 lists all)")


class Rate(str, Enum):
    raw = "raw"
    r25 = "25"


def export_command(
    path: Path = typer.Argument(..., help="Trial log (.mcap).", show_default=False, metavar="TRIAL.mcap"),
    csv: Path = typer.Option(..., "--csv", help="CSV file to write (measured-data format, version 1).",
                             show_default=False),
    rate: Rate = typer.Option(Rate.r25, "--rate", help="'25': the decimated per-sample channel (the paper's "
                                                       "25 Hz log); 'raw': every loop sample."),
    extra: bool = typer.Option(True, "--extra/--no-extra", help="Keep extra columns (raw: pid_*, dither, "
                                                                "true_*) after the standard ones."),
):
    """Export a trial log to the measured-data CSV (../shared/specs/measured-data.md), atomically.

    Columns: time_s, position_um, friction_N, normal_1_N, normal_2_N,
    position_ref_um, valve_cmd (those present), then extra columns; the trial's
    metadata (normal_force_N, lubricant, recipe, seed, ...) as '# key: value' lines.
    """
    from rig.data import DataFormatError, write_csv
    from rig.log import read_trial

    try:
        trial = read_trial(path, channel="raw" if rate == Rate.raw else "25hz")
    except DataFormatError as exc:
        _fail(str(exc))
    if not extra:
        trial.extra = {}
    try:
        write_csv(trial, csv)
    except OSError as exc:
        _fail(f"cannot write {csv}: {exc.strerror or exc}", EXIT_FAILURE)
    console.print(f"wrote {csv}: {len(trial)} rows, columns {', '.join(trial.columns())}", highlight=False)


def import_command(
    path: Path = typer.Argument(..., help="Measured-data CSV (version 1).", show_default=False, metavar="IN.csv"),
    out: Path = typer.Option(..., "--out", "-o", help="Trial log to write (.mcap).", show_default=False),
):
    """Import a measured-data CSV into a trial log (MCAP), atomically.

    Bad input (missing column, non-numeric value, time not increasing, NaN in a
    required column, empty data) is one error naming the file and the line,
    exit status 2, and no output file. A trailing partial line is a warning; the
    complete rows before it are imported. Every row goes to both the raw and
    the per-sample channel; the CSV metadata to the 'trial' metadata record.
    Exit status: 0 done, 2 bad input.
    """
    from rig.data import DataFormatError, PartialLineWarning, read_csv
    from rig.log import write_trial_data

    if out.suffix.lower() != ".mcap":
        _fail(f"--out {out}: the trial log is an MCAP file (use a .mcap name)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PartialLineWarning)
        try:
            trial = read_csv(path)
        except DataFormatError as exc:
            _fail(str(exc))
    for w in caught:
        if issubclass(w.category, PartialLineWarning):
            err_console.print(f"[yellow]warning:[/] {w.message}", highlight=False)
    try:
        write_trial_data(trial, out, extra_metadata={"imported_from": str(path)})
    except OSError as exc:
        _fail(f"cannot write {out}: {exc.strerror or exc}", EXIT_FAILURE)
    console.print(f"wrote {out}: {len(trial)} samples, columns {', '.join(trial.columns())}", highlight=False)


def recover_command(
    path: Path = typer.Argument(..., help="Damaged or truncated trial log (.mcap).", show_default=False,
                                metavar="FILE.mcap"),
    out: Path = typer.Option(..., "--out", "-o", help="Readable trial log to write (.mcap).", show_default=False),
):
    """Rewrite a truncated trial log (e.g. after a crash; no footer) into a readable one.

    Every complete chunk before the damaged point is kept; the new file carries a
    'recovery' metadata record (`rig info` shows it as recovered).
    """
    from rig.data import DataFormatError
    from rig.log import recover

    try:
        res = recover(path, out)
    except (DataFormatError, ValueError) as exc:
        _fail(str(exc))
    n = sum(res["messages"].values())
    what = "was complete" if res["complete_before"] else f"damaged at: {res['error'] or 'no footer'}"
    console.print(f"wrote {out}: {n} messages up to t = {res['last_t_s']:.3f} s ({path} {what})", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("run")(run_command)
    app.command("info")(info_command)
    app.command("export")(export_command)
    app.command("import")(import_command)
    app.command("recover")(recover_command)
