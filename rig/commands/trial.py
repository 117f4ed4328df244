"""Trial command: ``rig run`` (the log commands are in :mod:`rig.commands.logs`).

``rig run RECIPE --sim`` loads and validates the recipe (:mod:`rig.config.recipe`),
the rig profile and the friction model, compiles the reference
(:mod:`trajectories`) and checks it against the stroke and the actuator BEFORE
anything moves, then hands the plan to the trial session (:mod:`rig.session`)
on the simulated rig's backend (``--sim``) or the hardware's (``--hardware
PROFILE``, :class:`rig.session.hardware.HardwareBackend`), one MCAP per trial.

Exit status: 0 success; 2 bad input (recipe, profile, plan, CSV; nothing is
written); 1 a failure while running; 130 interrupted by Ctrl-C (the MCAP is
finished with what was logged and marked ``interrupted``).
"""

from __future__ import annotations

import datetime
import signal
import sys
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from rig.commands.common import (EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_FAILED, check_output_path, console,
                                 err_console, fail, warn)

EXIT_FAILURE = EXIT_FAILED
EXIT_INTERRUPTED = EXIT_ABORTED


#: log size of the raw 1 kHz channel (protobuf rig.LoopBlock) per second of trial, measured: 49-54 MB per hour
#: (a slow slide to the velocity steps, simulated, 1 MB chunks; docs/trial.md)
RAW_LOG_BYTES_PER_S_AT_1KHZ = 55e6 / 3600
#: the per-sample JSON channel (/log25) per message, measured
LOG25_BYTES_PER_SAMPLE = 40.0  # zstd-compressed JSON
#: past this estimated log size `rig run` asks before starting (--yes skips; without a terminal it warns)
LOG_SIZE_ASK_BYTES = 500e6
#: a trial longer than this gets its estimate printed
LONG_TRIAL_S = 600.0
#: the simulated rig's speed with the log, a conservative figure for the estimate (README: 440-1500x)
SIM_REALTIME_FACTOR = 400.0


# ---------------------------------------------------------------------------
# Progress reporting
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
        self._compiling = False

    def __enter__(self) -> "TrialProgress":
        self._t0 = time.perf_counter()
        if self.enabled:
            from rig.commands.warmup import SIM_KERNELS, cold_kernels
            from rig.jitstart import aot_in_use

            self._compiling = not aot_in_use() and cold_kernels(SIM_KERNELS)  # shown until the first block arrives
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
        if self._compiling:
            return (f"{self.title}compiling the simulation kernels (first run after an install or a change, "
                    "once; `rig warmup` does it ahead)")
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
        if self._compiling and self.t_s > 0:
            self._compiling = False
            self._last_draw = 0.0
        now = time.perf_counter()
        if now - self._last_draw >= 0.125:
            self._last_draw = now
            self._draw(self.t_s)

    __call__ = update


# ---------------------------------------------------------------------------
# rig run
# ---------------------------------------------------------------------------

def _summary_table(result, out: Path) -> Table:
    fig = result.figures
    ticks, wall, dur = result.ticks, result.wall_s, result.duration_s
    tab = Table(title=f"trial {result.status}: {out}", show_header=False, box=None)
    tab.add_row("simulated/trial time", f"{dur:.2f} s")
    tab.add_row("wall time", f"{wall:.2f} s")
    tab.add_row("loop ticks", f"{ticks} ({ticks / wall:,.0f} ticks/s, {dur / wall:.1f}x real time)"
                if wall and wall > 0 else str(ticks))
    tab.add_row("tracking error rms", f"{fig.tracking_error_rms_um:.3f} µm (max {fig.max_abs_err_um:.2f} µm)")
    tab.add_row("mean friction", f"{fig.mean_friction_N:.3f} N (mu {fig.mean_mu:.4f}); "
                                 f"mean |friction| {fig.mean_abs_friction_N:.3f} N")
    if result.status != "completed":
        tab.add_row("stopped", f"{result.cause}: {result.reason}")
    size = out.stat().st_size if out.exists() else 0
    tab.add_row("file written", f"{out} ({size / 1e6:.2f} MB)")
    return tab


def _trial_paths(out: Path, n: int) -> list[Path]:
    if n == 1:
        return [out]
    return [out.with_name(f"{out.stem}-{k + 1:02d}{out.suffix}") for k in range(n)]


