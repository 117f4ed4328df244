"""Device errors: every failure names the device and its address.

The real-time loop turns any :class:`DeviceError` into an interlock trip and the
safe state (valve nulled and disabled), so a lost device never leaves the
actuator under closed-loop control on stale data.
"""

from __future__ import annotations


class DeviceError(RuntimeError):
    """A device failed: ``str()`` is ``"<device> at <address>: <what>"``."""

    def __init__(self, device: str, address: str, message: str, kind: str = "io"):
        self.device = device
        self.address = address
        self.message = message
        # "io" (timeout, no answer), "lost" (the connection or port is gone: trips at once),
        # "protocol" (exception response, bad frame), "bus" (CAN send/receive), "fault"
        self.kind = kind
        super().__init__(f"{device} at {address}: {message}")
