"""The trial log: one MCAP file per trial (written by the ``mcap`` package's Writer).

Channels (layout and codecs: :mod:`rig.log.schemas`):

``/raw`` (message encoding ``rig.columns.v2``)
    The 1 kHz loop data as blocks (1 s by default) of columns stored as the
    devices deliver them: integer counts with scale, offset and unit in the
    channel's schema, derived floats as float32, delta/shuffle filtered.
    A documented binary that Foxglove does not decode; its JSON twin is
    ``/log25``. Older logs (``rig.columns.v1``, JSON blocks) are read alike.
``/log25`` (JSON schema ``rig.Sample``)
    One message per sample at the decimated rate (25 Hz like the paper's log,
    section 4.2): ``t_s, position_um, friction_N, normal_1_N, normal_2_N,
    position_ref_um, valve_cmd, mu``. What Foxglove plots
    (``config/foxglove/rig-trial.json``).
``/events`` (``rig.Event``), ``/loop_stats`` (``rig.LoopStats``), JSON.

The same JSON channels are served live, while a trial runs, over the Foxglove
WebSocket protocol by :mod:`rig.log.live` (``rig run --live``).

``log_time`` = wall-clock ns since the Unix epoch (trial start + ``t_s``);
``t_s`` stays a field. Metadata records: ``trial`` (recipe, lubricant,
normal_force_N, seed, software_version, rates, ``start_time_ns``), ``recipe``,
``rig_profile``, ``trial_end``, and ``recovery`` in a recovered file. Every
chunk's CRC is verified on read (:mod:`rig.log.reader`).

:func:`load_trial` dispatches a ``.csv`` (:func:`rig.data.read_csv`), a ``.parquet``
(:func:`read_parquet`, as ``rig export`` writes it) or a ``.mcap`` (:func:`read_trial`); it lives here, above :mod:`rig.data`, which
imports nothing from the log.
"""

from __future__ import annotations

import os
from pathlib import Path

from typing import TYPE_CHECKING

from rig.errors import DataFormatError
from rig.log.reader import LogDamageWarning, read_log, read_metadata, read_trial, scan, trial_info
from rig.log.topics import EVENTS_TOPIC, LOG25_TOPIC, RAW_TOPIC, STATS_TOPIC

if TYPE_CHECKING:
    from rig.data import TrialData
    from rig.log.schemas import BLOCK_KEYS, RAW_V1_ENCODING, RAW_V2_ENCODING, SAMPLE_FIELDS
    from rig.log.csv_import import read_parquet, write_parquet, write_trial_data
    from rig.log.recover import recover
    from rig.log.writer import TrialLogWriter

#: imported when first used, so that reading a log (rig info, export) does not load the writer's stack, and
#: ``rig info`` (reader.trial_info) does not load numpy (the layouts' codecs, :mod:`rig.log.schemas`)
_LAZY = {"TrialLogWriter": "rig.log.writer", "recover": "rig.log.recover", "read_parquet": "rig.log.csv_import",
         "write_parquet": "rig.log.csv_import", "write_trial_data": "rig.log.csv_import",
         **dict.fromkeys(("BLOCK_KEYS", "RAW_V1_ENCODING", "RAW_V2_ENCODING", "SAMPLE_FIELDS"), "rig.log.schemas")}


def __getattr__(name: str):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'rig.log' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value
    return value


def load_trial(path: str | os.PathLike, *, strict: bool = False) -> TrialData:
    """Load a trial from a measured-data ``.csv``, its ``.parquet`` twin or a rig ``.mcap`` log (25 Hz channel)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        from rig.data import read_csv

        return read_csv(path)
    if suffix == ".parquet":
        from rig.log.csv_import import read_parquet

        return read_parquet(path)
    if suffix == ".mcap":
        return read_trial(path, strict=strict)
    raise DataFormatError(path, None, f"unknown data file type {suffix!r} (expected .csv, .parquet or .mcap)")


__all__ = ["TrialLogWriter", "read_trial", "read_metadata", "read_log", "scan", "trial_info", "recover",
           "write_trial_data", "write_parquet", "read_parquet", "load_trial", "LogDamageWarning", "RAW_TOPIC", "LOG25_TOPIC",
           "EVENTS_TOPIC", "STATS_TOPIC", "SAMPLE_FIELDS", "BLOCK_KEYS", "RAW_V1_ENCODING", "RAW_V2_ENCODING"]