def estimate_log(plan, recipe, hardware: bool) -> dict:
    """What a trial will cost before it starts: duration, log size, wall time (estimates)."""
    dur = float(plan.duration_s)
    raw = RAW_LOG_BYTES_PER_S_AT_1KHZ * dur * float(recipe.log.raw_rate_hz) / 1000.0
    dec = LOG25_BYTES_PER_SAMPLE * dur * float(recipe.log.decimated_rate_hz)
    wall = dur if hardware else dur / SIM_REALTIME_FACTOR
    return {"duration_s": dur, "log_bytes": raw + dec, "wall_s": wall}


def _human_s(t: float) -> str:
    if t < 1:
        return "under 1 s"
    if t < 120:
        return f"{t:.0f} s"
    if t < 7200:
        return f"{t / 60:.0f} min"
    return f"{t / 3600:.1f} h"


def _check_size(est: dict, n_trials: int, out: Path, yes: bool, hardware: bool) -> None:
    """Print the estimate of a long trial; past LOG_SIZE_ASK_BYTES ask (unless --yes) or warn (no terminal)."""
    total = est["log_bytes"] * n_trials
    if est["duration_s"] < LONG_TRIAL_S and total < LOG_SIZE_ASK_BYTES:
        return
    what = (f"{n_trials} trials of " if n_trials > 1 else "") + f"{_human_s(est['duration_s'])} of trial time"
    where = "on the rig" if hardware else f"about {_human_s(est['wall_s'] * n_trials)} on the simulated rig"
    text = (f"{what}: about {total / 1e6:,.0f} MB of log in {out.parent or Path('.')} ({where}; "
            f"~{RAW_LOG_BYTES_PER_S_AT_1KHZ * 3.6e3 / 1e6:.0f} MB per hour of 1 kHz raw data)")
    if total < LOG_SIZE_ASK_BYTES or yes:
        err_console.print(f"estimate: {text}", markup=False)
        return
    if not sys.stdin.isatty():
        warn(f"{text}; past {LOG_SIZE_ASK_BYTES / 1e6:.0f} MB (lower log.raw_rate_hz in the recipe to write less; "
             "--yes silences this)")
        return
    if not typer.confirm(f"{text}. Start?", default=False, err=True):
        fail("not started (answer was no; --yes skips the question)", EXIT_ABORTED)


class _SignalNote:
    """Ctrl-C / SIGTERM / SIGHUP noted for the whole of `rig run` (the session installs its own handlers for the
    run itself and restores these): a signal while the log is opened or finished is not lost, and a
    second signal then is not a traceback. ``caught``: names of the signals noted."""

    def __init__(self):
        self.caught: list[str] = []
        self._old: dict = {}

    def _note(self, signum, _frame) -> None:
        if signum == signal.SIGHUP:
            from rig.session.core import detach_from_terminal

            detach_from_terminal()
        self.caught.append(signal.Signals(signum).name)

    def __enter__(self) -> "_SignalNote":
        if threading.current_thread() is threading.main_thread():
            from rig.session.core import STOP_SIGNALS

            for sig in STOP_SIGNALS:
                self._old[sig] = signal.signal(sig, self._note)
        return self

    def __exit__(self, *exc) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)


def _load_friction_model(path: Path):
    """The friction model YAML of --friction-model; a recipe or a profile given instead is one clear error."""
    from rig.config.loader import ConfigError, load_model_yaml
    from rig.model.spec import FrictionModel

    try:
        return load_model_yaml(path, FrictionModel, key="friction_model", what="friction model")
    except ConfigError as exc:
        fail(f"--friction-model: {exc}")


# the options of `rig run` (module level: the command's signature stays one line a parameter)
_RUN_RECIPE_PATH = typer.Argument(..., help="Recipe YAML (config/recipes/*.yaml).", show_default=False,
                                metavar="RECIPE")
_RUN_SIM = typer.Option(False, "--sim", help="Run on the simulated rig (rig.session.sim.SimBackend).")
_RUN_HARDWARE = typer.Option(None, "--hardware", metavar="PROFILE",
                             help="Run on the real rig described by this hardware profile YAML "
                                  "(rig.session.hardware.HardwareBackend).")
_RUN_LUBRICANT = typer.Option(None, "--lubricant", metavar="NAME",
                              help="Override the recipe's lubricant: a name the profile maps to a "
                                   "friction model (dry, paraffin, boundary; its lubricant_map).")
