"""Load-cell driver against the pymodbus emulator over real transports (TCP, RTU over ptys)."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceError
from drivers.loadcells import decode_value, encode_value


def test_register_encoding_exact():
    # 1.0f = 0x3F800000: big word order -> [0x3F80, 0x0000], little -> swapped
    assert encode_value(1.0, "float32", "big") == [0x3F80, 0x0000]
    assert encode_value(1.0, "float32", "little") == [0x0000, 0x3F80]
    assert encode_value(-2, "int32", "big") == [0xFFFF, 0xFFFE]
    assert encode_value(-2, "int16", "big") == [0xFFFE]
    assert decode_value([0xC2F6, 0xE979], "float32", "big") == pytest.approx(-123.456, abs=1e-4)
    assert decode_value([0xE979, 0xC2F6], "float32", "little") == pytest.approx(-123.456, abs=1e-4)
    assert decode_value([0x0001, 0x0000], "int32", "little") == 1.0


def test_a_lost_device_trips_at_once_other_errors_are_counted():
    from drivers.config import InterlockConfig
    from drivers.device import DeviceHealth
    from rig.hardware.interlocks import Interlocks

    il = Interlocks(InterlockConfig(), -5000.0, 5000.0, 0.05, 1e-3)
    h = DeviceHealth("load-cell conditioner", "modbus-tcp://127.0.0.1:1 unit 1", consecutive_errors=1)
    lost = DeviceError(h.device, h.address, "connection lost (closed by the conditioner)", kind="lost")
    slow = DeviceError(h.device, h.address, "no answer within 2 ms")
    trip = il.device_error(0.5, "loadcells", lost, h)
    assert trip is not None and trip.name == "device_lost" and "closed by the conditioner" in trip.message
    assert il.device_error(0.5, "loadcells", slow, h) is None  # one timeout is counted, not a trip
