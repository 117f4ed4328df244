"""Measured trial data: the in-memory record and the CSV interchange format.

The CSV format is ``../shared/specs/measured-data.md`` (version 1), kept to the
letter: ``# rig-trial-csv: 1`` first, ``# key: value`` metadata lines, a header
with at least ``time_s``, ``position_um``, ``friction_N``; optional
``normal_1_N``, ``normal_2_N``, ``position_ref_um``, ``valve_cmd``; extra
columns kept and never an error (numeric ones as float arrays with empty cells
as NaN, any with text as string arrays). Numbers are ASCII only (``١٢٣`` or
``１２`` are not numbers, nor ``1_000``). Bad input raises
:class:`DataFormatError` naming the file, the line and what is wrong (an
invalid ``normal_force_N`` metadata value too); a trailing partial line is a
warning.

:class:`TrialData` is what every analysis (identify, stribeck, diagnose)
consumes, whether it came from a CSV or from the rig's MCAP log
(``rig.log.load_trial`` dispatches on the suffix; this module imports nothing
from the log).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.errors import DataFormatError  # noqa: F401 - defined without numpy, for rig info

CSV_MAGIC = "rig-trial-csv"
CSV_VERSION = "1"
REQUIRED_COLUMNS = ("time_s", "position_um", "friction_N")
OPTIONAL_COLUMNS = ("normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd")
STANDARD_COLUMNS = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
POSITION_SOURCES = ("on_sample", "load_point")  # measured-data.md: where position_um is measured


class PartialLineWarning(UserWarning):
    """The file ends with an incomplete row (cut off mid-write); it was ignored."""


@dataclass
class TrialData:
    """One trial's samples, in the measured-data units (s, µm, N).

    ``normal_force_N`` is the nominal per-rider normal force: the
    ``normal_force_N`` metadata when present, else the median of
    ``(normal_1_N + normal_2_N) / 2`` (measured-data.md).
    ``events`` are the rig log's events (``{"t_s": float, "kind": str, ...}``),
    empty for CSV input.
    """

    time_s: np.ndarray
    position_um: np.ndarray
    friction_N: np.ndarray
    normal_1_N: np.ndarray | None = None
    normal_2_N: np.ndarray | None = None
    position_ref_um: np.ndarray | None = None
    valve_cmd: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)
    events: list[dict] = field(default_factory=list)
    source: str = ""
    warnings: list[str] = field(default_factory=list)

    @property
    def pause_intervals(self) -> list[tuple[float, float]]:
        """The operator's pauses, ``(t_pause_s, t_resume_s)`` (:func:`rig.kinematics.pause_intervals`)."""
        from rig.kinematics import pause_intervals

        return pause_intervals(self.events)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def trial_uid(self) -> str | None:
        """The trial's id (measured-data.md optional key), kept through export, import and copies."""
        return self.metadata.get("trial_uid") or None

    @property
    def specimen(self) -> str | None:
        """The test piece (measured-data.md optional key)."""
        return self.metadata.get("specimen") or None

    @property
    def operator(self) -> str | None:
        return self.metadata.get("operator") or None

    @property
    def is_load_point(self) -> bool:
        """``position_source: load_point`` (measured-data.md): the position is measured at the
        actuator or load point, so the machine's compliance lies between it and the interface.
        The one rule identify and diagnose use; any other value (absent, ``on_sample``, unknown:
        a warning on reading) is on the sample."""
        return str(self.metadata.get("position_source", "on_sample")).strip() == "load_point"

    @property
    def has_normals(self) -> bool:
        return self.normal_1_N is not None and self.normal_2_N is not None

    def positive_metadata(self, key: str, unit: str) -> float | None:
        """The metadata value ``key`` as a positive number (None when absent); ValueError naming the
        trial, the key and the ``unit`` when it is not one."""
        value = self.metadata.get(key)
        if value is None:
            return None
        v = positive_number(value)
        if v is None:
            raise ValueError(f"{self.source or 'trial'}: {key} metadata {value!r} is not a positive number of {unit}")
        return v

    @property
    def normal_force_N(self) -> float:
        """Nominal per-rider normal force N (N)."""
        v = self.positive_metadata("normal_force_N", "newtons")
        if v is not None:
            return v
        if self.has_normals:
            with np.errstate(invalid="ignore"):
                med = float(np.nanmedian((self.normal_1_N + self.normal_2_N) / 2.0)) \
                    if np.isfinite(self.normal_1_N + self.normal_2_N).any() else float("nan")
            if math.isfinite(med) and med > 0:
                return med
            raise ValueError(f"{self.source or 'trial'}: the normal columns' median is {med:g} N and there is no "
                             "normal_force_N metadata; the nominal normal force is unknown")
        raise ValueError(
            f"{self.source or 'trial'}: no normal_force_N metadata and no normal columns; "
            "the nominal normal force is unknown"
        )

    @property
    def total_normal_N(self) -> np.ndarray:
        """Sum of both rider normal forces per sample (N); twice the nominal without normal columns."""
        if self.has_normals:
            return self.normal_1_N + self.normal_2_N
        return np.full(self.time_s.shape, 2.0 * self.normal_force_N)

    @property
    def mu(self) -> np.ndarray:
        """Friction coefficient of one interface, friction / (normal_1 + normal_2) (measured-data.md);
        NaN where the normal forces sum to zero (never a division by zero)."""
        total = self.total_normal_N
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(total != 0.0, self.friction_N / np.where(total != 0.0, total, 1.0), np.nan)

    def columns(self) -> dict[str, np.ndarray]:
        """All present columns in the CSV's canonical order (standard first, then extra)."""
        out: dict[str, np.ndarray] = {}
        for name in STANDARD_COLUMNS:
            arr = getattr(self, name)
            if arr is not None:
                out[name] = arr
        out.update(self.extra)
        return out

    def select(self, mask: np.ndarray) -> "TrialData":
        """A copy holding only the samples where ``mask`` is true."""
        def pick(a):
            return None if a is None else np.asarray(a)[mask]
        return TrialData(
            time_s=self.time_s[mask], position_um=self.position_um[mask], friction_N=self.friction_N[mask],
            normal_1_N=pick(self.normal_1_N), normal_2_N=pick(self.normal_2_N),
            position_ref_um=pick(self.position_ref_um), valve_cmd=pick(self.valve_cmd),
            extra={k: v[mask] for k, v in self.extra.items()}, metadata=dict(self.metadata),
            events=list(self.events), source=self.source, warnings=list(self.warnings),
        )