_RUN_OUT = typer.Option(None, "--out", "-o", metavar="PATH",
                        help="MCAP file to write (default: a new out/<recipe name>/<UTC start>-"
                             "<trial id>.mcap per trial); with trials > 1 the files are numbered "
                             "NAME-01.mcap, NAME-02.mcap, ... An existing file is exit 2.")
_RUN_OVERWRITE = typer.Option(False, "--overwrite", help="Replace an existing --out file (a trial log is "
                                                         "never overwritten otherwise).")
_RUN_SPECIMEN = typer.Option(None, "--specimen", metavar="ID", help="The test piece (specimen) "
                                                                   "of this trial; overrides the recipe's metadata.")
_RUN_OPERATOR = typer.Option(None, "--operator", metavar="NAME", help="Who ran the trial.")
_RUN_NOTE = typer.Option(None, "--note", metavar="TEXT", help="A note for the trial record.")
_RUN_MD = typer.Option(None, "--md", metavar="KEY=VALUE", help="Any metadata of the lab "
                                                              "(repeatable); overrides the recipe's metadata block.")
_RUN_ALLOW_EXPIRED_CALIBRATION = typer.Option(False, "--allow-expired-calibration",
                                              help="--hardware: run although a calibration is past its "
                                                   "due date or a shunt check drifted (logged as an event).")
_RUN_PROFILE_PATH = typer.Option(None, "--profile", metavar="PROFILE",
                                 help="Rig profile YAML for --sim (default: the recipe's "
                                      "'profile', else config/rigs/sim.yaml).")
_RUN_FRICTION_MODEL = typer.Option(None, "--friction-model", metavar="MODEL.yaml",
                                   help="Friction model YAML (e.g. from `rig diagnose "
                                        "--model-out`) replacing the profile's lubricant model.")
_RUN_SEED = typer.Option(None, "--seed", min=0, max=2**32 - 1001, metavar="N",
                         help="Random seed, 0 or more (default: the recipe's); trial k of "
                              "several uses seed + k - 1.")
_RUN_QUIET = typer.Option(False, "--quiet", "-q", help="No progress bar.")
_RUN_PLAN_ONLY = typer.Option(False, "--plan-only", help="Validate and compile the plan, print its "
                                                         "segment table, run nothing.")
_RUN_LIVE = typer.Option(False, "--live", help="Serve the running trial to Foxglove (Open connection -> "
                                               "Foxglove WebSocket -> ws://127.0.0.1:8765): /log25, /events, "
                                               "/loop_stats, as in the MCAP (rig.log.live).")
_RUN_LIVE_PORT = typer.Option(8765, "--live-port", min=0, max=65535, metavar="N",
                              help="Port of the --live WebSocket server (0: any free port).")
_RUN_LIVE_HOST = typer.Option("127.0.0.1", "--live-host", metavar="HOST",
                              help="Address the --live server binds to (0.0.0.0: every interface; the "
                                   "view has no authentication).")
_RUN_PACE = typer.Option(None, "--pace", metavar="X",
                         help="--sim: trial seconds per wall second (1 = real time, 10 = 10x, "
                              "0 = as fast as possible). Default: 1 with --live, else 0.")
_RUN_YES = typer.Option(False, "--yes", "-y", help="Start a trial whose log is estimated past "
                                                   f"{LOG_SIZE_ASK_BYTES / 1e6:.0f} MB without asking.")


