"""``rig catalog build DIR`` and ``rig catalog query "SQL"``; the batch helpers of identify/diagnose.

The catalogue is a DuckDB file (docs/catalog.md); batch runs use the engine of
:mod:`rig.catalog.batch` (docs/scaling.md).
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
from pathlib import Path
from typing import Callable, Optional

import typer
from rich.console import Console
from rich.table import Table

from rig.commands.common import show_progress

console = Console(width=None if Console().is_terminal else 160)
err_console = Console(stderr=True)

catalog_app = typer.Typer(help="The lab's archive: index trial files into a DuckDB catalogue and query it.",
                          no_args_is_help=True)


def _fail(msg: str, code: int = 2):
    err_console.print(f"[red]error:[/red] {msg}", soft_wrap=True, highlight=False)
    raise typer.Exit(code)


def progress_bar(description: str, total: int, *, enabled: bool = True):
    """A rich progress bar over files and a ``progress(done, total, result)`` callback for the engine;
    shown on a terminal only (:func:`rig.commands.common.show_progress`); failures are printed either way."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    prog = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=err_console,
                    disable=not (enabled and show_progress()),
                    transient=False)
    task = prog.add_task(description, total=total)

    def cb(done, _total, result):
        prog.update(task, completed=done)
        if not result.ok:
            item = result.item[0] if isinstance(result.item, tuple) else result.item
            prog.console.print(f"[yellow]failed:[/yellow] {item}: {result.error}", highlight=False, soft_wrap=True)

    return prog, cb


def _check_jobs(jobs: Optional[int], scheduler: Optional[str]) -> None:
    if jobs is not None and jobs < 1:
        _fail(f"--jobs must be at least 1 (got {jobs})")
    if scheduler is not None and not scheduler.startswith(("tcp://", "tls://", "inproc://", "ws://", "wss://")):
        _fail(f"--scheduler {scheduler!r}: expected an address like tcp://HOST:PORT")


