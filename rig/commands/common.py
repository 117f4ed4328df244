"""What every ``rig`` command shares: the exit-code table, the error and warning printers,
the ``--json PATH`` convention, and the safety net that keeps tracebacks from operators.

Exit codes (one table, kept by every subcommand; ``tests/system/commands/test_exit_codes.py`` checks it):

====  =====================================================================
0     done (an analysis that ran, whatever it found)
1     a failed run: a trial that failed or tripped, a device that did not
      answer, a file that could not be written, an internal error
2     bad input: a file, option or value rig cannot use (nothing is written)
130   aborted by the operator (Ctrl-C, SIGTERM, SIGHUP)
====  =====================================================================

Conventions (``rig --help`` shows them): ``-o/--out PATH`` names a command's
main output file; ``--json PATH`` writes the JSON report to PATH and
``--json -`` prints it on standard output; ``--plot PATH`` writes a PNG.
Every error is one line, ``error: FILE, line N: what is wrong`` where there is
a file and a line; warnings are one line, ``warning: ...`` (never a Python
source line). An unexpected exception is reported as an internal error in one
line (``RIG_DEBUG=1`` shows the traceback).
"""

from __future__ import annotations

from contextlib import contextmanager

import json
import os
import sys
import warnings
from enum import Enum, IntEnum
from pathlib import Path
from typing import Any, NoReturn

import typer
from rich.console import Console
from typer.core import TyperGroup


class ExitCode(IntEnum):
    """The exit status of every ``rig`` command."""

    OK = 0
    FAILED = 1
    BAD_INPUT = 2
    ABORTED = 130


EXIT_OK = ExitCode.OK
EXIT_FAILED = ExitCode.FAILED
EXIT_BAD_INPUT = ExitCode.BAD_INPUT
EXIT_ABORTED = ExitCode.ABORTED

EXIT_TABLE = ("Exit status: 0 done; 1 failed run, trip or write; 2 bad input (nothing written); "
              "130 aborted (Ctrl-C).")

CONVENTIONS = (
    "Conventions: -o/--out PATH is a command's main output file; --json PATH writes the JSON report "
    "(--json - prints it); --plot PATH writes a PNG. Files are written atomically (complete or absent) "
    "and readable by others (0644 under the usual umask). " + EXIT_TABLE
    + " The first command of a fresh install compiles the simulation kernels (numba) for up to about "
    "a minute; `rig warmup` does it ahead."
)

#: help text of every ``--json`` option
JSON_HELP = "Write the JSON report to this file ('-': print it on standard output)."

# soft_wrap: one error is one line however narrow the terminal (tests grep it; so do operators)
err_console = Console(stderr=True, soft_wrap=True, highlight=False)
console = Console(soft_wrap=True, highlight=False)


def fail(message: str, code: int = EXIT_BAD_INPUT) -> NoReturn:
    """Print ``error: message`` on stderr and exit with ``code`` (default 2, bad input)."""
    err_console.print(f"[bold red]error:[/] {_escape(message)}")
    raise typer.Exit(int(code))


def warn(message: str) -> None:
    """Print ``warning: message`` on stderr (one line)."""
    err_console.print(f"[yellow]warning:[/] {_escape(message)}")


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(str(text))


def write_json(doc: Any, dest: Path | str, *, what: str = "report") -> None:
    """Write ``doc`` as JSON to ``dest`` (atomically, 0644) or, when ``dest`` is '-', to stdout.

    A file that cannot be written is exit 1 with the path named."""
    text = json.dumps(_finite(doc), indent=2, allow_nan=False, default=_json_default) + "\n"
    if str(dest) == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    from rig.data import atomic_write_text

    try:
        atomic_write_text(dest, text)
    except OSError as exc:
        fail(f"cannot write {dest}: {exc.strerror or exc}", EXIT_FAILED)
    console.print(f"wrote {dest}", markup=False)


def _finite(obj: Any) -> Any:
    """NaN and infinities as null: valid JSON for every reader (json.dumps would write NaN)."""
    if isinstance(obj, float):
        return obj if obj == obj and obj not in (float("inf"), float("-inf")) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    np = sys.modules.get("numpy")  # a numpy value exists only once numpy is imported (`rig info --json` never does)
    if np is not None:
        if isinstance(obj, np.floating):
            return _finite(float(obj))
        if isinstance(obj, np.ndarray):
            return _finite(obj.tolist())
        if isinstance(obj, np.generic):
            return obj.item()
    return obj