def run_command(
    recipe_path: Path = _RUN_RECIPE_PATH,
    sim: bool = _RUN_SIM,
    hardware: Optional[Path] = _RUN_HARDWARE,
    lubricant: Optional[str] = _RUN_LUBRICANT,
    out: Optional[Path] = _RUN_OUT,
    overwrite: bool = _RUN_OVERWRITE,
    specimen: Optional[str] = _RUN_SPECIMEN,
    operator: Optional[str] = _RUN_OPERATOR,
    note: Optional[str] = _RUN_NOTE,
    md: Optional[list[str]] = _RUN_MD,
    allow_expired_calibration: bool = _RUN_ALLOW_EXPIRED_CALIBRATION,
    profile_path: Optional[Path] = _RUN_PROFILE_PATH,
    friction_model: Optional[Path] = _RUN_FRICTION_MODEL,
    seed: Optional[int] = _RUN_SEED,
    quiet: bool = _RUN_QUIET,
    plan_only: bool = _RUN_PLAN_ONLY,
    live: bool = _RUN_LIVE,
    live_port: int = _RUN_LIVE_PORT,
    live_host: str = _RUN_LIVE_HOST,
    pace: Optional[float] = _RUN_PACE,
    yes: bool = _RUN_YES,
):
    """Run a trial recipe on the simulated (--sim) or real (--hardware PROFILE) rig; log it to MCAP.

    Everything is checked before anything moves: the recipe (file, field, line
    in the error), the profile, the friction model, and the compiled reference
    against the stroke and the actuator's speed. A trial longer than 10 min gets
    an estimate of its log size and duration first; past 500 MB `rig run` asks
    (--yes skips). Ctrl-C stops the run, finishes the MCAP with what was logged
    (status 'interrupted') and exits with 130.

    Exit status: 0 done; 2 bad input (nothing written); 1 failure while running; 130 interrupted.
    """
    pace = _check_flags(sim, hardware, pace, live, out, plan_only)
    aot_why = _prefer_aot() if sim and not plan_only else None
    inp = _resolve_inputs(recipe_path, lubricant, hardware, profile_path, friction_model,
                          _metadata_flags(specimen, operator, note, md or []), plan_only)
    if plan_only:
        _print_plan(inp)
        return
    hw = _hardware_config(inp)
    paths = _output_paths(out, overwrite, inp.recipe.trials)
    calib_events = _check_calibration(hw, allow_expired_calibration) if hw is not None else []
    view = _start_live(inp, live, live_host, live_port, pace) if live else None
    base_seed = inp.recipe.seed if seed is None else seed
    if base_seed + len(paths) - 1 > 2**32 - 1:
        fail(f"--seed {seed}: seed + trials - 1 must stay below 2**32")
    _check_size(estimate_log(inp.plan, inp.recipe, hw is not None), len(paths),
                out or Path("out") / inp.recipe.name / "x.mcap", yes, hw is not None)
    _run_trials(inp, hw, paths, base_seed, calib_events, view, overwrite=overwrite, quiet=quiet, pace=pace,
                allow_expired_calibration=allow_expired_calibration)
    if aot_why is not None:
        _aot_note(aot_why)


def _prefer_aot() -> str | None:
    """The simulation's and log's kernels from the ahead-of-time module (rig.jitstart; numba is then not
    imported: about 0.5 s less start-up), before anything imports them. None when used, else why not."""
    from rig.jitstart import prefer_aot

    return prefer_aot()


def _aot_note(why: str) -> None:
    """Say why this run used numba's JIT kernels; when the ahead-of-time module is not built for these
    sources, start its build in the background (once; later runs load it)."""
    from rig.jitstart import start_aot_build

    if why in ("RIG_AOT=0", "numba is loaded"):
        return
    if why == "not built yet":
        if start_aot_build():
            err_console.print("compiling the run's kernels ahead of time in the background (once after an install "
                              "or a change; later runs start about 0.5 s faster)", markup=False)
        return
    err_console.print(f"the run's ahead-of-time kernels: {why}; numba's JIT kernels were used", markup=False)


def _run_trials(inp: "_Inputs", hw, paths: list, base_seed: int, calib_events: list, view, *, overwrite: bool,
                quiet: bool, pace: float, allow_expired_calibration: bool) -> None:
    """Every trial of the recipe, one log each (trial k: seed + k - 1); a signal between two trials
    starts no further one; the emulated devices (--hardware) are new for every trial."""
    from rig.session.logfile import git_describe

    git_commit = git_describe()
    with _SignalNote() as sig_note, _Emulators() as emulators:
        for k, path in enumerate(paths):
            if sig_note.caught:
                err_console.print(f"interrupted ({sig_note.caught[0]}) before trial {k + 1}: not started",
                                  markup=False)
                raise typer.Exit(EXIT_INTERRUPTED)
            trial_seed = base_seed + k
            uid = str(uuid.uuid4())
            path = path or default_trial_path(inp.recipe.name, uid)
            meta = _trial_metadata(inp, hw, uid=uid, seed=trial_seed, k=k, n=len(paths), git_commit=git_commit)
            emulators.stop()
            events = list(calib_events)
            emu = None
            if hw is not None:
                # the emulated devices are started here (not by the backend) so that the shunt check of the
                # load cells runs against them before anything moves
                emu = emulators.start(hw, inp.profile, lubricant=inp.recipe.lubricant if inp.lub_key else None,
                                      normal_force_N=inp.recipe.normal_force_N, seed=trial_seed)
                if k == 0:
                    calib_events = events = events + _check_shunt(emu.hw if emu is not None else hw,
                                                                  allow_expired_calibration)
            backend = _make_backend(inp, hw, emu, trial_seed, k, pace)
            title = f"trial {k + 1}/{len(paths)} " if len(paths) > 1 else ""
            if overwrite and (path.exists() or path.is_symlink()):  # only now: every check before has passed
                try:
                    path.unlink()
                except OSError as exc:
                    fail(f"--overwrite: cannot remove {path}: {exc.strerror or exc}", EXIT_FAILURE)
            result = _run_one(inp, path, backend, meta, title, quiet, trial_seed, _on_open(view, events))
            _report(result, path, k, sig_note)


