"""Building the catalogue (incrementally) and writing analysis results into it.

:func:`build` walks a directory for trial files (``*.mcap``, ``*.csv``, ``*.parquet``), and
reads only what is new or changed: a file whose size and mtime match its
``files`` row is skipped without opening it; one whose size or mtime changed is
hashed, and re-read only when its sha256 changed too. A file that cannot be
read gets its ``files`` row with ``ok = false`` and the error; the build goes
on. Files gone from the directory are dropped from ``files`` and ``trial_files``;
analysis results stay, keyed by the trial's ``trial_uid``: a moved or renamed file
(or a copy, an export) joins them again when it is catalogued (issue 21).

The reading runs on the batch engine (:mod:`rig.catalog.batch`); the database
is written in this process only.
"""

from __future__ import annotations

import datetime as _dt
import glob as _glob
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from rig.catalog.batch import TaskResult, run_tasks
from rig.catalog.schema import DEFAULT_DB_NAME, open_catalog, utcnow
from rig.catalog.tasks import TRIAL_SUFFIXES, file_cost, index_file, sha256_file


@dataclass
class BuildReport:
    """What a build did, by path: read (new or changed), unchanged, failed, removed."""

    db: Path
    read: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    touched: list[str] = field(default_factory=list)  # mtime changed, same content: not re-read
    failed: dict[str, str] = field(default_factory=dict)
    removed: list[str] = field(default_factory=list)

    @property
    def n_files(self) -> int:
        return len(self.read) + len(self.unchanged) + len(self.touched)


def default_db(root: str | Path) -> Path:
    """The catalogue file of a directory: ``DIR/catalog.duckdb``."""
    return Path(root) / DEFAULT_DB_NAME


def find_trial_files(root: str | Path) -> list[Path]:
    """Every ``.mcap`` and ``.csv`` under ``root`` (recursive, sorted, resolved)."""
    root = Path(root)
    out = [p.resolve() for p in root.rglob("*") if p.is_file() and p.suffix.lower() in TRIAL_SUFFIXES]
    return sorted(set(out))


def expand_inputs(spec: str | Path) -> tuple[list[Path], Path]:
    """A directory, a glob pattern or one file -> (trial files, the directory whose catalogue
    they belong to by default). Raises ``FileNotFoundError`` naming ``spec`` when nothing matches."""
    s = str(spec)
    p = Path(s)
    if p.is_dir():
        return find_trial_files(p), p
    if p.is_file():
        return [p.resolve()], p.parent
    if _glob.has_magic(s):
        files = sorted({Path(m).resolve() for m in _glob.glob(s, recursive=True)
                        if Path(m).is_file() and Path(m).suffix.lower() in TRIAL_SUFFIXES})
        if not files:
            raise FileNotFoundError(f"{s}: no .mcap or .csv file matches")
        # the fixed part of the pattern (before the first wildcard) names the archive directory
        fixed = []
        for part in Path(s).parts:
            if _glob.has_magic(part):
                break
            fixed.append(part)
        base = Path(*fixed) if fixed else Path(".")
        return files, base if base.is_dir() else base.parent
    raise FileNotFoundError(f"{s}: no such file, directory or matching pattern")


def _parse_utc(text) -> _dt.datetime | None:
    if not text:
        return None
    s = str(text).strip()
    try:
        d = _dt.datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        try:
            d = _dt.datetime.strptime(s, "%Y-%m-%d")
        except ValueError:
            return None
    if d.tzinfo is not None:
        d = d.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return d


_TRIAL_COLUMNS = ("path", "trial_uid", "uid_source", "sha256", "kind", "recipe", "lubricant", "specimen", "operator",
                  "note", "rig_profile", "backend", "started_utc", "duration_s", "status", "log_status",
                  "normal_force_N", "seed", "n_samples", "n_events", "slip_mm", "written_by", "metadata")


def trial_key(row: dict) -> tuple[str, str]:
    """(trial_uid, where it came from) of an indexed file: its ``trial_uid`` metadata (a log, its
    exports, imports, copies and recoveries share it), else the UUID of its content
    (:func:`rig.data.content_uid`: a file from another system; a moved or renamed copy keeps its
    results, the log ``rig import`` makes from it is the same trial, an edited one is another)."""
    from rig.data import content_uid

    uid = str(row.get("trial_uid") or "").strip()
    if uid:
        return uid, "metadata"
    return content_uid(row["sha256"]), "content"


