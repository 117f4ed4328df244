"""The Device protocol of the real-time loop, and the health every device reports.

In the manner of ros2_control's hardware components, the loop drives every
device the same way each tick: ``read(now)`` (take in what arrived, never
block for long), the controller update, ``write(now)`` (send this tick's
command; a no-op for a sensor), then ``health(now)``. ``connect()`` before the
first tick, ``close()`` after the last. A failure raises
:class:`drivers.errors.DeviceError` naming the device and its address.

The values themselves are plain attributes of the device (a sensor's
``position_um`` or ``forces_N``; the valve's ``command`` and ``enable``), so
the loop moves floats, not dicts.

The interlocks see :class:`DeviceHealth` only, never a driver's internals.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Protocol, runtime_checkable


@dataclass(slots=True)
class DeviceHealth:
    """What a device's link looks like now (updated in place by its device every tick).

    ``frames_ok`` / ``frames_bad`` (checksum or malformed) / ``frames_lost``
    (sequence gaps) count the device's messages since it was connected;
    ``garbage_bytes`` bytes skipped on a stream; ``age_s`` the time since the
    last new data (a new sample, frame or status); ``polls_since_new`` loop
    ticks without new data (with ``age_s``: a stall of the machine is not a
    dead device); ``errors`` failed requests or sends, ``consecutive_errors``
    the current run of them; ``status`` the device's status word and
    ``fault`` its fault bit(s) set; ``fault_code`` what it says about it;
    ``problems`` what the device's own checks found, as ``(trip name, sentence)``
    pairs (e.g. the servovalve's foreign frames, watchdog, following); each trips.
    """

    device: str                 # "LVDT conditioner", "load-cell conditioner", "servovalve controller"
    address: str
    frames_ok: int = 0
    frames_bad: int = 0
    frames_lost: int = 0
    garbage_bytes: int = 0
    age_s: float = 0.0
    polls_since_new: int = 0
    errors: int = 0
    consecutive_errors: int = 0
    status: int = 0
    fault: bool = False
    fault_code: int = 0
    problems: list = field(default_factory=list)  # (trip name, sentence): each must trip the loop

    def as_dict(self) -> dict:
        return asdict(self)


@runtime_checkable
class Device(Protocol):
    """One device of the rig, as the real-time loop drives it."""

    name: str       # the loop's key: "lvdt", "loadcells", "valve"
    address: str

    def connect(self) -> None: ...

    def read(self, now: float) -> None: ...

    def write(self, now: float) -> None: ...

    def health(self, now: float) -> DeviceHealth: ...

    def close(self) -> None: ...


@runtime_checkable
class DitherChecked(Protocol):
    """A device that checks the dither reaches its output (the valve): the lowest 500 Hz gain its
    check judged this run, None while never judged. The loop logs it beside the frame counters."""

    @property
    def dither_gain_min(self) -> float | None: ...


def release_quietly(release: Callable[[], Any]) -> None:
    """Call a device's ``close``/``shutdown`` at the end of its life, ignoring what it raises (the
    port, socket or bus may already be gone; nothing is left to tell the operator)."""
    try:
        release()
    except Exception:  # noqa: BLE001 - SerialException, OSError, python-can and pymodbus errors
        pass