@dataclass
class _Inputs:
    """What `rig run` resolved from its arguments before anything moves."""

    recipe: Any                 # the recipe, with --lubricant applied
    recipe_path: Path
    profile: Any                # the rig profile, and its path
    ppath: Path
    fm: Any                     # the friction model of --friction-model (None: the profile's), its path
    fm_path: Path | None
    lub_key: str | None         # the profile's key of the recipe's lubricant (None: not mapped)
    plan: Any                   # the compiled plan
    trial_md: dict              # the trial's metadata: the recipe's, then the flags'
    hardware: Path | None       # --hardware's profile (None: --sim)


def _check_flags(sim: bool, hardware: Path | None, pace: float | None, live: bool, out: Path | None,
                 plan_only: bool) -> float:
    """The flags that need no file: exit 2 naming the flag. Returns the pace (default: 1 with --live)."""
    if sim == (hardware is not None) and not plan_only:
        fail("choose exactly one of --sim or --hardware PROFILE")
    if pace is not None and not (pace >= 0 and pace < float("inf")):
        fail(f"--pace {pace:g}: expected a number >= 0 (1 = real time, 0 = as fast as possible)")
    if hardware is not None and pace not in (None, 1.0):
        fail(f"--pace {pace:g}: the hardware runs in real time (--pace is for --sim)")
    if out is not None:
        check_output_path(out, "--out", (".mcap",))
    return (1.0 if live else 0.0) if pace is None else pace


def _load_recipe(recipe_path: Path, lubricant: str | None):
    """The recipe, on ``--lubricant`` when given (its wording follows: :meth:`Recipe.with_lubricant`)."""
    from rig.config.recipe import RecipeError, load_recipe

    try:
        recipe = load_recipe(recipe_path)
    except RecipeError as exc:
        fail(str(exc))
    if lubricant is None:
        return recipe
    try:
        return recipe.with_lubricant(lubricant)
    except ValueError:
        fail(f"--lubricant {lubricant!r}: expected a lubricant name (one line of printable text, "
             "up to 100 characters)")


def _resolve_inputs(recipe_path: Path, lubricant: str | None, hardware: Path | None, profile_path: Path | None,
                    friction_model: Path | None, flags_md: dict, plan_only: bool) -> _Inputs:
    """Recipe, profile, required metadata, friction model and the compiled plan: every check before
    anything moves (exit 2 naming the file and what is wrong)."""
    from rig.config.profile import ProfileError, default_profile_path, load_profile
    from rig.config.recipe import compile_recipe
    from trajectories import PlanError

    recipe = _load_recipe(recipe_path, lubricant)
    trial_md = {**recipe.metadata, **flags_md}
    ppath = hardware if hardware is not None else (profile_path or recipe.profile_path() or default_profile_path())
    try:
        profile = load_profile(ppath)
    except ProfileError as exc:
        fail(str(exc))
    missing = [k for k in profile.required_metadata if not str(trial_md.get(k, "")).strip()]
    if missing:
        fail(f"{ppath}: the profile requires trial metadata {', '.join(missing)}: give "
             + " ".join(f"--{k} ..." if k in ("specimen", "operator", "note") else f"--md {k}=..." for k in missing)
             + f" or set them in the recipe's metadata block ({recipe_path}); nothing was run")
    fm = _load_friction_model(friction_model) if friction_model is not None else None
    lub_key = profile.lubricant_key(recipe.lubricant)
    plan_fm = fm
    if lub_key is None and fm is None:
        if hardware is None:
            where = "--lubricant" if lubricant is not None else f"{recipe_path}: lubricant"
            fail(f"{where} {recipe.lubricant!r} has no friction model in the profile {ppath} "
                 f"(it has: {', '.join(profile.lubricant_names())}; map a lab's name to one with the profile's "
                 "lubricant_map, or give --friction-model)")
        # the real rig runs any lubricant; the plan's run-up takes the longest slip length the profile knows
        plan_fm = profile.friction_model(max(profile.lubricants, key=lambda k: profile.lubricants[k].L_um))
    try:
        plan = compile_recipe(recipe, profile, friction_model=plan_fm)
    except PlanError as exc:
        fail(f"{recipe_path}: {exc}")
    if lub_key is None and fm is None and not plan_only:
        note_ff = ""
        if plan.controller.get("friction_ff"):
            plan.controller["friction_ff"] = False
            note_ff = "; friction feed-forward off"
        warn(f"lubricant {recipe.lubricant!r} is not mapped to a friction model in {ppath}: run-ups sized for the "
             f"longest slip length the profile knows{note_ff}")
    return _Inputs(recipe=recipe, recipe_path=recipe_path, profile=profile, ppath=ppath, fm=fm,
                   fm_path=friction_model, lub_key=lub_key, plan=plan, trial_md=trial_md, hardware=hardware)


