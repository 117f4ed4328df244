"""The catalogue's DuckDB schema (documented in docs/catalog.md; keep the two in step).

Version 2 (issue 21: trials keyed by their ``trial_uid``, files as attributes).
:func:`open_catalog` creates the tables in a new file and refuses a file written
with another schema version (one clear error, never a silent migration).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

SCHEMA_VERSION = 2
DEFAULT_DB_NAME = "catalog.duckdb"

#: the first columns of every results table: the trial, the file and its hash the result is of, when and by
#: which version it was computed, whether it worked (the ``catalog`` view reads them alike)
_RESULT_KEY_COLUMNS = ("trial_uid VARCHAR PRIMARY KEY, path VARCHAR, sha256 VARCHAR, run_utc TIMESTAMP, "
                       "rig_version VARCHAR, ok BOOLEAN, error VARCHAR")

TABLES = {
    "schema_version": """
        CREATE TABLE IF NOT EXISTS schema_version (
            version      INTEGER NOT NULL,
            created_utc  TIMESTAMP NOT NULL,
            rig_version  VARCHAR NOT NULL
        )""",
    "files": """
        CREATE TABLE IF NOT EXISTS files (
            path         VARCHAR PRIMARY KEY,
            kind         VARCHAR,
            size_bytes   BIGINT,
            mtime_ns     BIGINT,
            sha256       VARCHAR,
            indexed_utc  TIMESTAMP,
            ok           BOOLEAN,
            error        VARCHAR,
            reads        INTEGER,
            trial_uid    VARCHAR
        )""",
    "trial_files": """
        CREATE TABLE IF NOT EXISTS trial_files (
            path           VARCHAR PRIMARY KEY,
            trial_uid      VARCHAR NOT NULL,
            uid_source     VARCHAR,
            sha256         VARCHAR,
            kind           VARCHAR,
            recipe         VARCHAR,
            lubricant      VARCHAR,
            specimen       VARCHAR,
            operator       VARCHAR,
            note           VARCHAR,
            rig_profile    VARCHAR,
            backend        VARCHAR,
            started_utc    TIMESTAMP,
            duration_s     DOUBLE,
            status         VARCHAR,
            log_status     VARCHAR,
            normal_force_N DOUBLE,
            seed           BIGINT,
            n_samples      BIGINT,
            n_events       INTEGER,
            slip_mm        DOUBLE,
            written_by     VARCHAR,
            metadata       JSON
        )""",
    "identify_results": f"""
        CREATE TABLE IF NOT EXISTS identify_results (
            {_RESULT_KEY_COLUMNS},
            options         JSON,
            n_steps         INTEGER,
            A_mu            DOUBLE,
            B_mu            DOUBLE,
            L_um            DOUBLE,
            A_mu_sem        DOUBLE,
            B_mu_sem        DOUBLE,
            L_um_sem        DOUBLE,
            k_cr_kN_per_m   DOUBLE,
            seconds         DOUBLE,
            report          JSON
        )""",
    "diagnose_results": f"""
        CREATE TABLE IF NOT EXISTS diagnose_results (
            {_RESULT_KEY_COLUMNS},
            baseline               VARCHAR,
            baseline_holdout_rms_N DOUBLE,
            holdout_rms_N          DOUBLE,
            n_findings             INTEGER,
            causes                 VARCHAR[],
            seconds                DOUBLE,
            report                 JSON
        )""",
}

#: what a result column says when it was never computed (the ``results`` column of ``catalog``)
NOT_COMPUTED = "not computed: run `rig {0} DIR`"

VIEWS = {
    # one row per trial (its trial_uid): the columns of its primary file (the log rather than an export,
    # the original rather than a recovery, then by path), and every file that holds it
    "trials": """
        CREATE OR REPLACE VIEW trials AS
        WITH ranked AS (
            SELECT *, row_number() OVER (PARTITION BY trial_uid
                                         ORDER BY (kind <> 'mcap'), (status = 'recovered'), path) AS rank_
            FROM trial_files),
        grouped AS (
            SELECT trial_uid, list(path ORDER BY path) AS paths, list(sha256 ORDER BY path) AS sha256s,
                   count(*) AS n_files
            FROM trial_files GROUP BY trial_uid)
        SELECT r.* EXCLUDE (rank_), g.paths, g.sha256s, g.n_files
        FROM ranked r JOIN grouped g USING (trial_uid)
        WHERE r.rank_ = 1""",
    "catalog": f"""
        CREATE OR REPLACE VIEW catalog AS
        SELECT t.trial_uid, t.path, t.paths, t.n_files, t.kind, t.recipe, t.lubricant, t.specimen, t.operator,
               t.note, t.rig_profile, t.backend, t.started_utc, t.duration_s, t.status, t.normal_force_N, t.seed,
               t.n_samples, t.slip_mm, t.sha256,
               i.A_mu, i.B_mu, i.L_um, i.k_cr_kN_per_m, i.n_steps, i.rig_version AS identify_version,
               i.ok AS identify_ok, list_contains(t.sha256s, i.sha256) AS identify_current,
               d.causes, d.n_findings, d.holdout_rms_N, d.rig_version AS diagnose_version,
               d.ok AS diagnose_ok, list_contains(t.sha256s, d.sha256) AS diagnose_current,
               concat_ws('; ',
                   CASE WHEN i.trial_uid IS NULL THEN 'identify {NOT_COMPUTED.format("identify")}'
                        WHEN NOT i.ok THEN 'identify failed: ' || coalesce(i.error, '?')
                        WHEN NOT list_contains(t.sha256s, i.sha256) THEN 'identify stale: the file changed since'
                        ELSE 'identify done' END,
                   CASE WHEN d.trial_uid IS NULL THEN 'diagnose {NOT_COMPUTED.format("diagnose")}'
                        WHEN NOT d.ok THEN 'diagnose failed: ' || coalesce(d.error, '?')
                        WHEN NOT list_contains(t.sha256s, d.sha256) THEN 'diagnose stale: the file changed since'
                        ELSE 'diagnose done' END) AS results
        FROM trials t
        LEFT JOIN identify_results i ON i.trial_uid = t.trial_uid
        LEFT JOIN diagnose_results d ON d.trial_uid = t.trial_uid""",
    # test pieces wear: trials per specimen, first and last use, cumulative slip
    "specimens": """
        CREATE OR REPLACE VIEW specimens AS
        SELECT specimen, count(*) AS trials, min(started_utc) AS first_used_utc, max(started_utc) AS last_used_utc,
               sum(slip_mm) AS cumulative_slip_mm, list(DISTINCT lubricant ORDER BY lubricant) AS lubricants,
               list(DISTINCT operator ORDER BY operator) FILTER (WHERE operator IS NOT NULL) AS operators
        FROM trials WHERE specimen IS NOT NULL AND specimen <> ''
        GROUP BY specimen""",
}


class CatalogError(RuntimeError):
    """The catalogue cannot be opened or used (names the file and the fault)."""


def utcnow() -> _dt.datetime:
    """Now, as a naive UTC timestamp (the catalogue's TIMESTAMP columns are UTC)."""
    return _dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)


