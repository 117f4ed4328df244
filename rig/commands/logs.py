"""Log commands: ``rig info``, ``rig export``, ``rig import``, ``rig recover`` (:mod:`rig.log`).

Exit status (:mod:`rig.commands.common`): 0 done; 2 bad input (a file that is
not a readable log or CSV, a damaged log under ``--strict``); 1 a file that
cannot be written.
"""

from __future__ import annotations

import warnings
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from rig.commands.common import (EXIT_BAD_INPUT, EXIT_FAILED, JSON_HELP, check_new_output, check_output_path,
                                 console, fail, json_to_stdout, warn, write_json)

_fail = fail
_warn = warn


def info_command(
    path: Path = typer.Argument(..., help="Trial log (.mcap).", show_default=False, metavar="FILE.mcap"),
    events: int = typer.Option(20, "--events", "-n", help="How many events to list (0: none, -1: all)."),
    json_out: Optional[Path] = typer.Option(None, "--json", metavar="PATH", help=JSON_HELP + " Everything "
                                            "the tables show, and the full event list.", show_default=False),
):
    """Show a trial log: channels with message counts, duration, metadata, events, recovered, damage.

    Every chunk's CRC is checked: corrupt chunks are listed with their time range and channels."""
    from rig.errors import DataFormatError  # not rig.data: numpy is not needed here (issue 25: rig info < 0.3 s)
    from rig.log import trial_info

    try:
        info = trial_info(path)
    except DataFormatError as exc:
        _fail(str(exc))
    if json_out is not None:
        write_json(info, json_out)
        if json_to_stdout(json_out):
            return
    state = "complete, every chunk's CRC verified" if info["complete"] else \
        f"DAMAGED/TRUNCATED ({info['damage']}) -- `rig recover` keeps the intact chunks"
    console.print(f"[bold]{info['path']}[/]  {info['size_bytes'] / 1e6:.2f} MB  {state}", highlight=False)
    rec = info["metadata"].get("recovery")
    if info["recovered"]:
        console.print(f"[yellow]recovered[/] from {rec.get('recovered_from')} "
                      f"(damage: {rec.get('recovery_error')}; {rec.get('messages')} messages kept)", highlight=False)
    else:
        console.print("recovered: no")
    dur = info["duration_s"]
    console.print(f"duration: {dur:.3f} s" if dur is not None else "duration: (no samples)")
    started = info["metadata"].get("trial", {}).get("started_utc")
    if started:
        console.print(f"started: {started}", highlight=False)
    who = [f"{k} {info[k]}" for k in ("trial_uid", "specimen", "operator") if info.get(k)]
    console.print("trial: " + ("; ".join(who) if who else "(no trial_uid: written before rig recorded one)")
                  + (f"; note: {info['note']}" if info.get("note") else ""), highlight=False, markup=False)
    cal = _calibration_line(info["metadata"].get("trial", {}).get("calibration"))
    if cal:
        console.print(f"calibration: {cal}", highlight=False, markup=False)
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
            if key in ("json", "calibration") and len(value) > 80:
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
    for d in info["corrupt_chunks"]:
        _warn(f"corrupt chunk ({d['error']}): t = {d['t_start_s']:.3f}..{d['t_end_s']:.3f} s, channels lost "
              f"there: {', '.join(d['channels']) or 'unknown'}")


def _calibration_line(text: str | None) -> str:
    """The calibration snapshot of a hardware trial in one line: channel, serial, due date."""
    import json

    try:
        snap = json.loads(text) if text else {}
    except ValueError:
        return ""
    return ", ".join(f"{ch} {rec.get('serial')}" + (f" (due {rec['due_on']})" if rec.get("due_on") else "")
                     for ch, rec in snap.items() if isinstance(rec, dict))


class Rate(str, Enum):
    raw = "raw"
    r25 = "25"


