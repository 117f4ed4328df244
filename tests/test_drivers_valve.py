"""Servovalve controller driver against its emulator on a python-can bus."""

from __future__ import annotations

import time

import pytest

from drivers.config import ValveConfig
from drivers.emulators.valve_controller import ValveControllerEmulator
from drivers.errors import DeviceError
from drivers.valve import (
    ST_ENABLED, ST_FAULT, ST_WATCHDOG, ValveController, decode_setpoint, encode_setpoint,
    encode_status,
)


def test_frames_exact_bytes():
    assert encode_setpoint(1.0, 5).hex() == "ff7f0501"
    assert encode_setpoint(-2.0, 0x106, enable=False).hex() == "01800600"  # saturated, seq wraps
    assert decode_setpoint(bytes.fromhex("00400100"))[0] == pytest.approx(0.5, abs=1e-4)
    assert encode_status(ST_ENABLED | ST_FAULT, 7, 0.0, 0x0101).hex() == "030700000101"


@pytest.fixture
def pair(request):
    cfg = ValveConfig(interface="virtual", channel=f"valve-{request.node.name}", node_id=3,
                      heartbeat_timeout_s=0.05)
    em = ValveControllerEmulator(cfg, watchdog_s=0.02, status_period_s=0.01)
    em.start()
    drv = ValveController(cfg)
    drv.connect()
    yield em, drv
    drv.close()
    em.stop()


def _pump(em, seconds):
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        now = time.monotonic()
        em.handle(em.recv(0.001), now)
        em.maybe_status(time.monotonic())


def test_enable_setpoints_watchdog_disable(pair):
    em, drv = pair
    drv.enable()
    _pump(em, 0.005)
    assert em.enabled
    drv.write(0.25)
    _pump(em, 0.003)
    assert em.setpoint == pytest.approx(0.25, abs=1e-4)
    assert em.output(time.monotonic()) == pytest.approx(0.25, abs=1e-4)
    drv.poll()
    assert drv.enabled and not drv.fault and drv.heartbeat >= 0
    # setpoints stop: the controller nulls its output by itself
    _pump(em, 0.03)
    assert em.output(time.monotonic()) == 0.0 and em.status_bits(time.monotonic()) & ST_WATCHDOG
    drv.write(0.1)
    _pump(em, 0.003)
    assert em.output(time.monotonic()) == pytest.approx(0.1, abs=1e-4)
    drv.disable()
    _pump(em, 0.003)
    assert not em.enabled and em.output(time.monotonic()) == 0.0
    drv.poll()
    assert not drv.enabled


def test_fault_bit_and_missing_heartbeat(pair):
    em, drv = pair
    drv.enable()
    _pump(em, 0.02)
    drv.poll()
    assert drv.enabled
    em.faults["fault"] = True
    _pump(em, 0.02)
    drv.poll()
    assert drv.fault and drv.fault_code == 0x0101 and drv.status_bits & ST_FAULT
    assert em.output(time.monotonic()) == 0.0
    em.faults = {"silent": True}
    drv.poll()
    _pump(em, 0.08)
    assert drv.poll() == 0
    assert drv.heartbeat_age_s() > 0.05


def test_closed_bus_names_device():
    drv = ValveController(ValveConfig(interface="virtual", channel="x", node_id=1))
    with pytest.raises(DeviceError) as ei:
        drv.write(0.0)
    assert "servovalve controller at can-virtual:x node 1" in str(ei.value)
    with pytest.raises(DeviceError):
        ValveController(ValveConfig(interface="socketcan", channel="nosuchcan0")).connect()


def test_udp_multicast_across_processes_smoke():
    """The transport of the emulated rig: frames cross process boundaries."""
    from rig.hardware.emulated import emulated_hardware, start_emulator_process

    hw = emulated_hardware("/tmp/rig-test-valve")
    h = start_emulator_process(hw, plant="integrator")
    drv = ValveController(hw.valve)
    try:
        drv.connect()
        drv.wait_status(0.5)
        drv.enable()
        for _ in range(20):
            drv.write(0.5)
            time.sleep(0.001)
        st = h.stats()
        assert st["valve_enabled"] and st["n_setpoints"] >= 15
        assert st["last"]["position_um"] > 0.0  # the plant moved (0.5 x 1000 µm/s)
    finally:
        drv.close()
        h.stop()
