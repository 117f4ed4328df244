"""A trial run to one MCAP file: open the log with the trial's metadata, run the session, close it."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any, Callable

from rig.session.core import Backend, FlushPaced, TrialResult, run_trial


def git_describe() -> str:
    """The repository's commit (and '-dirty'), for the trial metadata; '' outside a git checkout."""
    repo = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(repo), "describe", "--always", "--dirty", "--abbrev=12"],
                             capture_output=True, text=True, timeout=3)
        return out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        return ""


def open_log(path: Path, plan, recipe, profile, metadata: dict, flush_interval_s: float = 1.0,
             exclusive: bool = True):
    """A :class:`rig.log.TrialLogWriter` for one trial of ``recipe`` (raises OSError; ``exclusive``:
    the file is created with O_EXCL, FileExistsError when it exists: a trial is never overwritten)."""
    from rig.log import TrialLogWriter

    return TrialLogWriter(path, loop_rate_hz=plan.loop_rate_hz, decimated_rate_hz=recipe.log.decimated_rate_hz,
                          raw_rate_hz=recipe.log.raw_rate_hz, metadata=metadata,
                          recipe_yaml=recipe.source_text, recipe=recipe.model_dump(mode="json"),
                          profile=profile.model_dump(mode="json"),
                          raw_encoding=recipe.log.raw_encoding, raw_dtype=recipe.log.raw_dtype,
                          raw_format=recipe.log.raw_format, flush_interval_s=flush_interval_s,
                          exclusive=exclusive,
                          compact=True)  # a real-time trial's small chunks rewritten at close (docs/trial.md)


def run_to_log(path: Path, plan, recipe, profile, backend: Backend, metadata: dict, *,
               on_open: Callable[[Any], Any] | None = None, **session_kw) -> TrialResult:
    """Open the log (OSError if it cannot be written), run the session on ``backend``, close the log.

    ``on_open(writer)``: called once the log is open, before the trial starts (``rig run --live``
    attaches its :class:`rig.log.live.LiveView` there)."""
    # the backend says how often its log is flushed and fsync'd (HardwareBackend: 0.5 s of wall time,
    # so a crashed logger loses at most about half a second; a simulated trial: every second)
    writer = open_log(path, plan, recipe, profile, metadata,
                      flush_interval_s=backend.log_flush_interval_s if isinstance(backend, FlushPaced) else 1.0)
    if on_open is not None:
        on_open(writer)
    fields = {"recipe": recipe.name, "lubricant": recipe.lubricant}
    fields.update(session_kw.pop("trial_fields", {}))
    return run_trial(plan, backend, writer, trial_fields=fields, **session_kw)
