"""Every interlock trips on its condition, with a message, the time and the values.
The interlocks see the process values and each device's DeviceHealth only."""

from __future__ import annotations

import pytest

from drivers.config import InterlockConfig
from drivers.device import DeviceHealth
from drivers.errors import DeviceError
from rig.hardware.interlocks import Interlocks


CFG = InterlockConfig(friction_max_N=150, normal_min_N=50, normal_max_N=150, stale_s=0.005,
                      max_checksum_errors=5, max_modbus_errors=3, max_can_errors=2,
                      max_consecutive_late=3, late_threshold_s=0.001, following_error_um=1000,
                      min_following_error_um=100, max_velocity_um_s=1000)
OK = dict(x_ref=500.0, x=500.0, f=20.0, n1=100.0, n2=100.0, late_s=0.0)


def _fixture():
    il = Interlocks(CFG, 0.0, 5000.0, heartbeat_timeout_s=0.05, period_s=1e-3)
    health = {"lvdt": DeviceHealth("LVDT conditioner", "serial:/dev/fake@921600"),
              "loadcells": DeviceHealth("load-cell conditioner", "modbus-tcp://127.0.0.1:1502 unit 1"),
              "valve": DeviceHealth("servovalve controller", "can-virtual:x node 1", status=1)}
    return il, health


def _check(il, health, **kw):
    a = {**OK, **kw}
    return il.check(1.25, 100.0, a["x_ref"], a["x"], a["f"], a["n1"], a["n2"], health, a["late_s"])


def test_no_trip_when_all_is_well():
    il, h = _fixture()
    for _ in range(10):
        assert _check(il, h) is None


@pytest.mark.parametrize("name,kw,values", [
    ("stroke_limit", {"x": 5000.5}, {"position_um": 5000.5}),
    ("stroke_limit", {"x": -1.0}, {"position_um": -1.0}),
    ("friction_limit", {"f": -151.0}, {"friction_N": -151.0}),
    ("normal_force_band", {"n1": 49.0}, {"normal_1_N": 49.0}),
    ("normal_force_band", {"n2": 151.0}, {"normal_2_N": 151.0}),
    ("following_error", {"x_ref": 700.0}, {"position_ref_um": 700.0}),
])
def test_process_limits(name, kw, values):
    il, h = _fixture()
    tr = _check(il, h, **kw)
    assert tr is not None and tr.name == name and tr.t_s == 1.25
    for k, v in values.items():
        assert tr.values[k] == v
    assert str(tr).startswith(f"INTERLOCK {name} at t=1.250 s")


def test_stale_position_needs_age_and_ticks():
    il, h = _fixture()
    h["lvdt"].age_s = 0.02
    h["lvdt"].polls_since_new = 1  # the loop itself was late: not yet a dead device
    assert _check(il, h) is None
    h["lvdt"].polls_since_new = 5
    tr = _check(il, h)
    assert tr.name == "stale_position" and "serial:/dev/fake" in tr.message and "LVDT" in tr.message
    assert tr.values["age_s"] == 0.02


def test_stale_forces():
    il, h = _fixture()
    h["loadcells"].age_s, h["loadcells"].polls_since_new = 0.01, 10
    tr = _check(il, h)
    assert tr.name == "stale_forces" and "modbus-tcp://127.0.0.1:1502" in tr.message


def test_checksum_errors_per_second():
    il, h = _fixture()
    assert _check(il, h) is None
    h["lvdt"].frames_bad = 5
    assert _check(il, h) is None
    h["lvdt"].frames_bad = 6
    tr = _check(il, h)
    assert tr.name == "serial_checksum_errors" and tr.values["frames_bad"] == 6


def test_device_fault_bits():
    il, h = _fixture()
    h["lvdt"].fault, h["lvdt"].fault_code = True, 1
    assert _check(il, h).name == "lvdt_fault"
    h["lvdt"].fault = False
    h["loadcells"].fault = True
    assert _check(il, h).name == "loadcell_fault"


def test_valve_fault_heartbeat_and_bus_errors():
    il, h = _fixture()
    va = h["valve"]
    va.fault, va.fault_code = True, 0x0101
    tr = _check(il, h)
    assert tr.name == "valve_fault" and "0x0101" in tr.message
    va.fault = False
    va.age_s, va.polls_since_new = 0.04, 80  # within the heartbeat timeout (50 ms): fine
    assert _check(il, h) is None
    va.age_s = 0.08
    tr = _check(il, h)
    assert tr.name == "valve_heartbeat" and "can-virtual:x" in tr.message
    va.age_s, va.polls_since_new = 0.0, 0
    va.frames_bad = 1
    assert _check(il, h).name == "can_bus_errors"