def export_command(
    path: Path = typer.Argument(..., help="Trial log (.mcap).", show_default=False, metavar="TRIAL.mcap"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", metavar="PATH", show_default=False,
                                       help="File to write: a .csv (measured-data format, version 1) or a "
                                            ".parquet (same columns; for pandas and polars), by its suffix."),
    csv: Optional[Path] = typer.Option(None, "--csv", metavar="PATH", show_default=False,
                                       help="CSV file to write (as -o PATH.csv)."),
    parquet: Optional[Path] = typer.Option(None, "--parquet", metavar="PATH", show_default=False,
                                           help="Parquet file to write (as -o PATH.parquet)."),
    rate: Rate = typer.Option(Rate.r25, "--rate", help="'25': the decimated per-sample channel (the paper's "
                                                       "25 Hz log); 'raw': every loop sample."),
    extra: bool = typer.Option(True, "--extra/--no-extra", help="Keep extra columns (raw: pid_*, dither, "
                                                                "true_*) after the standard ones."),
    strict: bool = typer.Option(False, "--strict", help="A corrupt chunk is an error (exit 2), not a warning."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output file (exit 2 otherwise)."),
    elastic: Optional[str] = typer.Option(None, "--elastic-correction", metavar="K_kN_per_m|fit", show_default=False,
                                          help="Add interface_slip_um = position_um - friction_N / k: k in kN/m, "
                                               "or 'fit' (the file's machine_stiffness_kN_per_m, else the "
                                               "whole-record fit with stiffness)."),
):
    """Export a trial log to the measured-data CSV and/or Parquet, atomically.

    Columns: time_s, position_um, friction_N, normal_1_N, normal_2_N,
    position_ref_um, valve_cmd (those present), then extra columns; the trial's
    metadata (normal_force_N, lubricant, recipe, seed, ...) as '# key: value'
    lines (CSV) or key-value metadata (Parquet). Reads every log layout (v1, v2).
    """
    from rig.data import DataFormatError, write_csv
    from rig.log import LogDamageWarning, read_trial, write_parquet

    if out is not None:
        kind = out.suffix.lower()
        if kind == ".csv" and csv is None:
            csv = out
        elif kind == ".parquet" and parquet is None:
            parquet = out
        else:
            _fail(f"--out {out}: expected a .csv or .parquet file name (or give --csv and --parquet)")
    if csv is None and parquet is None:
        _fail("nothing to write: give -o OUT.csv and/or -o OUT.parquet (or --csv/--parquet)")
    for opt, p in (("--csv", csv), ("--parquet", parquet)):
        if p is not None:
            check_output_path(p, opt)
            check_new_output(p, opt, overwrite)
    if elastic is not None:
        from rig.analysis.elastic import parse_correction

        try:
            k_given = parse_correction(elastic)
        except ValueError as exc:
            _fail(str(exc))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LogDamageWarning)  # shown below from trial.warnings
            trial = read_trial(path, channel="raw" if rate == Rate.raw else "25hz", strict=strict)
    except DataFormatError as exc:
        _fail(str(exc))
    for w in trial.warnings:
        _warn(w)
    if not extra:
        trial.extra = {}
    if elastic is not None:
        from rig.analysis.elastic import correct

        try:
            ec = correct(trial, k_given)
        except ValueError as exc:
            _fail(str(exc))
        err = f" ± {ec['k_err_kN_per_m']:.3g}" if ec["k_err_kN_per_m"] is not None else ""
        console.print(f"elastic correction: k = {ec['k_kN_per_m']:.4g}{err} kN/m ({ec['source']})", highlight=False)
    for target, write in ((csv, write_csv), (parquet, write_parquet)):
        if target is None:
            continue
        try:
            write(trial, target, overwrite=overwrite)
        except FileExistsError:
            _fail(f"{target}: appeared while exporting; not overwritten (--overwrite replaces it)")
        except OSError as exc:
            _fail(f"cannot write {target}: {exc.strerror or exc}", EXIT_FAILED)
        console.print(f"wrote {target}: {len(trial)} rows, columns {', '.join(trial.columns())}", highlight=False)


