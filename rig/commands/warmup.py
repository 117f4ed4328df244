"""``rig warmup``: compile the numba kernels ahead, so that the first real command is not the slow one.

numba compiles a kernel the first time it is called and caches the machine
code beside the source (``__pycache__``, ``cache=True``); every later process
loads it from there. Each command compiles only what it calls, so the first
``rig run`` pays for the simulation kernels and the first ``rig identify`` for
the identification kernels. pip cannot run code at install time, hence this
command: it runs a short simulated trial (logged to a temporary file, so the
log's kernels compile too) and identifies a synthetic velocity-step record (and,
with ``--all``, diagnoses it), writing nothing but the cache, and builds the run
path's kernels ahead of time (:func:`rig.jitstart.build_aot`). The groups compile
in parallel processes (numba compiles in one thread per process), one per core.

:func:`cold_kernels` tells a command whether its first call will compile, so
that its progress display can say so.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import typer

from rig.commands.common import EXIT_FAILED, console, fail

_RIG = Path(__file__).resolve().parents[1]
#: the modules whose numba kernels each command compiles on its first call
SIM_KERNELS = ("sim/plant.py", "control.py", "model/friction.py", "model/sensors.py", "log/figures.py",
               "log/loopblock.py", "log/kernels.py")
IDENTIFY_KERNELS = ("kinematics/velocity.py", "kinematics/steps.py", "model/forward.py", "model/loading.py",
                    "model/friction.py", "model/sensors.py")


def cold_kernels(modules) -> bool:
    """True when one of these modules (paths under rig/) has no numba cache newer than its source: its
    kernels will compile on first use (seconds), so a progress display should say so."""
    for rel in modules:
        src = _RIG / rel
        try:
            t_src = src.stat().st_mtime
            cached = [f for f in (src.parent / "__pycache__").glob(f"{src.stem}.*.nbi")]
        except OSError:
            return True
        if not cached or max(f.stat().st_mtime for f in cached) < t_src:
            return True
    return False


def _warm_simulation() -> float:
    """The simulation, controller and log kernels: the smoke recipe simulated and logged to a temp file."""
    import tempfile

    from rig.config.profile import default_profile_path, load_profile
    from rig.config.recipe import load_recipe
    from rig.log import TrialLogWriter
    from rig.session.sim import simulate

    t0 = time.perf_counter()
    recipe = load_recipe(_RIG.parent / "config" / "recipes" / "smoke.yaml")
    profile = load_profile(recipe.profile_path() or default_profile_path())
    log, _ = simulate(recipe, profile)
    with tempfile.TemporaryDirectory() as tmp:
        w = TrialLogWriter(Path(tmp) / "warmup.mcap", threaded=False, fsync=False)
        w.warm_up()
        for b in log.blocks[:2]:
            w.write_block(b)
        w.close()
    return time.perf_counter() - t0


def _build_run_kernels() -> float:
    """The run path's kernels ahead of time (rig.jitstart.build_aot: numba.pycc; `rig run --sim` then loads
    them without numba). Nothing to do when they are built for these sources."""
    from rig.jitstart import build_aot_once

    t0 = time.perf_counter()
    build_aot_once()  # or waits for a `rig run --sim`'s build in the background
    return time.perf_counter() - t0


def _synthetic_steps():
    """A synthetic record of the paper's velocity steps (boundary lubricant, one 1 -> 5 µm/s step)."""
    from rig.config.profile import default_profile_path, load_profile
    from rig.sim.synth import generate, paper_step_protocol

    profile = load_profile(default_profile_path())
    return generate(profile.friction_model("boundary"), paper_step_protocol(highs=(5.0,)), seed=0).trial


def _warm_identification() -> float:
    """The identification kernels, on a synthetic record of the paper's velocity steps."""
    from rig.analysis.identify import identify_trials

    t0 = time.perf_counter()
    try:
        identify_trials([_synthetic_steps()], names=["warmup"], whole_record=True, stiffness=True)
    except ValueError:
        pass  # a short record may have too little to fit: the kernels are compiled all the same
    return time.perf_counter() - t0


def _warm_diagnosis() -> float:
    """The diagnosis kernels, on the same synthetic record."""
    from rig.diagnosis import diagnose

    t0 = time.perf_counter()
    try:
        diagnose(_synthetic_steps())
    except ValueError:
        pass
    return time.perf_counter() - t0


def warmup_command(
    all_: bool = typer.Option(False, "--all", help="Also the diagnosis kernels (slower)."),
):
    """Compile the simulation and identification kernels (numba) now; later commands start fast.

    Writes nothing but numba's cache (beside the sources) and the run's kernels
    compiled ahead of time (`rig run --sim` loads them without numba; a C
    compiler is needed, else the run uses numba's JIT). Run it once after
    installing; running it again is quick (everything is cached).
    """
    from concurrent.futures import ProcessPoolExecutor

    t0 = time.perf_counter()
    jobs = {"simulation": _warm_simulation, "identification": _warm_identification,
            "run (ahead of time)": _build_run_kernels}
    if all_:
        jobs["diagnosis"] = _warm_diagnosis
    workers = max(1, min(len(jobs), os.cpu_count() or 1))
    done: dict[str, float] = {}
    try:
        with console.status(f"compiling the {', '.join(jobs)} kernels in {workers} process(es)..."):
            if workers == 1:
                done = {name: fn() for name, fn in jobs.items()}
            else:
                with ProcessPoolExecutor(max_workers=workers) as pool:
                    futures = {name: pool.submit(fn) for name, fn in jobs.items()}
                    done = {name: f.result() for name, f in futures.items()}
    except Exception as exc:  # noqa: BLE001 - a broken install: say what is missing
        fail(f"warmup failed: {type(exc).__name__}: {exc}", EXIT_FAILED)
    parts = ", ".join(f"{name} {t:.1f} s" for name, t in done.items())
    console.print(f"warm in {time.perf_counter() - t0:.1f} s ({parts}, {workers} in parallel; numba's cache is "
                  "beside the sources; later commands load it)", markup=False)


def register(app: typer.Typer) -> None:
    app.command("warmup")(warmup_command)
