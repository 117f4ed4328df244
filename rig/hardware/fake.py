"""An in-process fake rig for unit tests of the loop and its interlocks: no emulator, no clock.

:class:`FakeDevice` is a :class:`drivers.device.Device` whose values
(``position_um``, ``forces_N``) and :class:`drivers.device.DeviceHealth`
(``health_``) a test sets directly; ``fail_read`` / ``fail_write`` make its next
``read`` / ``write`` raise a :class:`drivers.errors.DeviceError`.
:class:`FakeValve` adds the valve's ``command`` / ``enable`` (every write is kept
in ``writes``), ``start()``, ``safe_stop()`` and ``final_state()``.
:class:`FakeClock` is a simulated clock for the loop's pacer: a sleep moves it
on at once, ``stall(s)`` makes the next wake ``s`` late. So each interlock's
trip is a deterministic test (tests/unit/hardware/test_hardware_fake_loop.py).
"""

from __future__ import annotations

from drivers.device import DeviceHealth
from drivers.errors import DeviceError
from rig.hardware.devices import RigDevices


class FakeDevice:
    def __init__(self, name: str, device: str, address: str = "fake:0"):
        self.name, self.address = name, address
        self.health_ = DeviceHealth(device, address, frames_ok=1)
        self.position_um = 0.0
        self.forces_N = (0.0, 100.0, 100.0)
        self.fail_read: DeviceError | None = None
        self.fail_write: DeviceError | None = None
        self.connected = False
        self.reads = 0

    def _err(self, msg: str, kind: str = "io") -> DeviceError:
        return DeviceError(self.health_.device, self.address, msg, kind=kind)

    def connect(self) -> None:
        self.connected = True

    def read(self, now: float | None = None) -> None:
        self.reads += 1
        if self.fail_read is not None:
            self.health_.errors += 1
            self.health_.consecutive_errors += 1
            raise self.fail_read

    def write(self, now: float | None = None) -> None:
        if self.fail_write is not None:
            raise self.fail_write

    def health(self, now: float | None = None) -> DeviceHealth:
        return self.health_

    def close(self) -> None:
        self.connected = False


class FakeValve(FakeDevice):
    """The valve: ``writes`` keeps ``(command, enable)`` of every write; ``confirm`` is what
    ``safe_stop()`` answers."""

    def __init__(self, address: str = "fake-can:0 node 1"):
        super().__init__("valve", "servovalve controller", address)
        self.command, self.enable = 0.0, False
        self.writes: list[tuple[float, bool]] = []
        self.started = self.stopped = False
        self.confirm = True
        self.dither_gain_min = None

    def start(self) -> None:
        self.started = True

    def write(self, now: float | None = None) -> None:
        self.writes.append((self.command, self.enable))
        super().write(now)

    def safe_stop(self) -> bool:
        self.stopped = True
        self.command, self.enable = 0.0, False
        self.writes.append((0.0, False))
        return self.confirm

    def final_state(self) -> dict:
        on = self.writes[-1][1] if self.writes else False
        return {"status_bits": 1 if on else 8, "enabled": on, "output": self.writes[-1][0] if self.writes else 0.0,
                "nmt": "OPERATIONAL", "nulled": not on, "source": "fake"}


class FakeSafety(FakeDevice):
    """The safety chain's I/O: ``enable`` (the amplifier's, set by the loop each tick) kept in ``writes``;
    a test opens the e-stop by putting ``("estop", ...)`` in ``health_.problems``."""

    def __init__(self):
        super().__init__("safety", "safety I/O module", "fake-modbus:io")
        self.enable = False
        self.writes: list[bool] = []

    def write(self, now: float | None = None) -> None:
        self.writes.append(self.enable)
        super().write(now)

    def safe_stop(self) -> bool:
        self.enable = False
        return True

    def describe(self) -> str:
        return "fake chain"


def fake_rig(x_um: float = 500.0, safety: bool = False) -> RigDevices:
    """An LVDT at ``x_um``, load cells at 0 N friction and 100 N per rider, a valve (and the safety chain's
    I/O); all healthy."""
    lvdt = FakeDevice("lvdt", "LVDT conditioner", "fake-serial:lvdt")
    lvdt.position_um = x_um
    cells = FakeDevice("loadcells", "load-cell conditioner", "fake-modbus:1")
    return RigDevices(position=lvdt, forces=cells, valve=FakeValve(), safety=FakeSafety() if safety else None)


class ListQueue:
    """The loop's output queue, in a list (``items``), for running the loop in-process."""

    def __init__(self):
        self.items = []

    def put(self, item):
        self.items.append(item)

    def cancel_join_thread(self):
        pass


class FakeClock:
    """A simulated CLOCK_MONOTONIC for :class:`rig.hardware.timing.Pacer` (``Pacer(..., clock=c, sleep=c.sleep)``):
    ``sleep`` moves it on at once; ``stall(s)`` makes the next wake ``s`` late (a stalled machine)."""

    def __init__(self, t0: float = 1000.0):
        self.now = t0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)

    def stall(self, seconds: float) -> None:
        self.now += seconds