def _print_plan(inp: _Inputs) -> None:
    """--plan-only: the segment table and the log's estimate."""
    typer.echo(inp.plan.summary())
    hardware = inp.hardware is not None
    est = estimate_log(inp.plan, inp.recipe, hardware)
    typer.echo(f"estimate: about {est['log_bytes'] * inp.recipe.trials / 1e6:,.1f} MB of log for "
               f"{inp.recipe.trials} trial(s) of {_human_s(est['duration_s'])}"
               + ("" if hardware else f"; about {_human_s(est['wall_s'])} each on the simulated rig"))


def _hardware_config(inp: _Inputs):
    """The profile's typed hardware section for --hardware (exit 2 naming the field), None for --sim."""
    if inp.hardware is None:
        return None
    from drivers.config import HardwareConfigError, hardware_of_profile

    try:
        return hardware_of_profile(inp.profile, where=str(inp.hardware))
    except HardwareConfigError as exc:
        fail(str(exc))


def _output_paths(out: Path | None, overwrite: bool, trials: int) -> list[Path | None]:
    """One log path per trial (None: the default, new per trial); an existing --out is exit 2 unless
    --overwrite."""
    if out is None:
        return [None] * trials
    paths: list[Path | None] = _trial_paths(out, trials)
    taken = [p for p in paths if p.exists() or p.is_symlink()]
    if taken and not overwrite:
        fail(f"--out {taken[0]}: exists; a trial log is never overwritten (--overwrite replaces it, or give "
             "another name; without --out each trial gets a new file)")
    return paths


def _start_live(inp: _Inputs, live: bool, host: str, port: int, pace: float):
    """--live: the Foxglove view, closed when the command ends (a port in use: exit 1)."""
    from rig.log.live import LiveView, LiveViewError

    try:
        view = LiveView(host, port, name=f"rig run {inp.recipe.name}")
    except LiveViewError as exc:
        fail(f"--live: {exc}", EXIT_FAILURE)
    pace_txt = "" if inp.hardware is not None else (f", pace {pace:g}x" if pace > 0 else ", unpaced")
    err_console.print(f"live view: {view.url} (Foxglove: Open connection -> Foxglove WebSocket; "
                      f"layout config/foxglove/rig-trial.json{pace_txt})", highlight=False, markup=False)
    _close_at_exit(view)
    return view


def _trial_metadata(inp: _Inputs, hw, *, uid: str, seed: int, k: int, n: int, git_commit: str) -> dict:
    """The trial record's metadata (docs/trial.md): who and what, the recipe, profile, model, seed."""
    recipe = inp.recipe
    meta = {"trial_uid": uid, "recipe": recipe.name, "recipe_file": str(inp.recipe_path),
            "lubricant": recipe.lubricant, "normal_force_N": recipe.normal_force_N, "seed": seed, "trial": k + 1,
            "trials": n, "profile": str(inp.ppath), "profile_name": inp.profile.name,
            "backend": "hardware" if hw is not None else "sim",
            "friction_model": str(inp.fm_path) if inp.fm_path else f"profile:{recipe.lubricant}",
            "plan_duration_s": inp.plan.duration_s, "git_commit": git_commit}
    if inp.fm is not None:
        meta["friction_model_json"] = inp.fm.model_dump_json()
    if inp.lub_key is not None and inp.lub_key != recipe.lubricant:
        meta["lubricant_model"] = inp.lub_key
    meta.update(inp.trial_md)
    if hw is not None:
        meta["calibration"] = calibration_snapshot(hw)
    return meta


