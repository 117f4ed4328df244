"""Querying the catalogue from Python: :func:`query` returns column names and rows."""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.catalog.schema import CatalogError, open_catalog


@dataclass
class QueryResult:
    columns: list[str]
    rows: list[tuple]

    def records(self) -> list[dict[str, Any]]:
        """One dict per row (column -> value)."""
        return [dict(zip(self.columns, r)) for r in self.rows]

    def to_json(self) -> str:
        return json.dumps(self.records(), default=_plain, indent=2)


def _plain(o):
    if isinstance(o, (_dt.datetime, _dt.date)):
        return o.isoformat()
    return str(o)


def query(db: str | Path, sql: str, params: list | None = None) -> QueryResult:
    """Run ``sql`` on the catalogue ``db`` (read-only) and return its columns and rows.
    A bad query raises :class:`CatalogError` with DuckDB's message."""
    import duckdb

    con = open_catalog(db, read_only=True)
    try:
        try:
            cur = con.execute(sql, params or [])
            rows = cur.fetchall()
            cols = [d[0] for d in (cur.description or [])]
        except duckdb.Error as exc:
            raise CatalogError(f"{db}: query failed: {str(exc).strip()}") from exc
    finally:
        con.close()
    return QueryResult(cols, rows)
