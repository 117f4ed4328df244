"""Fixtures of the system tests: a private copy of the emulated profile (free ports, tmp paths), a short
hardware recipe, and the loop process's PID. Each fixture returns a function, session-scoped, so that
module-scoped fixtures can use them too."""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest
import yaml


REPO = Path(__file__).resolve().parents[2]


def _deep_update(d: dict, u: dict) -> dict:
    for k, v in u.items():
        if isinstance(v, dict) and isinstance(d.get(k), dict):
            _deep_update(d[k], v)
        else:
            d[k] = v
    return d


def _private_profile(tmp_path: Path, autostart: bool = True, **hw_overrides) -> Path:
    """An overlay of config/rigs/emulated.yaml with its devices moved to free ports and ``tmp_path``."""
    from drivers.emulators.modbus_conditioner import free_tcp_port

    rnd = random.Random(os.getpid() ^ hash(str(tmp_path)))
    hw = {"loadcells": {"port": free_tcp_port()}, "lvdt": {"port": str(tmp_path / "lvdt")},
          "valve": {"channel": f"t{os.getpid()}-{rnd.randrange(1 << 30)}"},
          "safety": {"port": free_tcp_port(), "latch_dir": str(tmp_path)},
          "emulators": {"run_dir": str(tmp_path), "autostart": autostart}}
    _deep_update(hw, hw_overrides)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"extends": str(REPO / "config/rigs/emulated.yaml"), "hardware": hw},
                                   sort_keys=False))
    return path


def _find_child(ppid: int, comm: str) -> int | None:
    """PID of a descendant of ``ppid`` whose kernel name is ``comm``."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if (d / "comm").read_text().strip() != comm:
                continue
            stat = (d / "stat").read_text()
            parent = int(stat.rsplit(")", 1)[1].split()[1])
        except OSError:
            continue
        if parent == ppid:
            return int(d.name)
    return None


def _short_recipe(name: str, settle_s: float = 0.5, stub_um: float = 30.0, rest_s: float = 1.5) -> str:
    """A short boundary-lubricant recipe: a hold, a run-in stub each way at 20 µm/s, a hold."""
    return f"""\
name: {name}
description: a short trial for the hardware tests
lubricant: boundary
normal_force_N: 100
seed: 3
trials: 1
accel_um_s2: 100
log: {{raw_rate_hz: 1000, decimated_rate_hz: 25}}
segments:
  - {{kind: hold, label: settle, duration_s: {settle_s}}}
  - {{kind: run_in, label: stub, distance_um: {stub_um}, speed_um_s: 20}}
  - {{kind: hold, label: rest, duration_s: {rest_s}}}
"""


@pytest.fixture(scope="session")
def private_profile():
    """``private_profile(tmp_path, autostart=True, **hw_overrides) -> Path`` (see ``_private_profile``)."""
    return _private_profile


@pytest.fixture(scope="session")
def find_child():
    """``find_child(ppid, comm) -> int | None``: a descendant process by its kernel name."""
    return _find_child


@pytest.fixture(scope="session")
def short_recipe():
    """``short_recipe(name, settle_s, stub_um, rest_s) -> str``: a short boundary recipe's YAML text."""
    return _short_recipe
