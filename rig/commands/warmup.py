"""``rig warmup``: compile the numba kernels ahead, so that the first real command is not the slow one.

numba compiles a kernel the first time it is called and caches the machine
code beside the source (``__pycache__``, ``cache=True``); every later process
loads it from there. Each command compiles only what it calls, so the first
``rig run`` pays for the simulation kernels and the first ``rig identify`` for
the identification kernels. pip cannot run code at install time, hence this
command: it runs a short simulated trial in memory and identifies it (and,
with ``--all``, diagnoses it), writing nothing but the cache.
"""

from __future__ import annotations

import time
from pathlib import Path

import typer

from rig.commands.common import EXIT_FAILED, console, fail


def warmup_command(
    all_: bool = typer.Option(False, "--all", help="Also the diagnosis kernels (slower)."),
):
    """Compile the simulation and identification kernels (numba) now; later commands start fast.

    Writes nothing but numba's cache (beside the sources). Run it once after
    installing; running it again is quick (everything is cached).
    """
    from rig.analysis.identify import identify_trials
    from rig.config.profile import default_profile_path, load_profile
    from rig.config.recipe import load_recipe
    from rig.session.sim import simulate

    t0 = time.perf_counter()
    recipe_path = Path(__file__).resolve().parents[2] / "config" / "recipes" / "smoke.yaml"
    try:
        recipe = load_recipe(recipe_path)
        profile = load_profile(recipe.profile_path() or default_profile_path())
    except Exception as exc:  # noqa: BLE001 - a broken install: say what is missing
        fail(f"cannot load the smoke recipe and profile of the installation: {exc}", EXIT_FAILED)
    with console.status("compiling the simulation kernels..."):
        log, _ = simulate(recipe, profile)
    t_sim = time.perf_counter() - t0
    trial = log.trial_data(recipe.log.decimated_rate_hz)
    with console.status("compiling the identification kernels..."):
        try:
            identify_trials([trial], names=["warmup"], whole_record=True, stiffness=True)
        except ValueError:
            pass  # a short record may have too little to fit: the kernels are compiled all the same
    t_id = time.perf_counter() - t0 - t_sim
    line = f"warm: simulation {t_sim:.1f} s, identification {t_id:.1f} s"
    if all_:
        from rig.diagnosis import diagnose

        t1 = time.perf_counter()
        with console.status("compiling the diagnosis kernels..."):
            try:
                diagnose(trial)
            except ValueError:
                pass
        line += f", diagnosis {time.perf_counter() - t1:.1f} s"
    console.print(line + " (numba's cache is beside the sources; later commands load it)", markup=False)


def register(app: typer.Typer) -> None:
    app.command("warmup")(warmup_command)
