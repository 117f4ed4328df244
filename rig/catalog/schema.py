"""The catalogue's DuckDB schema (documented in docs/catalog.md; keep the two in step).

Version 1. :func:`open_catalog` creates the tables in a new file and refuses a
file written with another schema version (one clear error, never a silent
migration).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

SCHEMA_VERSION = 1
DEFAULT_DB_NAME = "catalog.duckdb"

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
            reads        INTEGER
        )""",
    "trials": """
        CREATE TABLE IF NOT EXISTS trials (
            path           VARCHAR PRIMARY KEY,
            sha256         VARCHAR,
            kind           VARCHAR,
            recipe         VARCHAR,
            lubricant      VARCHAR,
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
            written_by     VARCHAR,
            metadata       JSON
        )""",
    "identify_results": """
        CREATE TABLE IF NOT EXISTS identify_results (
            path            VARCHAR PRIMARY KEY,
            sha256          VARCHAR,
            run_utc         TIMESTAMP,
            rig_version     VARCHAR,
            ok              BOOLEAN,
            error           VARCHAR,
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
    "diagnose_results": """
        CREATE TABLE IF NOT EXISTS diagnose_results (
            path                   VARCHAR PRIMARY KEY,
            sha256                 VARCHAR,
            run_utc                TIMESTAMP,
            rig_version            VARCHAR,
            ok                     BOOLEAN,
            error                  VARCHAR,
            baseline               VARCHAR,
            baseline_holdout_rms_N DOUBLE,
            holdout_rms_N          DOUBLE,
            n_findings             INTEGER,
            causes                 VARCHAR[],
            seconds                DOUBLE,
            report                 JSON
        )""",
}

VIEWS = {
    "catalog": """
        CREATE OR REPLACE VIEW catalog AS
        SELECT t.path, t.kind, t.recipe, t.lubricant, t.rig_profile, t.backend, t.started_utc, t.duration_s,
               t.status, t.normal_force_N, t.seed, t.n_samples, t.sha256,
               i.A_mu, i.B_mu, i.L_um, i.k_cr_kN_per_m, i.n_steps, i.rig_version AS identify_version,
               i.ok AS identify_ok, (i.sha256 = t.sha256) AS identify_current,
               d.causes, d.n_findings, d.holdout_rms_N, d.rig_version AS diagnose_version,
               d.ok AS diagnose_ok, (d.sha256 = t.sha256) AS diagnose_current
        FROM trials t
        LEFT JOIN identify_results i ON i.path = t.path
        LEFT JOIN diagnose_results d ON d.path = t.path""",
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