def import_command(
    path: Path = typer.Argument(..., help="Measured-data CSV (version 1).", show_default=False, metavar="IN.csv"),
    out: Path = typer.Option(..., "--out", "-o", help="Trial log to write (.mcap).", show_default=False),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out file (exit 2 otherwise)."),
    column_map: Optional[list[str]] = typer.Option(None, "--map", help="OUR=THEIRS column names of a lab's own "
                                                   "CSV, comma-separated or repeated: time_s=Time,position_um="
                                                   "LP_disp,friction_N=Shear (the format line is then optional)."),
    scale: Optional[list[str]] = typer.Option(None, "--scale", help="COLUMN=FACTOR (our name), repeated: e.g. "
                                              "position_um=1000 for mm."),
):
    """Import a measured-data CSV into a trial log (MCAP), atomically.

    Bad input (missing column, non-numeric value, time not increasing, NaN in a
    required column, empty data, invalid normal_force_N metadata) is one error
    naming the file and the line, exit status 2, and no output file. A trailing
    partial line is a warning; the complete rows before it are imported. Extra
    columns are kept. Every row goes to both the raw and the per-sample channel;
    the CSV metadata to the 'trial' metadata record.
    """
    from rig.data import DataFormatError, read_csv
    from rig.log import write_trial_data

    check_output_path(out, "--out", (".mcap",))
    check_new_output(out, "--out", overwrite)
    cmap = _pairs(column_map, "--map", str) if column_map else None
    factors = _pairs(scale, "--scale", float) if scale else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            trial = read_csv(path, column_map=cmap, scale=factors)
        except DataFormatError as exc:
            _fail(str(exc))
    for w in caught:
        _warn(str(w.message))
    try:
        extra = {"imported_from": str(path)}
        if not str(trial.metadata.get("trial_uid", "")).strip():  # the CSV's own identity: the catalogue's for it
            from rig.catalog.tasks import sha256_file
            from rig.data import content_uid

            extra["trial_uid"] = content_uid(sha256_file(path))
        write_trial_data(trial, out, extra_metadata=extra, overwrite=overwrite)
    except DataFormatError as exc:
        _fail(str(exc))
    except FileExistsError:
        _fail(f"--out {out}: appeared while importing; not overwritten (--overwrite replaces it)")
    except OSError as exc:
        _fail(f"cannot write {out}: {exc.strerror or exc}", EXIT_FAILED)
    console.print(f"wrote {out}: {len(trial)} samples, columns {', '.join(trial.columns())}", highlight=False)


def _pairs(values: list[str], option: str, conv) -> dict:
    """``A=B`` items (comma-separated or repeated) of ``--map`` / ``--scale``; exit 2 naming the bad one."""
    from rig.data import STANDARD_COLUMNS

    out = {}
    for item in (p.strip() for v in values for p in v.split(",")):
        if not item:
            continue
        key, sep, val = (s.strip() for s in item.partition("="))
        if not sep or not key or not val:
            _fail(f"{option} {item!r}: expected NAME=VALUE, e.g. {'time_s=Time' if option == '--map' else 'position_um=1000'}")
        if option == "--map" and key not in STANDARD_COLUMNS:
            _fail(f"{option} {item!r}: {key!r} is not a column of the format ({', '.join(STANDARD_COLUMNS)})")
        try:
            out[key] = conv(val)
        except ValueError:
            _fail(f"{option} {item!r}: {val!r} is not a number")
        if conv is float and not (out[key] == out[key] and abs(out[key]) < float("inf") and out[key] != 0):
            _fail(f"{option} {item!r}: the factor must be a finite, non-zero number")
    return out


def recover_command(
    path: Path = typer.Argument(..., help="Damaged or truncated trial log (.mcap).", show_default=False,
                                metavar="FILE.mcap"),
    out: Path = typer.Option(..., "--out", "-o", help="Readable trial log to write (.mcap).", show_default=False),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out file (exit 2 otherwise)."),
):
    """Rewrite a truncated or damaged trial log (e.g. after a crash) into a readable one.

    Every intact chunk is kept; a chunk that fails its CRC is dropped (its values
    are never carried forward). The new file carries a 'recovery' metadata
    record (`rig info` shows it as recovered).
    """
    from rig.data import DataFormatError
    from rig.log import recover

    check_output_path(out, "--out", (".mcap",))
    if out.exists() and path.exists() and out.resolve() == path.resolve():
        _fail(f"--out {out}: the same file as the damaged log (write the readable one beside it)")
    check_new_output(out, "--out", overwrite)
    try:
        res = recover(path, out, overwrite=overwrite)
    except FileExistsError:
        _fail(f"--out {out}: appeared while recovering; not overwritten (--overwrite replaces it)")
    except (DataFormatError, ValueError) as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"cannot write {out}: {exc.strerror or exc}", EXIT_FAILED)
    n = sum(res["messages"].values())
    if res["complete_before"]:
        what = "was complete"
    else:
        what = "damaged: " + "; ".join(filter(None, [res["error"] or ("no footer" if not res["damage"] else ""),
                                                    f"{len(res['damage'])} corrupt chunk(s) dropped"
                                                    if res["damage"] else ""]))
    console.print(f"wrote {out}: {n} messages up to t = {res['last_t_s']:.3f} s ({path} {what})", highlight=False)
    for d in res["damage"]:
        _warn(f"dropped corrupt chunk ({d['error']}): t = {d['t_start_s']:.3f}..{d['t_end_s']:.3f} s, "
              f"channels {', '.join(d['channels']) or 'unknown'}")


def register(app: typer.Typer) -> None:
    app.command("info")(info_command)
    app.command("export")(export_command)
    app.command("import")(import_command)
    app.command("recover")(recover_command)
