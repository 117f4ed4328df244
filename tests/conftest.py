"""Shared test fixtures: repository paths, the shared data folder, and a damaged copy of a log."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

# A test session's `rig run --sim` processes (subprocesses and CliRunner calls alike) use numba's JIT kernels
# and never start the detached build of the ahead-of-time ones (rig.jitstart.start_aot_build), which would
# outlive the session; the tests of those kernels set RIG_AOT themselves (tests/unit/sim/test_aot_kernels.py,
# tests/system/commands/test_cli_trial_run.py).
os.environ["RIG_AOT"] = "0"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    return SHARED


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    d = SHARED / "data" / "real"
    if not d.is_dir():
        pytest.skip(f"shared real data not found at {d}")
    return d


def _corrupt_middle_chunk(src: Path, dst: Path, nbytes: int = 64):
    """Flip ``nbytes`` bytes in the data of the chunk one third into the file; returns that chunk's index."""
    from mcap.reader import make_reader

    with open(src, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    victim = min(chunks, key=lambda c: abs(c.chunk_start_offset - src.stat().st_size / 3))
    data = bytearray(src.read_bytes())
    at = victim.chunk_start_offset + victim.chunk_length - victim.compressed_size // 2 - nbytes
    for i in range(at, at + nbytes):
        data[i] ^= 0xFF
    dst.write_bytes(bytes(data))
    return victim


@pytest.fixture(scope="session")
def corrupt_middle_chunk():
    """``corrupt_middle_chunk(src, dst, nbytes=64)``: a copy of an MCAP with one chunk's data flipped."""
    return _corrupt_middle_chunk


#: a short tuning trial: a square wave (step response), then a 2-70 Hz sine sweep on a slide (frequency response)
TUNE_RECIPE = """name: tune
lubricant: boundary
seed: 4
accel_um_s2: 500
controller: {ff1: on, friction_ff: on}
segments:
  - {kind: hold, duration_s: 0.5}
  - {kind: square, amplitude_um: 5, frequency_hz: 1, cycles: 2, velocity_um_s: 50, edge_speed_um_s: 500}
  - {kind: sine_sweep, f0_hz: 2, f1_hz: 70, amplitude_um: 0.35, duration_s: 12, velocity_um_s: 160}
"""


@pytest.fixture(scope="session")
def sweep_log(tmp_path_factory) -> Path:
    """A folder with ``tune.yaml`` (:data:`TUNE_RECIPE`) and its simulated trial ``tune.mcap``, made once."""
    from typer.testing import CliRunner

    from rig.cli import app

    d = tmp_path_factory.mktemp("tune")
    (d / "tune.yaml").write_text(TUNE_RECIPE)
    res = CliRunner().invoke(app, ["run", str(d / "tune.yaml"), "--sim", "--out", str(d / "tune.mcap")])
    assert res.exit_code == 0, res.output
    return d
