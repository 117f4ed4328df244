"""The lab's archive: every trial file in a DuckDB catalogue, and batch analyses on Dask.

- :mod:`rig.catalog.schema`: the tables (docs/catalog.md), versioned;
- :mod:`rig.catalog.build`: incremental indexing, writing identify/diagnose results;
- :mod:`rig.catalog.query`: SQL from Python;
- :mod:`rig.catalog.batch`: the engine (serial, this process and its own workers, or a Dask scheduler);
- :mod:`rig.catalog.tasks`: the per-file tasks the engine runs.

DuckDB and Dask are imported only when used.
"""

from rig.catalog.build import BuildReport, build, default_db, expand_inputs, find_trial_files
from rig.catalog.query import QueryResult, query
from rig.catalog.schema import SCHEMA_VERSION, CatalogError, open_catalog

__all__ = ["build", "BuildReport", "default_db", "expand_inputs", "find_trial_files", "query", "QueryResult",
           "SCHEMA_VERSION", "CatalogError", "open_catalog"]
