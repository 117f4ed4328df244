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

import time
from pathlib import Path
from typing import Any, Optional

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


def run_command(
    recipe_path: Path = typer.Argument(..., help="Recipe YAML (config/recipes/*.yaml).", show_default=False,
                                     metavar="RECIPE"),
    sim: bool = typer.Option(False, "--sim", help="Run on the simulated rig (rig.session.sim.SimBackend)."),
    hardware: Optional[Path] = typer.Option(None, "--hardware", metavar="PROFILE",
                                            help="Run on the real rig described by this hardware profile YAML "
                                                 "(rig.session.hardware.HardwareBackend)."),
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
    live: bool = typer.Option(False, "--live", help="Serve the running trial to Foxglove (Open connection -> "
                                                    "Foxglove WebSocket -> ws://127.0.0.1:8765): /log25, /events, "
                                                    "/loop_stats, as in the MCAP (rig.log.live)."),
    live_port: int = typer.Option(8765, "--live-port", min=0, max=65535, metavar="N",
                                  help="Port of the --live WebSocket server (0: any free port)."),
    live_host: str = typer.Option("127.0.0.1", "--live-host", metavar="HOST",
                                  help="Address the --live server binds to (0.0.0.0: every interface; the "
                                       "view has no authentication)."),
    pace: Optional[float] = typer.Option(None, "--pace", metavar="X",
                                         help="--sim: trial seconds per wall second (1 = real time, 10 = 10x, "
                                              "0 = as fast as possible). Default: 1 with --live, else 0."),
):
    """Run a trial recipe on the simulated (--sim) or real (--hardware PROFILE) rig; log it to MCAP.

    Everything is checked before anything moves: the recipe (file, field, line
    in the error), the profile, the friction model, and the compiled reference
    against the stroke and the actuator's speed. Ctrl-C stops the run, finishes
    the MCAP with what was logged (status 'interrupted') and exits with 130.

    Exit status: 0 done; 2 bad input (nothing written); 1 failure while running; 130 interrupted.
    """
    from rig.config.recipe import LUBRICANTS, RecipeError, compile_recipe, load_recipe
    from trajectories import PlanError

    if sim == (hardware is not None) and not plan_only:
        _fail("choose exactly one of --sim or --hardware PROFILE")
    if pace is not None and not (pace >= 0 and pace < float("inf")):
        _fail(f"--pace {pace:g}: expected a number >= 0 (1 = real time, 0 = as fast as possible)")
    if hardware is not None and pace not in (None, 1.0):
        _fail(f"--pace {pace:g}: the hardware runs in real time (--pace is for --sim)")
    if pace is None:
        pace = 1.0 if live else 0.0
    try:
        recipe = load_recipe(recipe_path)
    except RecipeError as exc:
        _fail(str(exc))
    if lubricant is not None:
        if lubricant not in LUBRICANTS:
            _fail(f"--lubricant {lubricant!r}: expected one of {', '.join(LUBRICANTS)}")
        recipe.lubricant = lubricant

    from rig.config.profile import ProfileError, default_profile_path, load_profile

    ppath = hardware if hardware is not None else (profile_path or recipe.profile_path() or default_profile_path())
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
        plan = compile_recipe(recipe, profile, friction_model=fm)
    except PlanError as exc:
        _fail(f"{recipe_path}: {exc}")
    if plan_only:
        typer.echo(plan.summary())
        return
    if hardware is not None:
        from drivers.config import HardwareConfigError, hardware_of_profile
        from rig.session.hardware import HardwareBackend

        try:
            hw = hardware_of_profile(profile, where=str(hardware))
        except HardwareConfigError as exc:
            _fail(str(exc))

    from rig.session.logfile import git_describe, run_to_log
    from rig.session.sim import SimBackend

    out = out or Path("out") / f"{recipe.name}.mcap"
    if out.suffix.lower() != ".mcap":
        _fail(f"--out {out}: the trial log is an MCAP file (use a .mcap name)")
    paths = _trial_paths(out, recipe.trials)
    view = None
    if live:
        from rig.log.live import LiveView, LiveViewError

        try:
            view = LiveView(live_host, live_port, name=f"rig run {recipe.name}")
        except LiveViewError as exc:
            _fail(f"--live: {exc}", EXIT_FAILURE)
        pace_txt = "" if hardware is not None else (f", pace {pace:g}x" if pace > 0 else ", unpaced")
        err_console.print(f"live view: {view.url} (Foxglove: Open connection -> Foxglove WebSocket; "
                          f"layout config/foxglove/rig-trial.json{pace_txt})", highlight=False, markup=False)
        _close_at_exit(view)
    base_seed = recipe.seed if seed is None else seed
    git_commit = git_describe()
    block_ticks = max(1, int(round(recipe.log.block_s * plan.loop_rate_hz)))
    for k, path in enumerate(paths):
        trial_seed = base_seed + k
        meta = {"recipe": recipe.name, "recipe_file": str(recipe_path), "lubricant": recipe.lubricant,
                "normal_force_N": recipe.normal_force_N, "seed": trial_seed, "trial": k + 1,
                "trials": len(paths), "profile": str(ppath), "profile_name": profile.name,
                "backend": "hardware" if hardware is not None else "sim",
                "friction_model": str(friction_model) if friction_model else f"profile:{recipe.lubricant}",
                "plan_duration_s": plan.duration_s, "git_commit": git_commit}
        if fm is not None:
            meta["friction_model_json"] = fm.model_dump_json()
        if hardware is not None:
            backend = HardwareBackend(hw, profile, lubricant=recipe.lubricant,
                                      normal_force_N=recipe.normal_force_N, seed=trial_seed)
        else:
            backend = SimBackend(profile, fm if fm is not None else profile.friction_model(recipe.lubricant),
                                 recipe.normal_force_N, trial_seed, block_ticks=block_ticks, pace=pace)
        title = f"trial {k + 1}/{len(paths)} " if len(paths) > 1 else ""
        try:
            with TrialProgress(plan, title=title, enabled=not quiet) as prog:
                result = run_to_log(path, plan, recipe, profile, backend, meta, progress=prog,
                                    echo=lambda text: err_console.print(text, highlight=False, markup=False),
                                    trial_fields={"normal_force_N": recipe.normal_force_N, "seed": trial_seed},
                                    on_open=view.attach if view is not None else None)
        except OSError as exc:
            _fail(f"cannot write {path}: {exc.strerror or exc}", EXIT_FAILURE)
        if result.close_error:
            _fail(f"cannot finish {path}: {result.close_error}; `rig recover {path} --out FIXED.mcap` keeps "
                  f"what reached the disk", EXIT_FAILURE)
        if result.status == "failed":
            err_console.print(f"[bold red]error:[/] trial {k + 1} failed: {result.reason}", highlight=False)
        console.print(_summary_table(result, path))
        if result.status == "interrupted":
            err_console.print(f"interrupted: {path} holds what was logged (status 'interrupted')")
            raise typer.Exit(EXIT_INTERRUPTED)
        if result.status == "failed":
            raise typer.Exit(EXIT_FAILURE)


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
