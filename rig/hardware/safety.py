"""The safety chain's latch: after an e-stop or a loss of hydraulic pressure, no run until a reset.

A trip of the chain (``estop``, ``hydraulic_pressure``: :data:`rig.hardware.interlocks.SAFETY_TRIPS`)
writes a latch file for the I/O module (``hardware.safety.latch_dir``, one file per module
address: the latch belongs to the frame's chain, whatever profile drives it). While it exists the
loop refuses to start, naming the chain and the trip; ``rig reset --hardware PROFILE`` removes it
only once it has read both inputs healthy (:func:`reset`), as LinuxCNC's ``estop_latch``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from drivers.config import SafetyConfig
from drivers.errors import DeviceError


def latch_path(cfg: SafetyConfig) -> Path:
    safe = f"{cfg.host}-{cfg.port}-unit{cfg.device_id}".replace("/", "_").replace(":", "_")
    return Path(os.path.expanduser(cfg.latch_dir)) / f"safety-latch-{safe}.json"


def write_latch(cfg: SafetyConfig, trip: dict) -> Path:
    """Latch the chain (atomically: a half-written latch is never read)."""
    p = latch_path(cfg)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(".tmp")
    tmp.write_text(json.dumps({"trip": trip, "utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
                               "module": cfg.address_text}, default=str))
    os.replace(tmp, p)
    return p


def read_latch(cfg: SafetyConfig) -> dict | None:
    p = latch_path(cfg)
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {"trip": {"name": "unknown", "message": f"unreadable latch file {p}"}, "utc": "?"}


def latched_message(cfg: SafetyConfig | None, profile_text: str = "PROFILE") -> str | None:
    """Why a run must not start (the chain is latched), or None."""
    if cfg is None:
        return None
    lat = read_latch(cfg)
    if lat is None:
        return None
    tr = lat.get("trip") or {}
    return (f"the safety chain ({cfg.address_text}) is latched by {tr.get('name')} at {lat.get('utc')} UTC: "
            f"{tr.get('message', '')}; once the e-stop is released and the pressure is back, "
            f"`rig reset --hardware {profile_text}` clears it")


def reset(cfg: SafetyConfig) -> tuple[bool, str]:
    """Read the chain's inputs; clear the latch only when both are healthy. (ok, what was seen)."""
    from drivers.safety_io import SafetyIO

    io = SafetyIO(cfg)
    try:
        io.connect()
        io.poll()
    except DeviceError as exc:
        return False, f"cannot read the safety chain: {exc}"
    finally:
        io.close()
    state = io.describe()
    if not (io.estop_ok and io.pressure_ok):
        return False, f"not reset: {state}"
    had = read_latch(cfg) is not None
    latch_path(cfg).unlink(missing_ok=True)
    return True, ("latch cleared; " if had else "nothing was latched; ") + state
