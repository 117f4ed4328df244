"""The layers of docs/architecture.md, as import-linter contracts in pyproject.toml.

``lint-imports`` must keep every contract; and the contracts must bite: on a
copy of the code with a deliberately wrong import (a lower layer importing a
higher one, drivers/ importing rig/, a cycle) the same check fails and names it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest


REPO = Path(__file__).resolve().parents[2]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(cwd: Path, *contracts: str) -> subprocess.CompletedProcess:
    args = [str(LINT), "--no-cache", "--no-logo", "--config", str(cwd / "pyproject.toml")]
    for c in contracts:
        args += ["--contract", c]
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def copy(tmp_path_factory) -> Path:
    """The three top-level packages and pyproject.toml, copied (no tests, no data)."""
    dst = tmp_path_factory.mktemp("layers")
    for pkg in ("rig", "drivers", "trajectories"):
        shutil.copytree(REPO / pkg, dst / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", dst / "pyproject.toml")
    return dst


def _append(path: Path, line: str) -> str:
    old = path.read_text()
    path.write_text(old + "\n" + line + "\n")
    return old


def test_contracts_are_kept():
    r = _lint(REPO)
    assert r.returncode == 0, r.stdout + r.stderr


def test_drivers_importing_rig_is_caught(copy):
    assert _lint(copy, "drivers-independent-of-rig").returncode == 0
    target = copy / "drivers" / "errors.py"
    old = _append(target, "import rig.session  # a deliberately wrong import")
    try:
        r = _lint(copy, "drivers-independent-of-rig")
    finally:
        target.write_text(old)
    assert r.returncode != 0
    assert "drivers.errors -> rig.session" in r.stdout


def test_lower_layer_importing_higher_is_caught(copy):
    wrong = "rig.model is not allowed to import rig.session"
    assert wrong not in _lint(copy, "rig-layers").stdout
    target = copy / "rig" / "model" / "friction.py"
    old = _append(target, "import rig.session.core  # a deliberately wrong import")
    try:
        r = _lint(copy, "rig-layers")
    finally:
        target.write_text(old)
    assert r.returncode != 0
    assert wrong in r.stdout


def test_cycle_is_caught(copy):
    target = copy / "drivers" / "errors.py"
    old = _append(target, "import drivers.lvdt  # drivers.lvdt imports drivers.errors: a cycle")
    try:
        r = _lint(copy, "no-cycles")
    finally:
        target.write_text(old)
    assert r.returncode != 0
    assert "No cycles are allowed in drivers" in r.stdout