def _json_default(obj: Any) -> Any:
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def json_to_stdout(dest: Path | str | None) -> bool:
    """True when ``--json -`` asks for JSON on stdout (then the tables are not printed there)."""
    return dest is not None and str(dest) == "-"


class _NoBar:
    """What :func:`progress_bar` yields when nothing is shown."""

    def advance(self, n: float = 1.0) -> None:
        pass

    def update(self, description: str | None = None, total: float | None = None) -> None:
        pass


class _Bar(_NoBar):
    def __init__(self, prog, task):
        self._p, self._t = prog, task

    def advance(self, n: float = 1.0) -> None:
        self._p.advance(self._t, n)

    def update(self, description: str | None = None, total: float | None = None) -> None:
        kw = {k: v for k, v in (("description", description), ("total", total)) if v is not None}
        self._p.update(self._t, **kw)


def show_progress(json_out=None, out_console: Console | None = None) -> bool:
    """Progress is for a person at a terminal: not with ``--json -`` nor when standard output is
    not a terminal (a pipe, a file, a CI log)."""
    return (out_console or console).is_terminal and not json_to_stdout(json_out)


@contextmanager
def progress_bar(json_out, description: str, total: float | None = None, unit: str = "",
                 out_console: Console | None = None, bar_console: Console | None = None):
    """A rich progress bar on standard error for a long analysis (full-rig stability scans,
    reproduce, diagnose): ``bar.advance()`` per finished piece, ``bar.update(description=...)``;
    ``total=None`` when the number of pieces is not known ahead (a pulsing bar and a count).
    Silent (a no-op bar) when :func:`show_progress` says so. The bar is removed when done."""
    if not show_progress(json_out, out_console):
        yield _NoBar()
        return
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    cols = [SpinnerColumn(), TextColumn("[progress.description]{task.description}"), BarColumn(),
            MofNCompleteColumn(), TextColumn(unit), TimeElapsedColumn()]
    if total is not None:
        cols.append(TimeRemainingColumn())
    with Progress(*cols, console=bar_console or err_console, transient=True) as prog:
        yield _Bar(prog, prog.add_task(description, total=total))


def check_output_path(path: Path, option: str, suffixes: tuple[str, ...] = ()) -> None:
    """An output path that is a directory, or has the wrong suffix, is bad input (exit 2) before any work;
    one that cannot be written (a read-only or missing file system, a file where a directory should be)
    is exit 1 naming ``path``, also before any work, so no other output is written first."""
    if path is None or str(path) == "-":
        return
    if path.is_dir():
        fail(f"{option} {path}: is a directory (give a file name)")
    if suffixes and path.suffix.lower() not in suffixes:
        fail(f"{option} {path}: expected a {' or '.join(suffixes)} file name")
    problem = _unwritable(Path(path))
    if problem:
        fail(f"{option} {path}: cannot write there ({problem}); nothing was written", EXIT_FAILED)


def _unwritable(path: Path) -> str | None:
    """Why a file cannot be written at ``path`` (None: it can). The atomic writer makes the missing
    directories and a temporary file beside ``path``: the nearest existing directory must take one."""
    import tempfile

    d = path.absolute().parent
    while not d.exists() and d != d.parent:
        d = d.parent
    if not d.is_dir():
        return f"{d} is not a directory"
    try:
        with tempfile.TemporaryFile(dir=d):
            pass
    except OSError as exc:
        return f"{d}: {exc.strerror or exc}"
    return None


def emit_outputs(con: Console, json_out: Path | None, doc: Any, plot: Path | None = None, draw=None) -> None:
    """The tail of an analysis command: the JSON report (``--json``), then the figure (``--plot``:
    ``draw(path)`` writes it) and ``wrote PATH``. Both paths were checked by :func:`check_output_path`
    before the work; a write that fails all the same is exit 1 naming the path asked for."""
    if json_out:
        write_json(doc, json_out)
    if plot:
        try:
            draw(plot)
        except OSError as exc:
            fail(f"cannot write {plot}: {exc.strerror or exc}", EXIT_FAILED)
        con.print(f"wrote {plot}", markup=False)