@catalog_app.command("build")
def build_cmd(
    root: Path = typer.Argument(..., help="Directory of trial files (.mcap, .csv), searched recursively."),
    db: Optional[Path] = typer.Option(None, "--db", help="Catalogue file (default DIR/catalog.duckdb)."),
    jobs: Optional[int] = typer.Option(1, "--jobs", help="Read files on N processes (this one and N-1 workers); 1: serially."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Use an existing Dask cluster, tcp://HOST:PORT."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
):
    """Index every trial log and CSV under DIR, reading only new or changed files."""
    from rig.catalog import CatalogError, build
    from rig.catalog.batch import BatchError

    if not root.is_dir():
        _fail(f"{root}: no such directory")
    _check_jobs(jobs, scheduler)
    prog, cb = progress_bar("reading trial files", 0, enabled=not quiet)
    try:
        with prog:
            def cb2(done, total, r):
                prog.update(prog.task_ids[0], total=total)
                cb(done, total, r)

            rep = build(root, db, jobs=jobs, scheduler=scheduler, progress=cb2)
    except (CatalogError, BatchError) as exc:
        _fail(str(exc), 1)
    console.print(f"{rep.db}: {rep.n_files} files; read {len(rep.read)} (new or changed), "
                  f"{len(rep.unchanged) + len(rep.touched)} unchanged, {len(rep.failed)} unreadable, "
                  f"{len(rep.removed)} removed", highlight=False)
    for path, err in rep.failed.items():
        console.print(f"  [yellow]unreadable:[/yellow] {path}: {err}", highlight=False, soft_wrap=True)


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(map(str, v))
    return str(v)


@catalog_app.command("query")
def query_cmd(
    sql: str = typer.Argument(..., help='SQL on the catalogue, e.g. "SELECT * FROM catalog WHERE B_mu > 5e-3".'),
    db: Path = typer.Option(Path("catalog.duckdb"), "--db", help="Catalogue file."),
    json_out: Optional[Path] = typer.Option(None, "--json", metavar="PATH", help="Write the rows as JSON to this "
                                            "file ('-': print them on standard output)."),
    csv_out: Optional[Path] = typer.Option(None, "--csv", metavar="PATH", help="Write the rows as CSV to this "
                                           "file ('-': print them on standard output)."),
):
    """Run SQL on the catalogue: a table, or --json PATH / --csv PATH ('-' prints)."""
    from rig.catalog import CatalogError, query

    if json_out and csv_out:
        _fail("give --json or --csv, not both")
    try:
        res = query(db, sql)
    except CatalogError as exc:
        _fail(str(exc), 2)  # no such catalogue, a query that fails: bad input (rig.commands.common)
    _note_not_computed(db, res)
    if json_out:
        if str(json_out) == "-":
            typer.echo(res.to_json())
        else:
            from rig.data import atomic_write_text

            atomic_write_text(json_out, res.to_json() + "\n")
        return
    if csv_out:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(res.columns)
        for r in res.rows:
            w.writerow(["" if v is None else (";".join(map(str, v)) if isinstance(v, list) else v) for v in r])
        if str(csv_out) == "-":
            typer.echo(buf.getvalue(), nl=False)
        else:
            from rig.data import atomic_write_text

            atomic_write_text(csv_out, buf.getvalue())
        return
    table = Table(title=f"{len(res.rows)} row(s)")
    for c in res.columns:
        table.add_column(c, overflow="fold")
    for r in res.rows:
        table.add_row(*(_cell(v) for v in r))
    console.print(table)


#: result columns of the catalogue and the command that computes them
_RESULT_COLUMNS = {"identify": {"A_mu", "B_mu", "L_um", "A_mu_sem", "B_mu_sem", "L_um_sem", "k_cr_kN_per_m", "n_steps",
                                "identify_ok", "identify_current", "identify_version"},
                   "diagnose": {"causes", "n_findings", "holdout_rms_N", "baseline_holdout_rms_N", "diagnose_ok",
                                "diagnose_current", "diagnose_version"}}


def _note_not_computed(db: Path, res) -> None:
    """A query whose result columns are all empty because the analysis never ran says so (stderr)."""
    from rig.catalog import query

    for kind, cols in _RESULT_COLUMNS.items():
        idx = [i for i, c in enumerate(res.columns) if c in cols]
        if not idx or not res.rows or any(r[i] is not None for r in res.rows for i in idx):
            continue
        try:
            n = query(db, f"SELECT count(*) FROM {kind}_results").rows[0][0]
        except Exception:  # noqa: BLE001 - a note only
            continue
        what = "no trial" if n == 0 else "none of these trials"
        err_console.print(f"note: {', '.join(res.columns[i] for i in idx)} empty: {kind} has been run on {what} "
                          f"in this catalogue; `rig {kind} DIR` computes and stores it (the `results` column of "
                          "`catalog` says which trials have results)", highlight=False, soft_wrap=True)


# ---------------------------------------------------------------------------
# batch identify / diagnose (called by rig.commands.analysis and rig.commands.diagnose)
# ---------------------------------------------------------------------------

SUMMARY_ROWS = 50  # larger batches print counts only; the catalogue has every row
BATCH_CHUNK = 2000  # files per round trip of a batch run (results written to the catalogue per chunk)


def is_batch(inputs: list[str], jobs: Optional[int], scheduler: Optional[str], db: Optional[Path]) -> bool:
    """A batch run: a directory or a glob among the inputs, or --jobs/--scheduler/--db given."""
    import glob as _glob

    if jobs is not None or scheduler is not None or db is not None:
        return True
    return any(Path(s).is_dir() or (_glob.has_magic(s) and not Path(s).exists()) for s in inputs)


def run_batch(kind: str, inputs: list[str], options: dict, *, jobs: Optional[int], scheduler: Optional[str],
              db: Optional[Path], summarize: Callable[[list], None]) -> None:
    """Expand DIR-or-GLOB inputs, index the files, run ``kind`` (identify | diagnose) on each on
    the engine with a progress bar, write the results into the catalogue, print a summary.
    Exit status 0 when every file was analysed, 1 when some failed (they are listed)."""
    from rig.catalog import CatalogError, build, default_db, expand_inputs
    from rig.catalog.batch import BatchError, engine, run_tasks
    from rig.catalog.build import record_diagnose, record_identify
    from rig.catalog.tasks import diagnose_file, file_cost, identify_file

    _check_jobs(jobs, scheduler)
    files: list[Path] = []
    base: Path | None = None
    for s in inputs:
        try:
            fs, b = expand_inputs(s)
        except FileNotFoundError as exc:
            _fail(str(exc))
        files += fs
        base = base or b
    files = sorted(set(files))
    if not files:
        _fail(f"{', '.join(inputs)}: no .mcap or .csv files")
    db = db or default_db(base)
    fn = identify_file if kind == "identify" else diagnose_file
    items = [(str(f), options) for f in files]
    try:
        with contextlib.ExitStack() as stack:
            # one engine (workers, cluster) for the indexing of new files and the analysis (none for --jobs 1 or one file)
            client = None
            if scheduler is not None or (jobs != 1 and len(items) > 1):
                client = stack.enter_context(engine(jobs, scheduler))
            build(base, db, files=files, jobs=1, prune=False, client=client)
            prog, cb = progress_bar(f"{kind} ({len(files)} files)", len(items))
            results = []
            with prog:
                # in chunks: each chunk's results go into the catalogue before the next is sent, so
                # memory stays bounded and an interrupted archive-wide run keeps what it finished
                for i in range(0, len(items), BATCH_CHUNK):
                    chunk = run_tasks(fn, items[i:i + BATCH_CHUNK], jobs=1, client=client, cost=file_cost,
                                      progress=lambda d, t, r, i=i: cb(i + d, len(items), r))
                    (record_identify if kind == "identify" else record_diagnose)(db, chunk, options)
                    results += chunk
    except (CatalogError, BatchError) as exc:
        _fail(str(exc), 1)
    if len(results) <= SUMMARY_ROWS:
        summarize(results)
    else:
        console.print(f"(per-file table omitted for {len(results)} files: `rig catalog query --db {db} "
                      f"\"SELECT * FROM {kind}_results\"`)", highlight=False)
    bad = [r for r in results if not r.ok]
    console.print(f"{kind}: {len(results) - len(bad)} of {len(results)} files done; results in {db}",
                  highlight=False)
    if bad:
        for r in bad:
            console.print(f"  [red]failed:[/red] {r.item[0]}: {r.error}", highlight=False, soft_wrap=True)
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.add_typer(catalog_app, name="catalog")


def identify_summary(results: list) -> None:
    """The batch identify table: one row per file."""
    table = Table(title="identify: per-file means (eqs. 10-13)")
    for c in ("file", "steps", "A_mu", "B_mu", "L (µm)", "k_cr (kN/m)", "s"):
        table.add_column(c, justify="right" if c != "file" else "left", overflow="fold")
    for r in results:
        if not r.ok:
            table.add_row(str(r.item[0]), "[red]failed[/red]", "", "", "", "", _cell(r.seconds))
            continue
        m = r.value["report"]["mean"]
        table.add_row(str(r.item[0]), str(r.value["report"]["n_steps"]), _cell(m.get("A_mu")), _cell(m.get("B_mu")),
                      _cell(m.get("L_um")), _cell(m.get("k_cr_kN_per_m")), f"{r.seconds:.2f}")
    console.print(table)


def diagnose_summary(results: list) -> None:
    """The batch diagnose table: one row per file."""
    table = Table(title="diagnose: per-file findings")
    for c in ("file", "baseline RMS (N)", "findings", "final RMS (N)", "s"):
        table.add_column(c, justify="right" if c != "file" else "left", overflow="fold")
    for r in results:
        if not r.ok:
            table.add_row(str(r.item[0]), "[red]failed[/red]", "", "", _cell(r.seconds))
            continue
        rep = r.value["report"]
        causes = ", ".join(f["cause"] for f in rep["findings"]) or "none"
        table.add_row(str(r.item[0]), _cell(rep["baseline"]["holdout_rms_N"]), causes, _cell(rep["holdout_rms_N"]),
                      f"{r.seconds:.2f}")
    console.print(table)
