"""`rig info` stays light (issue 25: under 0.3 s): reading a log's summary loads neither numpy nor the
data layer, nor Dask or scipy, nor pydantic (typer's adapters: rig.commands.common.quick_coercion) (a fresh
interpreter: the test process has them all loaded)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

LOG = Path(__file__).resolve().parents[2] / "data" / "v1-sim-1khz.mcap"


@pytest.mark.parametrize("args", [[], ["--json", "-"]])
def test_rig_info_imports_no_numpy(args):
    code = ("import sys, json; sys.argv = ['rig', 'info', *sys.argv[1:]]\n"
            "from rig.cli import main\n"
            "try:\n    main()\nexcept SystemExit as exc:\n    assert not exc.code, exc.code\n"
            "print(json.dumps(sorted(m for m in ('numpy', 'rig.data', 'distributed', 'scipy', 'pydantic') if m in sys.modules)))")
    p = subprocess.run([sys.executable, "-c", code, str(LOG), *args], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "COLUMNS": "200"})
    assert p.returncode == 0, p.stderr
    assert "complete, every chunk's CRC verified" in p.stdout or '"complete": true' in p.stdout
    assert json.loads(p.stdout.strip().splitlines()[-1]) == []