_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)", re.IGNORECASE | re.ASCII)


def parse_number(text: str) -> float | None:
    """A decimal number in ASCII (``1``, ``-2.5e3``, ``nan``, ``inf``), else None.

    Python's float() also takes other scripts' digits (``١٢٣``, ``１２``) and
    underscores (``1_000``); the interchange format does not."""
    s = text.strip()
    if not _NUMBER.fullmatch(s):
        return None
    return float(s)


def positive_number(value) -> float | None:
    """A metadata value as a finite positive number (:func:`parse_number`), else None."""
    v = parse_number(str(value))
    return v if v is not None and math.isfinite(v) and v > 0 else None


def _parse_float(text: str, path, lineno: int, column: str) -> float:
    v = parse_number(text)
    if v is None:
        raise DataFormatError(path, lineno, f"column '{column}': non-numeric value {text.strip()!r}")
    return v


def _plain_ascii(text: str) -> bool:
    """True when float() cannot accept anything the format rejects (ASCII, no underscores)."""
    return text.isascii() and "_" not in text


SPEC_LAYOUT = "../shared/specs/measured-data.md, section \"Layout\""


def read_csv(path: str | os.PathLike, column_map: dict[str, str] | None = None,
             scale: dict[str, float] | None = None) -> TrialData:
    """Read a measured-data CSV (version 1). Raises :class:`DataFormatError` on bad input.

    A trailing partial row is dropped with a :class:`PartialLineWarning` (also
    recorded in ``TrialData.warnings``).

    ``column_map`` ({our name: the file's column}, ``rig import --map``) reads a lab's other
    acquisition file: its columns are renamed, and its first line need not be the format's
    ``# rig-trial-csv: 1``; ``scale`` ({our name: factor}, ``--scale``) multiplies a column
    (units: mm -> µm is 1000) after reading.
    """
    path = Path(path)
    lines, ends_with_newline = _decoded_lines(path)
    lines, magic = _checked_magic(path, lines, column_map)
    metadata, i = _metadata(path, lines)
    names, header_lineno = _header(path, lines, i, column_map, magic)
    cols, extra, row_lines, file_warnings = _data_rows(path, lines[i + 1:], names, header_lineno,
                                                       ends_with_newline)
    _validate_rows(path, cols, row_lines)
    _apply_scale(path, cols, extra, scale, names, header_lineno)
    return TrialData(
        time_s=cols["time_s"], position_um=cols["position_um"], friction_N=cols["friction_N"],
        normal_1_N=cols.get("normal_1_N"), normal_2_N=cols.get("normal_2_N"),
        position_ref_um=cols.get("position_ref_um"), valve_cmd=cols.get("valve_cmd"),
        extra=extra, metadata=metadata, source=str(path), warnings=file_warnings,
    )