def _write_trial(con, row: dict) -> None:
    row = dict(row)
    row["trial_uid"], row["uid_source"] = trial_key(row)
    row["started_utc"] = _parse_utc(row.get("started_utc"))
    con.execute("DELETE FROM trial_files WHERE path = ?", [row["path"]])
    con.execute(f"INSERT INTO trial_files ({', '.join(_TRIAL_COLUMNS)}) VALUES ({', '.join('?' * len(_TRIAL_COLUMNS))})",
                [row.get(c) for c in _TRIAL_COLUMNS])


def _write_file(con, path: str, *, kind: str, size: int, mtime_ns: int, sha: str | None, ok: bool,
                error: str | None, read: bool, trial_uid: str | None = None) -> None:
    prev = con.execute("SELECT reads FROM files WHERE path = ?", [path]).fetchone()
    reads = ((prev[0] or 0) if prev else 0) + (1 if read else 0)
    con.execute("DELETE FROM files WHERE path = ?", [path])
    con.execute("INSERT INTO files VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [path, kind, size, mtime_ns, sha, utcnow(), ok, error, reads, trial_uid])


def build(root: str | Path, db: str | Path | None = None, *, jobs: int | None = 1, scheduler: str | None = None,
          files: Iterable[str | Path] | None = None, prune: bool = True,
          progress: Callable[[int, int, TaskResult], None] | None = None, client=None) -> BuildReport:
    """Index the trial files under ``root`` (or exactly ``files``) into ``db`` (default
    ``root/catalog.duckdb``), incrementally; see the module docstring. ``prune``: drop rows
    of files under ``root`` that no longer exist (only when walking ``root``)."""
    root = Path(root)
    db = Path(db) if db is not None else default_db(root)
    rep = BuildReport(db=db)
    paths = [Path(f).resolve() for f in files] if files is not None else find_trial_files(root)
    dbr = db.resolve()
    paths = [p for p in paths if p != dbr]
    con = open_catalog(db)
    try:
        known = {r[0]: r[1:] for r in con.execute("SELECT path, size_bytes, mtime_ns, sha256, ok FROM files")
                 .fetchall()}
        to_read: list[str] = []
        for p in paths:
            key = str(p)
            try:
                st = p.stat()
            except OSError as exc:
                rep.failed[key] = f"cannot stat: {exc.strerror or exc}"
                continue
            prev = known.get(key)
            if prev is not None and prev[0] == st.st_size and prev[1] == st.st_mtime_ns:
                rep.unchanged.append(key)
                continue
            if prev is not None and prev[2]:
                try:
                    sha = sha256_file(p)
                except OSError:
                    sha = None
                if sha == prev[2]:  # touched, same content: record the new stat, do not re-read
                    con.execute("UPDATE files SET size_bytes = ?, mtime_ns = ? WHERE path = ?",
                                [st.st_size, st.st_mtime_ns, key])
                    rep.touched.append(key)
                    continue
            to_read.append(key)
        results = run_tasks(index_file, to_read, jobs=jobs, scheduler=scheduler, progress=progress, client=client,
                            cost=file_cost)
        con.execute("BEGIN TRANSACTION")
        for r in results:
            key = r.item
            p = Path(key)
            try:
                st = p.stat()
                size, mtime = st.st_size, st.st_mtime_ns
            except OSError:
                size, mtime = None, None
            if r.ok:
                row = r.value
                _write_trial(con, row)
                _write_file(con, key, kind=row["kind"], size=row["size_bytes"], mtime_ns=row["mtime_ns"],
                            sha=row["sha256"], ok=True, error=None, read=True, trial_uid=trial_key(row)[0])
                rep.read.append(key)
            else:
                try:
                    sha = sha256_file(p)
                except OSError:
                    sha = None
                con.execute("DELETE FROM trial_files WHERE path = ?", [key])
                _write_file(con, key, kind=p.suffix.lower().lstrip("."), size=size, mtime_ns=mtime, sha=sha,
                            ok=False, error=r.error, read=True)
                rep.read.append(key)
                rep.failed[key] = r.error or "unknown error"
        if prune and files is None:
            here = {str(p) for p in paths}
            rootr = str(root.resolve()) + os.sep
            for key in known:
                if key.startswith(rootr) and key not in here:
                    con.execute("DELETE FROM files WHERE path = ?", [key])
                    con.execute("DELETE FROM trial_files WHERE path = ?", [key])
                    rep.removed.append(key)
        con.execute("COMMIT")
    finally:
        con.close()
    return rep


def _num(d: dict, k: str):
    v = (d or {}).get(k)
    return float(v) if isinstance(v, (int, float)) else None


def _uid_of(con, path: str, sha: str | None) -> str:
    """The trial a result belongs to: its file's ``trial_uid`` in the catalogue (the batch run indexes
    the files first), else the one its content gives (``sha256:...``), else the path itself."""
    from rig.data import content_uid

    row = con.execute("SELECT trial_uid FROM files WHERE path = ?", [path]).fetchone()
    if row and row[0]:
        return row[0]
    return content_uid(sha) if sha else f"path:{path}"


def _record(db: str | Path, table: str, results: list[TaskResult], ok_row, failed_cols: str, failed_row) -> None:
    """Write batch results into ``table`` in one transaction: the latest result per trial (its
    ``trial_uid``) replaces the previous one, so a moved, renamed or copied file keeps it.
    ``ok_row(r)`` gives a full row after (trial_uid, path, sha256, run_utc, rig_version, ok,
    error); a failure stores ``failed_cols`` from ``failed_row(r)`` after (trial_uid, path, run_utc,
    rig_version, ok, error)."""
    from rig import __version__

    con = open_catalog(db)
    try:
        con.execute("BEGIN TRANSACTION")
        for r in results:
            path = str(r.item[0])
            uid = _uid_of(con, path, r.value["sha256"] if r.ok else None)
            con.execute(f"DELETE FROM {table} WHERE trial_uid = ?", [uid])
            if r.ok:
                row = [uid, path, r.value["sha256"], utcnow(), __version__, True, None, *ok_row(r)]
                con.execute(f"INSERT INTO {table} VALUES ({', '.join('?' * len(row))})", row)
            else:
                row = [uid, path, utcnow(), __version__, False, r.error, *failed_row(r)]
                con.execute(f"INSERT INTO {table} (trial_uid, path, run_utc, rig_version, ok, error, {failed_cols}) "
                            f"VALUES ({', '.join('?' * len(row))})", row)
        con.execute("COMMIT")
    finally:
        con.close()


def record_identify(db: str | Path, results: list[TaskResult], options: dict) -> None:
    """Write batch ``identify`` results (from :func:`rig.catalog.tasks.identify_file`) into ``db``:
    the latest result per file replaces the previous one; failures are recorded with their error."""
    def ok_row(r):
        rep = r.value["report"]
        m, e = rep.get("mean", {}), rep.get("sem", {})
        return [json.dumps(options), rep.get("n_steps"), _num(m, "A_mu"), _num(m, "B_mu"), _num(m, "L_um"),
                _num(e, "A_mu"), _num(e, "B_mu"), _num(e, "L_um"), _num(m, "k_cr_kN_per_m"),
                r.seconds, json.dumps(rep, allow_nan=False)]

    _record(db, "identify_results", results, ok_row, "options, seconds",
            lambda r: [json.dumps(options), r.seconds])


def record_diagnose(db: str | Path, results: list[TaskResult], options: dict) -> None:
    """Write batch ``diagnose`` results (:func:`rig.catalog.tasks.diagnose_file`) into ``db``."""
    def ok_row(r):
        rep = r.value["report"]
        causes = [f.get("cause") for f in rep.get("findings", [])]
        return [rep.get("baseline", {}).get("model"), _num(rep.get("baseline", {}), "holdout_rms_N"),
                _num(rep, "holdout_rms_N"), len(causes), causes, r.seconds, json.dumps(rep, allow_nan=False)]

    _record(db, "diagnose_results", results, ok_row, "baseline, seconds",
            lambda r: [options.get("baseline"), r.seconds])
