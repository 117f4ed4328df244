"""The operator CLI, ``rig`` (typer).

Each subsystem registers its commands from its own module, so the modules
stay independent: ``rig.commands.trial`` (run), ``rig.commands.logs`` (info,
export, import, recover),
``rig.commands.analysis`` (identify, stribeck, stability, reproduce),
``rig.commands.diagnose`` (diagnose), ``rig.commands.hardware`` (devices,
emulate, loop-bench), ``rig.commands.catalog`` (catalog build, catalog query),
``rig.commands.warmup`` (warmup), ``rig.commands.heal`` (heal), ``rig.commands.tune``
(tune step, frf, autotune). A module that is
missing is simply not registered. The conventions (exit codes, ``-o/--out``,
``--json PATH``) and the safety net against tracebacks are in
:mod:`rig.commands.common`.
"""

from __future__ import annotations

import importlib

import typer

from rig import __version__
from rig.commands.common import CONVENTIONS, RigGroup

app = typer.Typer(
    cls=RigGroup,
    epilog=CONVENTIONS,
    name="rig",
    help=(
        "Run friction trials on a servohydraulic double-shear rig (Dupont & Dunlap 1995), "
        "simulated or real; log them to MCAP; identify rate-and-state friction; "
        "diagnose what the model of the rig gets wrong."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

COMMAND_MODULES = (
    "rig.commands.trial",
    "rig.commands.logs",
    "rig.commands.analysis",
    "rig.commands.diagnose",
    "rig.commands.hardware",
    "rig.commands.warmup",
    "rig.commands.catalog",
    "rig.commands.calibrate",
    "rig.commands.heal",
    "rig.commands.tune",
)


def _version(value: bool):  # noqa: FBT001
    if value:
        typer.echo(f"rig {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")):  # noqa: FBT001
    """rig: friction trials, logging, identification and diagnosis."""


for _name in COMMAND_MODULES:
    try:
        _mod = importlib.import_module(_name)
    except ModuleNotFoundError as exc:  # subsystem not installed/written yet
        if exc.name != _name:
            raise
        continue
    _mod.register(app)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