def _decoded_lines(path: Path) -> tuple[list[str], bool]:
    """The file's lines (UTF-8, BOM dropped) and whether it ends with a line break."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataFormatError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DataFormatError(path, line, "not valid UTF-8") from None
    lines = text.splitlines()
    if not lines:
        raise DataFormatError(path, 1, "empty file (expected '# rig-trial-csv: 1' on the first line)")
    return lines, text.endswith("\n") or text.endswith("\r")


def _is_magic(line: str) -> bool:
    first = line.strip()
    return first.startswith("#") and first.lstrip("#").strip().replace(" ", "") == f"{CSV_MAGIC}:{CSV_VERSION}"


def _checked_magic(path: Path, lines: list[str], column_map) -> tuple[list[str], bool]:
    """The lines with the format's first line (supplied for a ``--map`` file that lacks it: line
    numbers below then shift by one), and whether the file had it. Without it and without
    ``--map``: one error pointing at the spec's layout and at ``rig import --map``."""
    magic = _is_magic(lines[0])
    if magic:
        return lines, True
    if column_map is not None:
        return [f"# {CSV_MAGIC}: {CSV_VERSION}"] + lines, False
    raise DataFormatError(
        path, 1, f"first line must be '# {CSV_MAGIC}: {CSV_VERSION}', found {lines[0][:60]!r} "
                 f"(the format: {SPEC_LAYOUT}; a lab's own CSV: rig import {path.name} -o OUT.mcap "
                 "--map time_s=COLUMN,position_um=COLUMN,friction_N=COLUMN)")


def _metadata(path: Path, lines: list[str]) -> tuple[dict[str, str], int]:
    """The ``# key: value`` lines after the first (free text joins ``comment``) and the index of
    the line after them; a bad ``normal_force_N`` is an error, an unknown ``position_source`` a
    warning."""
    metadata: dict[str, str] = {}
    meta_line: dict[str, int] = {}
    i = 1
    while i < len(lines) and lines[i].lstrip().startswith("#"):
        body = lines[i].lstrip()[1:].strip()
        if ":" in body:
            key, value = body.split(":", 1)
            metadata[key.strip()] = value.strip()
            meta_line[key.strip()] = i + 1
        elif body:
            metadata.setdefault("comment", "")
            metadata["comment"] = (metadata["comment"] + " " + body).strip()
        i += 1
    if "normal_force_N" in metadata and positive_number(metadata["normal_force_N"]) is None:
        raise DataFormatError(path, meta_line["normal_force_N"],
                              f"normal_force_N metadata must be a positive number of newtons, found "
                              f"{metadata['normal_force_N']!r}")
    if metadata.get("position_source", "on_sample") not in POSITION_SOURCES:
        msg = (f"{path}, line {meta_line['position_source']}: unknown position_source "
               f"{metadata['position_source']!r} (expected on_sample or load_point); taken as on_sample")
        warnings.warn(msg, UserWarning, stacklevel=3)
    return metadata, i


def _header(path: Path, lines: list[str], i: int, column_map, magic: bool) -> tuple[list[str], int]:
    """The column names of the header at ``lines[i]`` (renamed by ``column_map``) and its line
    number; errors for a missing header, a ``--map`` column the file lacks, duplicate names and
    missing required columns."""
    if i >= len(lines) or not lines[i].strip():
        raise DataFormatError(path, i + 1, "missing header row (column names) after the metadata lines")
    header_lineno = i + 1
    names = [c.strip() for c in lines[i].split(",")]
    if column_map:
        missing_src = [f"{ours}={theirs}" for ours, theirs in column_map.items() if theirs not in names]
        if missing_src:
            raise DataFormatError(path, header_lineno - (0 if magic else 1),
                                  f"--map {', '.join(missing_src)}: no such column (header has: {', '.join(names)})")
        back = {theirs: ours for ours, theirs in column_map.items()}
        names = [back.get(n, n) for n in names]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DataFormatError(path, header_lineno, f"duplicate column name(s): {', '.join(dup)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise DataFormatError(path, header_lineno,
                              f"missing required column(s): {', '.join(missing)} (header has: {', '.join(names)})")
    return names, header_lineno


