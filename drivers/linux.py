"""Linux process helpers (prctl) for the device processes: the loop and the emulators."""

from __future__ import annotations

import ctypes
import signal

PR_SET_PDEATHSIG = 1
PR_SET_NAME = 15
PR_SET_TIMERSLACK = 29


def _libc():
    return ctypes.CDLL("libc.so.6", use_errno=True)


def prctl(option: int, arg: int) -> bool:
    try:
        return _libc().prctl(option, ctypes.c_ulong(arg), 0, 0, 0) == 0
    except Exception:  # noqa: BLE001 - not Linux
        return False


def set_process_name(name: str) -> bool:
    """Set the kernel's name of this process (``/proc/PID/comm``, 15 bytes: PR_SET_NAME)."""
    try:
        return _libc().prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0) == 0
    except Exception:  # noqa: BLE001
        return False


def set_pdeathsig(sig: int = signal.SIGTERM) -> bool:
    """Deliver ``sig`` to this process when its parent dies (PR_SET_PDEATHSIG)."""
    return prctl(PR_SET_PDEATHSIG, sig)
