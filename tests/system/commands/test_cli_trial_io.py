"""CLI: rig export (CSV, Parquet) / import / info / recover, corrupt chunks, v1 logs, and the CSV spec's bad
inputs (no partial output)."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from rig.cli import app


runner = CliRunner()


@pytest.mark.parametrize("cmd", ["run", "info", "export", "import", "recover"])
def test_help_is_complete(cmd):
    res = runner.invoke(app, [cmd, "--help"])
    assert res.exit_code == 0
    text = res.output
    expected = {"run": ["--sim", "--hardware", "--lubricant", "--out", "--profile", "--friction-model", "--seed"],
                "info": ["--events", "--json"], "export": ["--csv", "--parquet", "--rate", "--strict"],
                "import": ["--out"],
                "recover": ["--out"]}[cmd]
    for opt in expected:
        assert opt in text, (cmd, opt)