def _make_backend(inp: _Inputs, hw, emu, seed: int, k: int, pace: float):
    """The trial's backend: the hardware's (``hw``, the emulated devices ``emu``) or the simulated rig's."""
    recipe = inp.recipe
    try:
        if hw is not None:
            from rig.session.hardware import HardwareBackend

            return HardwareBackend(hw, inp.profile, lubricant=recipe.lubricant if inp.lub_key else None,
                                   normal_force_N=recipe.normal_force_N, seed=seed, emulator=emu)
        from rig.session.sim import SimBackend

        model = inp.fm if inp.fm is not None else inp.profile.friction_model(recipe.lubricant)
        block_ticks = max(1, int(round(recipe.log.block_s * inp.plan.loop_rate_hz)))
        return SimBackend(inp.profile, model, recipe.normal_force_N, seed, block_ticks=block_ticks, pace=pace)
    except ValueError as exc:  # e.g. a seed numpy cannot take: bad input, nothing written yet
        fail(f"{inp.recipe_path}: trial {k + 1} (seed {seed}): {exc}")


def _run_one(inp: _Inputs, path: Path, backend, meta: dict, title: str, quiet: bool, seed: int, on_open):
    """One trial into ``path`` with the progress bar; a log that cannot be written or finished is exit 1."""
    from rig.session.logfile import run_to_log

    try:
        with TrialProgress(inp.plan, title=title, enabled=not quiet) as prog:
            result = run_to_log(path, inp.plan, inp.recipe, inp.profile, backend, meta, progress=prog,
                                echo=lambda text: err_console.print(text, highlight=False, markup=False),
                                trial_fields={"normal_force_N": inp.recipe.normal_force_N, "seed": seed},
                                on_open=on_open)
    except FileExistsError:
        fail(f"{path}: appeared while the trial was being prepared; a trial log is never overwritten",
             EXIT_FAILURE)
    except OSError as exc:
        fail(f"cannot write {path}: {exc.strerror or exc}", EXIT_FAILURE)
    if result.close_error:
        fail(f"cannot finish {path}: {result.close_error}; `rig recover {path} --out FIXED.mcap` keeps "
             f"what reached the disk", EXIT_FAILURE)
    return result


def _report(result, path: Path, k: int, sig_note: "_SignalNote") -> None:
    """The trial's summary table; a failed trial is exit 1, an interrupted one (or a signal while its log
    was finished) exit 130."""
    if result.status == "failed":
        err_console.print(f"[bold red]error:[/] trial {k + 1} failed: {result.reason}", highlight=False)
    console.print(_summary_table(result, path))
    if result.status == "interrupted":
        err_console.print(f"interrupted: {path} holds what was logged (status 'interrupted')", markup=False)
        raise typer.Exit(EXIT_INTERRUPTED)
    if result.status == "failed":
        raise typer.Exit(EXIT_FAILURE)
    if sig_note.caught:  # arrived while the log was being opened or finished: the trial itself completed
        err_console.print(f"interrupted ({sig_note.caught[0]}) while {path} was being finished: it holds the "
                          "complete trial (status 'completed'); no further trial started", markup=False)
        raise typer.Exit(EXIT_INTERRUPTED)


def default_trial_path(recipe_name: str, uid: str, when: datetime.datetime | None = None) -> Path:
    """A trial's default log: ``out/<recipe name>/<UTC start, YYYYmmddTHHMMSSZ>-<first 8 of the trial id>.mcap``
    (new for every trial: created with O_EXCL, never overwriting one)."""
    when = when or datetime.datetime.now(datetime.timezone.utc)
    return Path("out") / recipe_name / f"{when.strftime('%Y%m%dT%H%M%SZ')}-{uid[:8]}.mcap"


def _metadata_flags(specimen, operator, note, md: list[str]) -> dict[str, str]:
    """--specimen/--operator/--note/--md KEY=VALUE as one dict (bad input: exit 2 naming the flag)."""
    import re

    from rig.config.recipe import METADATA_KEY, RESERVED_METADATA

    out: dict[str, str] = {}
    for item in md:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not re.match(METADATA_KEY, key):
            fail(f"--md {item!r}: expected KEY=VALUE with KEY of letters, digits, '_', '.', '-' (starting with a "
                 "letter or '_')")
        if key in RESERVED_METADATA:
            fail(f"--md {key}: set by rig itself")
        out[key] = value.strip()
    for name, value in (("specimen", specimen), ("operator", operator), ("note", note)):
        if value is not None:
            out[name] = value.strip()
    for key, value in out.items():
        if "\n" in value or "\r" in value or len(value) > 2000:
            fail(f"metadata {key}: one line of at most 2000 characters")
    return out