def check_new_output(path: Path, option: str, overwrite: bool) -> None:
    """A trial file (a log, its export, import or recovery) is never overwritten: an existing ``path``
    is exit 2 naming it, the file untouched, unless ``overwrite`` (``--overwrite``). The write itself
    is atomic and, without ``overwrite``, refuses a file that appeared meanwhile (FileExistsError)."""
    if path is None or str(path) == "-" or overwrite:
        return
    if path.exists() or path.is_symlink():
        fail(f"{option} {path}: exists; not overwritten (--overwrite replaces it)")


# ---------------------------------------------------------------------------
# warnings: one clean line, no Python source
# ---------------------------------------------------------------------------

def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ARG001
    text = str(message)
    name = getattr(category, "__name__", "")
    if name in ("RuntimeWarning",) and "encountered" in text:
        return  # numpy's 'invalid value encountered in ...': noise to an operator, the result says what matters
    warn(text)


class _CleanWarnings:
    def __enter__(self):
        self._old = warnings.showwarning
        warnings.showwarning = _show_warning
        return self

    def __exit__(self, *exc):
        warnings.showwarning = self._old
        return False


# ---------------------------------------------------------------------------
# the safety net
# ---------------------------------------------------------------------------

class RigGroup(TyperGroup):
    """The root command group: warnings as one line; no traceback ever reaches an operator.

    Errors the commands did not catch become one line: a data or configuration
    error (they name file and line) is exit 2; an OSError names the file, exit 1;
    anything else is an internal error (a bug: exit 1, ``RIG_DEBUG=1`` shows the
    traceback). Ctrl-C is exit 130 (typer).
    """

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        tidy_help(self)
        quick_coercion(self)
        with _CleanWarnings():
            try:
                return super().main(args=args, prog_name=prog_name, complete_var=complete_var,
                                    standalone_mode=standalone_mode, **extra)
            except Exception as exc:  # noqa: BLE001 - the last line of defence
                if os.environ.get("RIG_DEBUG"):
                    raise
                code = report_exception(exc)
                if standalone_mode:
                    sys.exit(int(code))
                return int(code)


class _QuickCoercion:
    """typer's conversion of one parameter's value, without the pydantic ``TypeAdapter`` typer 0.29 builds
    for every parameter of the invoked command (given or not: 3-8 ms each, and pydantic's import) where the
    result is plain: no value (None, or ``()`` for a list), a str for a ``str``, an int / float / bool that
    already is one (a default) within its min/max, a path (typer's own checks, on ``Path(value)``: what pydantic
    makes of a str). Anything else goes to typer's own conversion, built then."""

    def __init__(self, coerce_path, build):
        self._coerce_path, self._build, self._slow = coerce_path, build, None

    def coerce(self, value, param, ctx):
        if value is None:
            return () if param.multiple or param.nargs == -1 else None
        d = param.type_descriptor
        ann, info = d.annotation, d.parameter_info
        if info.parser is None and d.file_annotation is None and not (param.multiple or param.nargs != 1):
            if type(value) is ann and ann in (str, int, float, bool) and (info.min is None or value >= info.min) \
                    and (info.max is None or value <= info.max):
                return value
            path_type = info.path_type or ann
            if isinstance(ann, type) and issubclass(ann, Path) and path_type is ann and isinstance(value, (str, Path)):
                return self._coerce_path(Path(value) if type(value) is str else value, info, path_type=path_type,
                                         param=param, ctx=ctx)
        if self._slow is None:
            self._slow = self._build(d)
        return self._slow.coerce(value, param=param, ctx=ctx)