def _data_rows(path: Path, data_lines: list[str], names: list[str], header_lineno: int,
               ends_with_newline: bool):
    """The data rows: (standard columns by name, extra columns, each row's line number, warnings).
    A well-formed block goes through Arrow in one pass; anything irregular through the line
    parser, which names the line and the fault."""
    std_idx = [j for j, n in enumerate(names) if n in STANDARD_COLUMNS]
    extra_idx = [j for j, n in enumerate(names) if n not in STANDARD_COLUMNS]
    block = "\n".join(data_lines)
    fast = _plain_ascii(block)
    parsed = _parse_block_fast(block, data_lines, names, std_idx, extra_idx) \
        if fast and ends_with_newline and data_lines else None
    file_warnings: list[str] = []
    if parsed is not None:  # every line well formed: no per-line Python (a 3.6 M-row hour in seconds)
        table, extra_text = parsed
        row_lines = range(header_lineno + 1, header_lineno + 1 + len(data_lines))
    else:
        rows, row_texts, row_lines = _parse_lines(path, data_lines, names, std_idx, extra_idx, header_lineno,
                                                  ends_with_newline, fast, file_warnings)
        table = np.asarray(rows, dtype=float)
        extra_text = [[r[c] for r in row_texts] for c in range(len(extra_idx))]
    if len(row_lines) == 0:
        raise DataFormatError(path, header_lineno, "empty data: no rows after the header")
    cols = {names[j]: table[:, c] for c, j in enumerate(std_idx)}
    extra = {names[j]: _extra_column(extra_text[c]) for c, j in enumerate(extra_idx)}
    return cols, extra, row_lines, file_warnings


def _extra_column(texts: list[str]) -> np.ndarray:
    """An extra column: floats (empty cells NaN) when every cell is a number, else its strings
    (text is kept, never an error)."""
    nums = [parse_number(t) if t else math.nan for t in texts]
    if all(v is not None for v in nums):
        return np.asarray(nums, dtype=float)
    return np.asarray(texts, dtype=str)


def _partial_line(path: Path, lineno: int, file_warnings: list[str]) -> None:
    msg = f"{path}, line {lineno}: trailing partial line ignored (file cut off mid-write)"
    warnings.warn(msg, PartialLineWarning, stacklevel=5)
    file_warnings.append(msg)


def _parse_lines(path, data_lines, names, std_idx, extra_idx, header_lineno, ends_with_newline, fast,
                 file_warnings):
    """The line-by-line parser: (rows of the standard columns, rows of the extra columns' text,
    line numbers). Names the line and the field of the first fault; a cut-off last line is a
    :class:`PartialLineWarning`."""
    ncol = len(names)
    rows: list[list[float]] = []
    row_texts: list[list[str]] = []
    row_lines: list[int] = []
    for k, line in enumerate(data_lines):
        lineno = header_lineno + 1 + k
        if not line.strip():
            continue
        fields = line.split(",")
        is_last = k == len(data_lines) - 1
        if len(fields) != ncol:
            if is_last and not ends_with_newline and len(fields) < ncol:
                _partial_line(path, lineno, file_warnings)
                break
            raise DataFormatError(path, lineno, f"expected {ncol} fields, found {len(fields)}")
        try:
            if fast:
                values = [float(fields[j]) if fields[j].strip() or names[j] in REQUIRED_COLUMNS
                          else math.nan for j in std_idx]
            else:
                values = [_strict(fields[j], names[j]) for j in std_idx]
        except ValueError:
            if is_last and not ends_with_newline:
                # a number cut in half can still parse; one that does not is a partial line
                _partial_line(path, lineno, file_warnings)
                break
            _raise_field_error(path, lineno, fields, names, std_idx)
        rows.append(values)
        row_texts.append([fields[j].strip() for j in extra_idx])
        row_lines.append(lineno)
    return rows, row_texts, row_lines


def _raise_field_error(path, lineno: int, fields: list[str], names: list[str], std_idx: list[int]):
    """The error for the first bad field of a row: an empty required value or a non-number."""
    for j in std_idx:
        if not fields[j].strip() and names[j] in REQUIRED_COLUMNS:
            raise DataFormatError(path, lineno, f"column '{names[j]}': empty value") from None
        if fields[j].strip():
            _parse_float(fields[j], path, lineno, names[j])
    raise DataFormatError(path, lineno, "unreadable row")  # pragma: no cover - raised above


