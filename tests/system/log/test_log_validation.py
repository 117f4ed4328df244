"""Every kind of file the project writes (sim, hardware on the emulated rig, recovered, imported) is
read by the ``mcap`` package's own reader with CRCs checked, and, when Node.js and @mcap/core are
installed (``RIG_MCAP_JS``: a directory with node_modules/@mcap/core and @mcap/support), validated
independently by the TypeScript MCAP library (tests/tools/validate_mcap.js)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

from rig.log import read_trial, recover

SMOKE = REPO / "config/recipes/smoke.yaml"
VALIDATOR = Path(__file__).resolve().parents[2] / "tools" / "validate_mcap.js"


def _rig(*args, timeout=120, ok=(0,)):
    p = subprocess.run([sys.executable, "-m", "rig.cli", *map(str, args)], cwd=REPO, capture_output=True,
                       text=True, timeout=timeout)
    assert p.returncode in ok, p.stdout + p.stderr
    return p


def _js_env():
    base = os.environ.get("RIG_MCAP_JS", "/tmp/mcapjs")
    mods = Path(base) / "node_modules"
    if not shutil.which("node") or not (mods / "@mcap" / "core").is_dir():
        return None
    return {**os.environ, "NODE_PATH": str(mods)}


@pytest.fixture(scope="module")
def written(tmp_path_factory, private_profile):
    """sim, hardware (emulated rig), recovered (cut mid-file) and imported logs."""
    d = tmp_path_factory.mktemp("logs")
    files = {"sim": d / "sim.mcap", "hardware": d / "hw.mcap"}
    _rig("run", SMOKE, "--sim", "-q", "--out", files["sim"])
    # on a loaded machine the emulated rig may trip an interlock (exit 1): the log is then finished with
    # status 'failed', still a complete hardware log
    _rig("run", SMOKE, "--hardware", private_profile(d), "--out", files["hardware"], "-q", ok=(0, 1))
    cut = d / "cut.mcap"
    data = files["hardware"].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    files["recovered"] = d / "recovered.mcap"
    recover(cut, files["recovered"])
    _rig("export", files["sim"], "--csv", d / "sim.csv", "--rate", "raw")
    files["imported"] = d / "imported.mcap"
    _rig("import", d / "sim.csv", "--out", files["imported"])
    return files


@pytest.mark.slow
def test_mcap_package_reads_every_kind_of_file_with_crcs(written):
    for kind, path in written.items():
        with open(path, "rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            summary = reader.get_summary()
            n = sum(1 for _ in reader.iter_messages())
        assert n == summary.statistics.message_count > 0, kind
        tr = read_trial(path, "raw")
        assert len(tr) > 0, kind
        if kind != "imported":  # log_time: wall-clock ns since the epoch (after 2020)
            assert summary.statistics.message_start_time > 1_577_836_800 * 10 ** 9, kind


@pytest.mark.slow
def test_independent_validation_with_the_typescript_library(written):
    env = _js_env()
    if env is None:
        pytest.skip("node and @mcap/core not installed (set RIG_MCAP_JS)")
    p = subprocess.run(["node", str(VALIDATOR), *map(str, written.values())], capture_output=True, text=True,
                       env=env, timeout=120)
    results = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
    assert len(results) == len(written) and p.returncode == 0, p.stdout + p.stderr
    for r in results:
        assert r["ok"] and r["footer"] and r["statisticsMessageCount"] == r["indexedMessages"], r