def quick_coercion(cmd) -> None:
    """Give every parameter of ``cmd`` and its subcommands, their help option included (made on first use),
    a :class:`_QuickCoercion` (typer 0.29's private ``_runtime_param`` hook; nothing changes where typer has
    no such hook)."""
    try:
        from typer._coercion import build_runtime_param
        from typer._param_types import coerce_cli_path
    except ImportError:
        return

    def quick(p) -> None:
        if getattr(p, "_runtime_param", 0) is None and hasattr(p, "type_descriptor"):
            p._runtime_param = _QuickCoercion(coerce_cli_path, build_runtime_param)

    def walk(c) -> None:
        for p in getattr(c, "params", ()):
            quick(p)
        help_option = getattr(c, "get_help_option", None)
        if help_option is not None and not getattr(help_option, "_rig_quick", False):
            def get_help_option(ctx, _orig=help_option):
                opt = _orig(ctx)
                if opt is not None:
                    quick(opt)
                return opt

            get_help_option._rig_quick = True
            c.get_help_option = get_help_option
        for sub in getattr(c, "commands", {}).values():
            walk(sub)

    walk(cmd)


_METAVARS = {"float": "NUMBER", "int": "INTEGER", "str": "TEXT"}


def _no_type(ctx) -> None:  # noqa: ARG001
    return None


def tidy_help(cmd) -> None:
    """Help without Python types: no ``<bool>`` beside a flag, ``PATH`` / ``NUMBER`` / ``INTEGER`` / ``TEXT``
    instead of ``<path>``, ``<list[Path]>``, ``<float>``; fixed choices stay ``<a|b|c>``. Idempotent."""
    for p in getattr(cmd, "params", ()):
        if getattr(p, "_rig_tidy", False):
            continue
        p._rig_tidy = True
        if getattr(p, "is_flag", False):
            p.display_type_rich = _no_type
            continue
        desc = getattr(p, "type_descriptor", None)
        if desc is None:
            continue
        if desc.is_choice:
            if desc.is_list and p.metavar is None:  # a repeatable choice: the choices, not list[...]
                p.metavar = "<" + "|".join(str(getattr(c, "value", c)) for c in desc.choices or ()) + ">"
            continue
        if p.param_type_name == "argument":
            if p.metavar is None:
                p.metavar = p.name.upper()
            p.display_type_rich = _no_type
        elif p.metavar is None:
            p.metavar = "PATH" if desc.is_path else _METAVARS.get(getattr(p, "bare_type", lambda: "")(), "VALUE")
    if not getattr(cmd, "_rig_tidy_help", False) and hasattr(cmd, "get_help_option"):
        cmd._rig_tidy_help = True
        plain = cmd.get_help_option

        def get_help_option(ctx, _plain=plain):
            opt = _plain(ctx)
            if opt is not None:
                opt.display_type_rich = _no_type
            return opt

        cmd.get_help_option = get_help_option
    for sub in getattr(cmd, "commands", {}).values():
        tidy_help(sub)


def report_exception(exc: BaseException) -> ExitCode:
    """Print an exception a command did not handle as one line; return its exit code."""
    from rig.data import DataFormatError

    try:
        from rig.config.loader import ConfigError
    except ImportError:  # pragma: no cover
        ConfigError = DataFormatError  # type: ignore[misc,assignment]
    if isinstance(exc, (DataFormatError, ConfigError)):
        err_console.print(f"[bold red]error:[/] {_escape(exc)}")
        return EXIT_BAD_INPUT
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        err_console.print(f"[bold red]error:[/] {_escape(where)}{_escape(exc.strerror or exc)}")
        return EXIT_FAILED
    err_console.print(f"[bold red]internal error:[/] {type(exc).__name__}: {_escape(exc)} -- a bug in rig; "
                      "please report it with the command and its input (RIG_DEBUG=1 shows the traceback)")
    return EXIT_FAILED


__all__ = ["ExitCode", "EXIT_OK", "EXIT_FAILED", "EXIT_BAD_INPUT", "EXIT_ABORTED", "EXIT_TABLE", "CONVENTIONS",
           "JSON_HELP", "err_console", "console", "fail", "warn", "write_json", "json_to_stdout",
           "check_output_path", "check_new_output", "emit_outputs", "RigGroup", "report_exception", "Lubricant", "tidy_help"]


class Lubricant(str, Enum):
    """The lubricants of the paper's Table 2 (``rig.config.recipe.LUBRICANTS``; a test keeps them equal)."""

    dry = "dry"
    paraffin = "paraffin"
    boundary = "boundary"