def calibration_snapshot(hw) -> str:
    """Every channel's calibration record of the profile's hardware section, as JSON (the MCAP's trial
    record keeps it: which load cell, calibrated when, within which range, produced the trial)."""
    import json

    from drivers.config import calibration_records

    return json.dumps({ch: (cal.model_dump(mode="json", by_alias=True, exclude_none=True) if cal is not None else None)
                       for ch, cal in calibration_records(hw).items()}, sort_keys=True)


def _check_calibration(hw, allow: bool) -> list[tuple[str, dict]]:
    """Refuse (exit 2, naming the channel and the date) a calibration past its due date; with
    ``allow`` the run goes on and the events to log are returned."""
    from drivers.config import calibration_problems

    problems = calibration_problems(hw, datetime.date.today())
    if problems and not allow:
        fail(f"{problems[0]['message']}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")
             + "; recalibrate (`rig calibrate verify --hardware PROFILE`) or run with --allow-expired-calibration "
               "(logged); nothing was run")
    for p in problems:
        warn(f"{p['message']}: running anyway (--allow-expired-calibration; logged)")
    return [("calibration_expired", p) for p in problems]


class _Emulators:
    """The emulated devices of a --hardware trial (when the profile's emulators.autostart): one set per trial,
    stopped before the next starts and when the command ends, however it ends."""

    def __init__(self):
        self.handle = None

    def start(self, hw, profile, **kw):
        if not hw.emulators.autostart:
            return None
        from rig.hardware.emulated import EmulatorError, start_emulator_process

        try:
            self.handle = start_emulator_process(hw, profile, **kw)
        except EmulatorError as exc:
            fail(f"the emulated devices did not start: {exc}", EXIT_FAILURE)
        return self.handle

    def stop(self) -> None:
        if self.handle is not None:
            self.handle.stop()
            self.handle = None

    def __enter__(self) -> "_Emulators":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _check_shunt(hw, allow: bool) -> list[tuple[str, dict]]:
    """The load cells' shunt check before a --hardware trial (channels with a shunt register and a reference):
    a drifted bridge is exit 2 naming the channel (``--allow-expired-calibration``: an event instead)."""
    from rig.commands.calibrate import shunt_configured, shunt_rows

    if not shunt_configured(hw):
        return []
    from drivers.errors import DeviceError

    try:
        rows = shunt_rows(hw)
    except DeviceError as exc:
        fail(f"shunt check before the trial: {exc}", EXIT_FAILURE)
    today = datetime.date.today().isoformat()
    bad = [r for r in rows if r["ok"] is False]
    events = []
    for r in bad:
        dev = r["deviation_fraction"]
        msg = (f"hardware.loadcells.{r['channel']}: shunt check of {r['serial']} on {today} drifted "
               + (f"{dev * 100:+.3f} %" if dev is not None else "(no reading)")
               + f" (tolerance ±{r['tolerance_fraction'] * 100:.3f} %)")
        if not allow:
            fail(msg + "; recalibrate (`rig calibrate verify --hardware PROFILE`) or run with "
                       "--allow-expired-calibration (logged); nothing was run")
        warn(msg + ": running anyway (--allow-expired-calibration; logged)")
        events.append(("calibration_shunt_drift", {"channel": r["channel"], "serial": r["serial"], "date": today,
                                                   "deviation_fraction": dev, "message": msg}))
    return events


def _on_open(view, events: list[tuple[str, dict]]):
    """What runs once the log is open: the calibration events (--allow-expired-calibration), the live view."""
    if not events and view is None:
        return None

    def on_open(writer) -> None:
        for kind, data in events:
            writer.event(0.0, kind, **data)
        if view is not None:
            view.attach(writer)
    return on_open


def _close_at_exit(view) -> None:
    """Stop the live view when the command ends, however it ends (normally, typer.Exit, an error)."""
    import click

    def close() -> None:
        view.close()
        if view.dropped:
            err_console.print(f"live view: {view.dropped} updates dropped (the publisher fell behind; the log "
                              f"has everything)", highlight=False, markup=False)

    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        ctx.call_on_close(close)
    else:  # called as a function, outside the CLI
        import atexit

        atexit.register(close)


def register(app: typer.Typer) -> None:
    app.command("run")(run_command)
