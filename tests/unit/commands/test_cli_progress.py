"""Progress bars of the long analyses (reproduce, stability --simulate, diagnose): on a
terminal they show; with ``--json -`` or when standard output is not a terminal (a pipe, a
file, CI) nothing of them reaches either stream."""

from __future__ import annotations

import io
import json

from rich.console import Console

from rig.commands.common import progress_bar, show_progress


def _consoles(terminal: bool):
    out = Console(file=io.StringIO(), force_terminal=terminal, width=100)
    err_buf = io.StringIO()
    return out, Console(file=err_buf, force_terminal=terminal, width=100), err_buf


def test_bar_shows_on_a_terminal():
    out, err, buf = _consoles(True)
    assert show_progress(None, out)
    with progress_bar(None, "kp scan", total=4, unit="runs", out_console=out, bar_console=err) as bar:
        for _ in range(4):
            bar.advance()
        bar.update(description="boundary (PD): kp scan")
    assert "kp scan" in buf.getvalue()


def test_bar_silent_with_json_to_stdout_or_no_terminal():
    for terminal, json_out in ((True, "-"), (False, None), (False, "r.json")):
        out, err, buf = _consoles(terminal)
        assert not show_progress(json_out, out)
        with progress_bar(json_out, "diagnosing", out_console=out, bar_console=err) as bar:
            bar.advance()
            bar.update(description="diagnosing: trying sensor_lag")
        assert buf.getvalue() == ""
