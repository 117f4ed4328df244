"""The rig's devices as the loop drives them: the only module that names the concrete drivers.

:func:`build_devices` turns a :class:`drivers.config.HardwareConfig` into a
:class:`RigDevices`: the position sensor (``position_um``), the force sensors
(``forces_N``), the servovalve (``command``, ``enable``) and the list of all
three in read order, each a :class:`drivers.device.Device`.

:class:`ValveDevice` adapts the CANopen servovalve controller's host driver
(:class:`drivers.valve.CanopenValve`) to the Device protocol: ``read`` drains
its frames (TPDO status, heartbeat, EMCY); ``write`` sends this tick's
set-point (RPDO) and the SYNC; ``health`` carries the driver's
``problems()`` (foreign or malformed frames, fault/EMCY, watchdog, heartbeat,
not operational, not enabled, a spool that does not follow its command), each
of which trips the loop. ``start()`` (NMT start, fault reset, enable, verified
by the valve's status) is the explicit operator action the loop calls once,
before the first tick, never after a trip; ``safe_stop()`` nulls and disables
and says whether the valve confirmed it.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.config import HardwareConfig
from drivers.device import Device, DeviceHealth
from drivers.errors import DeviceError
from drivers.loadcells import LoadCellReader
from drivers.lvdt import LvdtReader
from drivers.valve import DEVICE as VALVE_DEVICE
from drivers.valve import CanopenValve


class ValveDevice:
    """The CANopen servovalve controller as a :class:`drivers.device.Device` (``name`` "valve").

    Set ``command`` (spool fraction in [-1, 1]) and ``enable`` before ``write(now)``;
    with ``enable`` false the set-point goes out nulled with the enable bit cleared.
    """

    name = "valve"

    def __init__(self, driver: CanopenValve):
        self.driver = driver
        self.address = driver.address
        self.command = 0.0
        self.enable = False
        self.status = driver._st
        self._health = DeviceHealth(VALVE_DEVICE, self.address)

    # -- values --------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        """The controller reports itself enabled (last status PDO)."""
        return self.status.enabled

    def final_state(self) -> dict:
        st = self.status
        return {"status_bits": st.status_word, "enabled": st.enabled, "output": st.spool_actual,
                "nmt": st.nmt_state, "nulled": st.nulled}

    # -- the Device protocol -----------------------------------------------------------
    def connect(self) -> None:
        self.driver.connect()

    def start(self) -> None:
        """NMT start, fault reset, enable; returns once the valve's status shows it enabled."""
        self.driver.start(self.driver.cfg.start_timeout_s)

    def read(self, now: float | None = None) -> None:
        self.status = self.driver.read()

    def write(self, now: float | None = None) -> None:
        if self.enable:
            self.driver.write(self.command)
        else:
            self.driver.write(0.0, enable=False)

    def health(self, now: float | None = None) -> DeviceHealth:
        d, st, h = self.driver, self.status, self._health
        h.frames_ok = st.n_tpdo or (1 if st.heartbeat_age_s < float("inf") else 0)  # heartbeats before start
        h.frames_bad = st.malformed_frames + st.bus_malformed + st.foreign_frames
        h.errors = d.send_errors
        h.age_s = st.heartbeat_age_s
        h.status, h.fault_code = st.status_word, st.emcy[0][0] if st.emcy else 0
        h.fault = st.fault
        h.problems = d.problems()
        return h

    @property
    def dither_gain_min(self) -> float | None:
        """The lowest spool/command 500 Hz gain the valve's dither check judged this run (None: never judged)."""
        g = self.driver.dither.min_gain_seen
        return round(g, 4) if g != float("inf") else None

    def safe_stop(self) -> bool:
        """Null and disable; True once the valve confirms it (then NMT pre-operational)."""
        return self.driver.safe_stop()

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
    return RigDevices(position=LvdtReader(hw.lvdt), forces=LoadCellReader(hw.loadcells, pipelined=True),
                      valve=ValveDevice(CanopenValve(hw.valve)))


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