def _validate_rows(path, cols: dict[str, np.ndarray], row_lines) -> None:
    """Required columns finite, ``time_s`` strictly increasing; the error names the first bad line."""
    for name in REQUIRED_COLUMNS:
        bad = np.flatnonzero(~np.isfinite(cols[name]))
        if bad.size:
            raise DataFormatError(path, row_lines[bad[0]], f"column '{name}': NaN or infinite value")
    t = cols["time_s"]
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if bad.size:
        j = bad[0] + 1
        raise DataFormatError(path, row_lines[j],
                              f"time_s not strictly increasing ({float(t[j - 1])!r} then {float(t[j])!r})")


def _apply_scale(path, cols, extra, scale, names, header_lineno) -> None:
    """``--scale COLUMN=FACTOR``: multiply a numeric column in place (a lab's units to ours)."""
    for name, factor in (scale or {}).items():
        if name in cols:
            cols[name] = cols[name] * float(factor)
        elif name in extra and extra[name].dtype.kind == "f":
            extra[name] = extra[name] * float(factor)
        else:
            raise DataFormatError(path, header_lineno, f"--scale {name}={factor:g}: no numeric column {name!r} "
                                                       f"(columns: {', '.join(names)})")
    if scale and "time_s" in scale and not float(scale["time_s"]) > 0:
        raise DataFormatError(path, header_lineno, "--scale time_s must be positive (time must increase)")


