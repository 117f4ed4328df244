"""Every interlock trips on its condition, with a message, the time and the values."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from drivers.config import InterlockConfig
from drivers.errors import DeviceError
from rig.hardware.interlocks import Interlocks


class FakeLvdt:
    address = "serial:/dev/fake@921600"

    def __init__(self):
        self.age = 0.0
        self.polls_since_frame = 0
        self.status = 0
        self.parser = SimpleNamespace(bad_frames=0)

    def age_s(self, now=None):
        return self.age


class FakeCells(FakeLvdt):
    address = "modbus-tcp://127.0.0.1:1502 unit 1"

    def __init__(self):
        super().__init__()
        self.reads_since_new = 0


class FakeValve:
    address = "can-virtual:x node 1"

    def __init__(self):
        self.fault = False
        self.fault_code = 0
        self.status_bits = 1
        self.age = 0.0
        self.polls_since_status = 0
        self.bus_error_frames = 0

    def heartbeat_age_s(self, now=None):
        return self.age


CFG = InterlockConfig(friction_max_N=150, normal_min_N=50, normal_max_N=150, stale_s=0.005,
                      max_checksum_errors=5, max_modbus_errors=3, max_can_errors=2,
                      max_consecutive_late=3, late_threshold_s=0.001, max_following_error_um=100)
OK = dict(x_ref=500.0, x=500.0, f=20.0, n1=100.0, n2=100.0, late_s=0.0)


def _fixture():
    il = Interlocks(CFG, 0.0, 5000.0, heartbeat_timeout_s=0.05, period_s=1e-3)
    return il, FakeLvdt(), FakeCells(), FakeValve()


def _check(il, lv, lc, va, **kw):
    a = {**OK, **kw}
    return il.check(1.25, 100.0, a["x_ref"], a["x"], a["f"], a["n1"], a["n2"], lv, lc, va, a["late_s"])


def test_no_trip_when_all_is_well():
    il, lv, lc, va = _fixture()
    for _ in range(10):
        assert _check(il, lv, lc, va) is None


@pytest.mark.parametrize("name,kw,values", [
    ("stroke_limit", {"x": 5000.5}, {"position_um": 5000.5}),
    ("stroke_limit", {"x": -1.0}, {"position_um": -1.0}),
    ("friction_limit", {"f": -151.0}, {"friction_N": -151.0}),
    ("normal_force_band", {"n1": 49.0}, {"normal_1_N": 49.0}),
    ("normal_force_band", {"n2": 151.0}, {"normal_2_N": 151.0}),
    ("following_error", {"x_ref": 700.0}, {"position_ref_um": 700.0}),
])
def test_process_limits(name, kw, values):
    il, lv, lc, va = _fixture()
    tr = _check(il, lv, lc, va, **kw)
    assert tr is not None and tr.name == name and tr.t_s == 1.25
    for k, v in values.items():
        assert tr.values[k] == v
    assert name.split("_")[0] in str(tr).lower() or "INTERLOCK" in str(tr)


def test_stale_position_needs_age_and_ticks():
    il, lv, lc, va = _fixture()
    lv.age = 0.02
    lv.polls_since_frame = 1  # the loop itself was late: not yet a dead device
    assert _check(il, lv, lc, va) is None
    lv.polls_since_frame = 5
    tr = _check(il, lv, lc, va)
    assert tr.name == "stale_position" and "serial:/dev/fake" in tr.message
    assert tr.values["age_s"] == 0.02


def test_stale_forces():
    il, lv, lc, va = _fixture()
    lc.age, lc.reads_since_new = 0.01, 10
    tr = _check(il, lv, lc, va)
    assert tr.name == "stale_forces" and "modbus-tcp://127.0.0.1:1502" in tr.message


def test_checksum_errors_per_second():
    il, lv, lc, va = _fixture()
    assert _check(il, lv, lc, va) is None
    lv.parser.bad_frames = 5
    assert _check(il, lv, lc, va) is None
    lv.parser.bad_frames = 6
    tr = _check(il, lv, lc, va)
    assert tr.name == "serial_checksum_errors" and tr.values["bad_frames"] == 6


def test_device_status_bits():
    il, lv, lc, va = _fixture()
    lv.status = 1
    assert _check(il, lv, lc, va).name == "lvdt_fault"
    lv.status = 0
    lc.status = 2
    assert _check(il, lv, lc, va).name == "loadcell_fault"


def test_valve_fault_heartbeat_and_bus_errors():
    il, lv, lc, va = _fixture()
    va.fault, va.fault_code = True, 0x0101
    tr = _check(il, lv, lc, va)
    assert tr.name == "valve_fault" and "0x0101" in tr.message
    va.fault = False
    va.age, va.polls_since_status = 0.08, 80
    tr = _check(il, lv, lc, va)
    assert tr.name == "valve_heartbeat" and "can-virtual:x" in tr.message
    va.age, va.polls_since_status = 0.0, 0
    va.bus_error_frames = 1
    assert _check(il, lv, lc, va).name == "can_bus_errors"


def test_run_of_missed_deadlines():
    il, lv, lc, va = _fixture()
    assert _check(il, lv, lc, va, late_s=0.002) is None
    assert _check(il, lv, lc, va, late_s=0.002) is None
    assert _check(il, lv, lc, va, late_s=0.0) is None  # the run is broken
    for _ in range(2):
        assert _check(il, lv, lc, va, late_s=0.003) is None
    tr = _check(il, lv, lc, va, late_s=0.003)
    assert tr.name == "missed_deadlines" and tr.values["run"] == 3


def test_device_errors():
    il, *_ = _fixture()
    mb = DeviceError("load-cell conditioner", "modbus-tcp://h:1", "no answer")
    assert il.device_error(0.1, mb, {"modbus": 2}) is None
    tr = il.device_error(0.1, mb, {"modbus": 3})
    assert tr.name == "modbus_errors" and "modbus-tcp://h:1" in tr.message
    can_err = DeviceError("servovalve controller", "can-x", "CAN send failed", kind="bus")
    assert il.device_error(0.1, can_err, {"can": 1}) is None
    assert il.device_error(0.1, can_err, {"can": 2}).name == "can_bus_errors"
    lost = DeviceError("LVDT conditioner", "serial:/dev/x", "port lost")
    tr = il.device_error(0.2, lost, {})
    assert tr.name == "device_lost" and tr.values["address"] == "serial:/dev/x"