def open_catalog(db: str | Path, *, read_only: bool = False):
    """Open (creating when missing, unless ``read_only``) a catalogue; checks the schema version."""
    import duckdb

    db = Path(db)
    if read_only and not db.exists():
        raise CatalogError(f"{db}: no such catalogue (build it with `rig catalog build DIR`)")
    if not read_only:
        db.parent.mkdir(parents=True, exist_ok=True)
    try:
        con = duckdb.connect(str(db), read_only=read_only)
    except duckdb.Error as exc:
        raise CatalogError(f"{db}: cannot open the catalogue: {str(exc).splitlines()[0]}") from exc
    try:
        have = {r[0] for r in con.execute("SELECT table_name FROM information_schema.tables").fetchall()}
        if "schema_version" in have:
            row = con.execute("SELECT max(version) FROM schema_version").fetchone()
            if row and row[0] is not None and row[0] != SCHEMA_VERSION:
                raise CatalogError(f"{db}: catalogue schema version {row[0]}, this rig reads version "
                                   f"{SCHEMA_VERSION}; rebuild it into a new file (docs/catalog.md)")
        elif read_only:
            raise CatalogError(f"{db}: not a rig catalogue (no schema_version table)")
        elif (have & set(TABLES)) - {"schema_version"}:
            raise CatalogError(f"{db}: has catalogue tables but no schema_version; not a rig catalogue")
        if not read_only:
            from rig import __version__

            for ddl in TABLES.values():
                con.execute(ddl)
            for ddl in VIEWS.values():
                con.execute(ddl)
            if con.execute("SELECT count(*) FROM schema_version").fetchone()[0] == 0:
                con.execute("INSERT INTO schema_version VALUES (?, ?, ?)", [SCHEMA_VERSION, utcnow(), __version__])
    except BaseException:
        con.close()
        raise
    return con
