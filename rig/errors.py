"""The error a data file that breaks its format raises (:class:`DataFormatError`), in a module of its own
that imports nothing: reading a log's summary (``rig info``) raises it without loading numpy and the
data layer (:mod:`rig.data`, which re-exports it and is where the formats are)."""

from __future__ import annotations

import os


class DataFormatError(ValueError):
    """A data file breaks its format. ``str()`` names the file, the line and the fault."""

    def __init__(self, path: str | os.PathLike, line: int | None, message: str):
        self.path = str(path)
        self.line = line
        self.message = message
        where = f"{self.path}, line {line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")