def _parse_block_fast(block: str, data_lines: list[str], names: list[str], std_idx: list[int],
                      extra_idx: list[int]):
    """The data rows parsed in one pass by Arrow's CSV reader, or None whenever anything is
    irregular (a blank line, a wrong field count, a quote, a field that is not a plain number,
    an empty required value): :func:`read_csv`'s line-by-line parser then finds and names it.
    Returns (table of the standard columns, one list of strings per extra column)."""
    if any(not ln.strip() for ln in data_lines):
        return None
    try:
        import pyarrow as pa
        import pyarrow.csv as pacsv
    except ImportError:  # pragma: no cover - a declared dependency
        return None
    types = {names[j]: pa.float64() for j in std_idx}
    types.update({names[j]: pa.string() for j in extra_idx})
    try:
        tab = pacsv.read_csv(
            pa.py_buffer(block.encode("ascii")),
            read_options=pacsv.ReadOptions(column_names=[f"c{j}" for j in range(len(names))],
                                           use_threads=True),
            parse_options=pacsv.ParseOptions(delimiter=",", quote_char=False, double_quote=False,
                                             escape_char=False, newlines_in_values=False,
                                             ignore_empty_lines=False),
            convert_options=pacsv.ConvertOptions(
                column_types={f"c{j}": types[names[j]] for j in range(len(names))},
                null_values=[""], strings_can_be_null=False, quoted_strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, ValueError):
        return None
    if tab.num_rows != len(data_lines):
        return None
    table = np.empty((tab.num_rows, len(std_idx)))
    for c, j in enumerate(std_idx):
        col = tab.column(f"c{j}")
        if col.null_count and names[j] in REQUIRED_COLUMNS:
            return None  # an empty required value: named by the line parser
        table[:, c] = col.to_numpy(zero_copy_only=False)  # null (an empty optional value) -> NaN
    extra_text = [[t.strip() for t in tab.column(f"c{j}").to_pylist()] for j in extra_idx]
    return table, extra_text


def _strict(text: str, name: str) -> float:
    """One standard-column field: ASCII number; empty is NaN in optional columns (ValueError otherwise)."""
    if not text.strip():
        if name in REQUIRED_COLUMNS:
            raise ValueError("empty")
        return math.nan
    v = parse_number(text)
    if v is None:
        raise ValueError(text)
    return v


def _fmt(x: float) -> str:
    if not math.isfinite(x):
        return "nan"
    return repr(float(x)) if abs(x) >= 1e15 or (x != 0 and abs(x) < 1e-6) else f"{x:.9g}"


def write_csv(trial: TrialData, path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """Write ``trial`` as a measured-data CSV (version 1), atomically.

    The file appears complete or not at all (written to a temporary file in the
    same directory, then renamed). ``overwrite=False``: FileExistsError when ``path`` exists
    (checked atomically at the rename). The trial's ``trial_uid``, ``specimen``, ``operator`` and
    other metadata are ``# key: value`` lines (measured-data.md).
    """
    path = Path(path)
    cols = trial.columns()
    buf = io.StringIO()
    buf.write(f"# {CSV_MAGIC}: {CSV_VERSION}\n")
    meta = dict(trial.metadata)
    meta.pop(CSV_MAGIC, None)
    if "normal_force_N" not in meta:
        try:
            meta["normal_force_N"] = f"{trial.normal_force_N:g}"
        except ValueError:
            pass
    for key, value in meta.items():
        value = str(value).replace("\r", " ").replace("\n", " ")
        buf.write(f"# {key}: {value}\n")
    names = list(cols)
    buf.write(",".join(names) + "\n")
    text_cols = {n for n in names if np.asarray(cols[n]).dtype.kind in "USO"}
    if not text_cols:
        table = np.column_stack([np.asarray(cols[n], dtype=float) for n in names])
        for row in table:
            buf.write(",".join(_fmt(v) for v in row) + "\n")
    else:
        series = [[str(v) for v in cols[n]] if n in text_cols else [_fmt(v) for v in np.asarray(cols[n], float)]
                  for n in names]
        for row in zip(*series):
            buf.write(",".join(row) + "\n")
    atomic_write_text(path, buf.getvalue(), overwrite=overwrite)
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` (after fsync),
    on any error it is removed. The file at ``path`` is complete or absent, never half-written.
    ``overwrite=False``: the temporary file is linked to ``path`` instead (atomic, no clobber):
    FileExistsError when ``path`` exists, which is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # like open(): colleagues can read results (mkstemp makes 0600)
    try:
        yield Path(tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
            os.unlink(tmp)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> None:
    """Write ``data`` to ``path`` so that the file is complete or absent, never half-written."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def content_uid(sha256_hex: str) -> str:
    """The trial id of a file that carries none (a CSV from another system): a UUID (version 5) of its
    content's sha256, so the file, its moved copies and the log ``rig import`` makes from it are one trial."""
    import uuid

    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"rig-trial:sha256:{sha256_hex}"))


# ---------------------------------------------------------------------------
# calibration: what the force channels' records say about a trial's numbers (issue 21)
# ---------------------------------------------------------------------------

#: the force channels of a trial and their TrialData columns
FORCE_CHANNELS = {"friction": "friction_N", "normal_1": "normal_1_N", "normal_2": "normal_2_N"}


def calibration_records_of(trial: TrialData) -> dict[str, dict]:
    """The calibration snapshot a trial log recorded (``calibration`` metadata: JSON by channel), {} when none."""
    import json

    text = trial.metadata.get("calibration")
    if not text:
        return {}
    try:
        doc = json.loads(text)
    except ValueError:
        return {}
    return {k: v for k, v in doc.items() if isinstance(v, dict)} if isinstance(doc, dict) else {}


def calibration_warnings(trial: TrialData, effects_N: dict[str, float] | None = None) -> list[dict]:
    """Warnings (``{where, message}``) when a trial's numbers rest on more than its calibration covers:

    * a force channel read outside its ``verified_range_N`` (its share of the samples is named);
    * a fitted effect (``effects_N``: name -> size in N of the friction force it explains) smaller
      than the friction channel's stated ``uncertainty_N``.

    Nothing when the trial has no calibration snapshot (a CSV from another system, an older log)."""
    cal = calibration_records_of(trial)
    out: list[dict] = []
    for ch, col in FORCE_CHANNELS.items():
        rec = cal.get(ch) or {}
        rng = rec.get("verified_range_N")
        x = getattr(trial, col)
        if not rng or x is None or len(rng) != 2:
            continue
        a = np.abs(np.asarray(x, dtype=float))
        a = a[np.isfinite(a)]
        outside = float(np.mean((a < rng[0]) | (a > rng[1]))) if a.size else 0.0
        if outside > 0:
            out.append({"where": f"calibration of {ch} ({rec.get('serial')})",
                        "message": f"{outside * 100:.1f} % of its readings lie outside the verified range "
                                   f"{rng[0]:g}..{rng[1]:g} N (|force|, certificate {rec.get('certificate')})"})
    u = (cal.get("friction") or {}).get("uncertainty_N")
    for name, size in (effects_N or {}).items():
        if u and size is not None and math.isfinite(size) and abs(size) < u:
            out.append({"where": f"calibration of friction ({cal['friction'].get('serial')})",
                        "message": f"{name}: {abs(size):.3g} N is smaller than the friction channel's stated "
                                   f"uncertainty {u:g} N"})
    return out
