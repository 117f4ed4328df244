"""Progress bars of the long analyses (reproduce, stability --simulate, diagnose): on a
terminal they show; with ``--json -`` or when standard output is not a terminal (a pipe, a
file, CI) nothing of them reaches either stream."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from rig.cli import app


def test_reproduce_no_progress_when_not_a_terminal():
    res = CliRunner().invoke(app, ["reproduce", "--engine", "synth", "--trials", "2", "--lubricant", "boundary",
                                   "--jobs", "1", "--json", "-"])
    assert res.exit_code == 0, res.output
    rep = json.loads(res.stdout)
    assert "boundary" in rep["lubricants"] and "warnings" in rep
    assert "simulating and identifying" not in res.output