def test_run_of_missed_deadlines():
    il, h = _fixture()
    assert _check(il, h, late_s=0.002) is None
    assert _check(il, h, late_s=0.002) is None
    assert _check(il, h, late_s=0.0) is None  # the run is broken
    for _ in range(2):
        assert _check(il, h, late_s=0.003) is None
    tr = _check(il, h, late_s=0.003)
    assert tr.name == "missed_deadlines" and tr.values["run"] == 3


def test_device_errors_count_consecutive_failures_from_health():
    il, h = _fixture()
    mb = DeviceError("load-cell conditioner", "modbus-tcp://h:1", "no answer")
    h["loadcells"].consecutive_errors = 2
    assert il.device_error(0.1, "loadcells", mb, h["loadcells"]) is None
    h["loadcells"].consecutive_errors = 3
    tr = il.device_error(0.1, "loadcells", mb, h["loadcells"])
    assert tr.name == "modbus_errors" and "modbus-tcp://h:1" in tr.message
    can_err = DeviceError("servovalve controller", "can-x", "CAN send failed", kind="bus")
    h["valve"].consecutive_errors = 1
    assert il.device_error(0.1, "valve", can_err, h["valve"]) is None
    h["valve"].consecutive_errors = 2
    assert il.device_error(0.1, "valve", can_err, h["valve"]).name == "can_bus_errors"
    lost = DeviceError("LVDT conditioner", "serial:/dev/x", "port lost")
    tr = il.device_error(0.2, "lvdt", lost, h["lvdt"])
    assert tr.name == "device_lost" and tr.values["address"] == "serial:/dev/x"


@pytest.mark.parametrize("kw,channel", [
    ({"x": float("nan")}, "position_um"),
    ({"f": float("inf")}, "friction_N"),
    ({"n1": float("nan")}, "normal_1_N"),
    ({"n2": -float("inf")}, "normal_2_N"),
    ({"x_ref": float("nan")}, "position_ref_um"),
])
def test_non_finite_values_trip_naming_the_channel(kw, channel):
    il, h = _fixture()
    tr = _check(il, h, **kw)
    assert tr is not None and tr.name == "non_finite" and tr.values["channel"] == channel
    assert channel in tr.message
    if channel in ("position_um", "friction_N"):
        assert ("LVDT" if channel == "position_um" else "load-cell") in tr.message


def test_limits_are_written_so_that_nan_trips():
    """Every limit is `not (value within limit)`: a NaN that slipped past the finite check still trips."""
    il, h = _fixture()
    nan = float("nan")
    assert il._windows(0.0, 0.0, h) is None
    h["lvdt"].frames_lost = 10 ** 6
    tr = il._windows(0.0, 0.5, h)
    assert tr is not None and tr.name == "frame_loss" and "LVDT" in tr.message
    il2, h2 = _fixture()
    h2["lvdt"].age_s, h2["lvdt"].polls_since_new = nan, 100
    assert _check(il2, h2).name == "stale_position"


def test_non_finite_controller_output_trips():
    il, _ = _fixture()
    assert il.command(0.5, 0.01, 1.0, 2.0, 0.0, 0.0) is None
    tr = il.command(0.5, float("nan"), 1.0, float("nan"), 0.0, 0.0)
    assert tr.name == "non_finite" and tr.values["channel"] == "valve_cmd"
    tr = il.command(0.5, 0.0, 1.0, float("inf"), 0.0, 0.0)
    assert tr.values["channel"] == "pid_i"


def test_following_error_scales_with_velocity_like_linuxcnc():
    """limit = max(MIN_FERROR, FERROR |v| / v_max): 100 µm at rest, 1000 µm at 1000 µm/s (CFG)."""
    il, h = _fixture()
    assert il.following_limit_um(0.0) == 100.0
    assert il.following_limit_um(-500.0) == pytest.approx(500.0)
    assert _check(il, h, x_ref=599.0) is None            # 99 µm at rest: inside
    tr = _check(il, h, x_ref=601.0)                      # 101 µm at rest: trips
    assert tr.name == "following_error" and tr.values["limit_um"] == 100.0
    il2, h2 = _fixture()
    args = (1.25, 100.0, 901.0, 500.0, 20.0, 100.0, 100.0, h2, 0.0)
    assert il2.check(*args, v_ref_um_s=500.0) is None     # 401 µm at 500 µm/s: inside 500 µm
    assert il2.check(*args, v_ref_um_s=300.0).name == "following_error"


def test_device_problems_trip_with_their_name():
    il, h = _fixture()
    h["valve"].problems = [("valve_watchdog", "canopen-x node 1 nulled on its set-point watchdog")]
    tr = _check(il, h)
    assert tr.name == "valve_watchdog" and "watchdog" in tr.message and tr.values["problems"] == ["valve_watchdog"]
