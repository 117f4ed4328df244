"""The rig's devices as the loop drives them: the only module that names the concrete drivers.

:func:`build_devices` turns a :class:`drivers.config.HardwareConfig` into a
:class:`RigDevices`: the position sensor (``position_um``), the force sensors
(``forces_N``), the servovalve (``command``, ``enable``) and the list of all
three in read order, each a :class:`drivers.device.Device`.

:class:`drivers.valve.CanopenValve` is a Device itself: ``read`` drains its
frames (TPDO status, heartbeat, EMCY); ``write`` sends this tick's set-point
(RPDO) and the SYNC; ``health`` carries the driver's ``problems()`` (foreign or
malformed frames, fault/EMCY, watchdog, heartbeat, not operational, not
enabled, a spool that does not follow its command), each of which trips the
loop. ``start()`` (NMT start, fault reset, enable, verified by the valve's
status) is the explicit operator action the loop calls once, before the first
tick, never after a trip; ``safe_stop()`` nulls and disables and says whether
the valve confirmed it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.config import HardwareConfig
from drivers.device import Device
from drivers.errors import DeviceError
from drivers.loadcells import LoadCellReader
from drivers.lvdt import LvdtReader
from drivers.safety_io import SafetyLink
from drivers.valve import CanopenValve


@dataclass
class RigDevices:
    position: LvdtReader
    forces: LoadCellReader
    valve: CanopenValve
    safety: SafetyLink | None = field(default=None)

    @property
    def all(self) -> list[Device]:
        """Every device, in read and write order (position first: the control error; then forces; the
        valve; the safety chain's I/O last, so that a nulled set-point goes out before the enable drops)."""
        return [self.position, self.forces, self.valve] + ([self.safety] if self.safety is not None else [])


def build_devices(hw: HardwareConfig) -> RigDevices:
    return RigDevices(position=LvdtReader(hw.lvdt), forces=LoadCellReader(hw.loadcells, pipelined=True),
                      valve=CanopenValve(hw.valve),
                      safety=safety_link(hw))


def safety_link(hw: HardwareConfig) -> SafetyLink | None:
    """The safety chain's I/O on its own process, polled every loop period, just below the loop's priority."""
    if hw.safety is None:
        return None
    rt = hw.realtime
    return SafetyLink(hw.safety, 1e-3, max(1, rt.priority - 1) if rt.sched_fifo else 0)


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
