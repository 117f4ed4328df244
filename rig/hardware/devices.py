"""The rig's devices as the loop drives them: the only module that names the concrete drivers.

:func:`build_devices` turns a :class:`drivers.config.HardwareConfig` into a
:class:`RigDevices`: the position sensor (``position_um``), the force sensors
(``forces_N``), the servovalve (``command``, ``enable``) and the list of all
three in read order, each a :class:`drivers.device.Device`.

:class:`ValveDevice` adapts the servovalve controller's driver
(:class:`drivers.valve.ValveController`) to the Device protocol: ``write``
sends the setpoint every tick and turns changes of ``enable`` into the
controller's enable/disable commands.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.config import HardwareConfig
from drivers.device import Device, DeviceHealth
from drivers.errors import DeviceError
from drivers.loadcells import LoadCellReader
from drivers.lvdt import LvdtReader
from drivers.valve import DEVICE as VALVE_DEVICE
from drivers.valve import ValveController


class ValveDevice:
    """The servovalve controller as a :class:`drivers.device.Device` (``name`` "valve").

    Set ``command`` (valve command in [-1, 1]) and ``enable`` before
    ``write(now)``. While ``enable`` is true and the controller does not
    report itself enabled, the enable command is repeated every
    ``enable_retry_ticks`` writes; when ``enable`` turns false the setpoint
    goes out nulled with the enable flag cleared, followed by one disable
    command.
    """

    name = "valve"

    def __init__(self, driver: ValveController, enable_retry_ticks: int = 20):
        self.driver = driver
        self.address = driver.address
        self.command = 0.0
        self.enable = False
        self._sent_enable = False
        self._retry = max(1, enable_retry_ticks)
        self._since_enable = 0
        self._since_disable = 0
        self._health = DeviceHealth(VALVE_DEVICE, self.address)

    # -- values --------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        """The controller reports itself enabled (last status frame)."""
        return self.driver.enabled

    def final_state(self) -> dict:
        d = self.driver
        return {"status_bits": d.status_bits, "enabled": d.enabled, "output": d.output}

    # -- the Device protocol -----------------------------------------------------------
    def connect(self) -> None:
        self.driver.connect()

    def read(self, now: float | None = None) -> None:
        self.driver.poll(now)

    def write(self, now: float | None = None) -> None:
        d = self.driver
        if self.enable:
            if not self._sent_enable or (not d.enabled and self._since_enable >= self._retry):
                d.enable()
                self._sent_enable = True
                self._since_enable = 0
            self._since_enable += 1
            d.write(self.command)
        else:
            d.write(0.0, enable=False)
            # disable once on the transition, then again while the controller still says enabled
            if self._sent_enable or (d.enabled and self._since_disable >= self._retry):
                self._sent_enable = False
                self._since_disable = 0
                d.disable()
            self._since_disable += 1

    def health(self, now: float | None = None) -> DeviceHealth:
        d, h = self.driver, self._health
        h.frames_ok, h.frames_bad = d.n_status, d.bus_error_frames
        h.errors, h.consecutive_errors = d.send_errors, d.consecutive_send_errors
        h.age_s = d.heartbeat_age_s(now)
        h.polls_since_new = d.polls_since_status
        h.status, h.fault, h.fault_code = d.status_bits, d.fault, d.fault_code
        return h

    def close(self) -> None:
        self.driver.close()


@dataclass
class RigDevices:
    position: LvdtReader
    forces: LoadCellReader
    valve: ValveDevice

    @property
    def all(self) -> list[Device]:
        """Every device, in read order (position first: the control error; then forces; the valve)."""
        return [self.position, self.forces, self.valve]


def build_devices(hw: HardwareConfig) -> RigDevices:
    return RigDevices(position=LvdtReader(hw.lvdt), forces=LoadCellReader(hw.loadcells),
                      valve=ValveDevice(ValveController(hw.valve)))


def wait_for_data(devices: list[Device], timeout_s: float, clock) -> None:
    """Read every device until each has delivered data (``health().frames_ok > 0``); DeviceError
    naming the first that did not within ``timeout_s``."""
    import time

    t_end = clock() + timeout_s
    pending = list(devices)
    while pending:
        now = clock()
        for d in list(pending):
            try:
                d.read(now)
            except DeviceError:
                if now >= t_end:
                    raise
                continue
            if d.health(now).frames_ok > 0:
                pending.remove(d)
        if pending and now >= t_end:
            h = pending[0].health(now)
            raise DeviceError(h.device, h.address, f"no data within {timeout_s:g} s ({h.frames_bad} bad frames, "
                                                   f"{h.garbage_bytes} garbage bytes)")
        if pending:
            time.sleep(0.001)
