"""Load-cell driver against the pymodbus emulator over real transports (TCP, RTU over ptys)."""

from __future__ import annotations

import time

import pytest

from drivers.config import LoadCellConfig
from drivers.emulators.modbus_conditioner import ModbusConditionerEmulator
from drivers.emulators.pty import PtyBridge
from drivers.emulators.modbus_conditioner import free_tcp_port
from drivers.errors import DeviceError
from drivers.loadcells import LoadCellReader, encode_value


def _serve(cfg, **kw):
    em = ModbusConditionerEmulator(cfg, **kw)
    em.start()
    return em


@pytest.fixture
def tcp_cfg():
    return LoadCellConfig(transport="tcp", host="127.0.0.1", port=free_tcp_port(), timeout_s=0.05)


def test_tcp_float32_one_request_exact_registers_and_calibration(tcp_cfg):
    cfg = LoadCellConfig.model_validate({**tcp_cfg.model_dump(),
                                         "friction": {"address": 2, "scale": 2.0, "offset": 1.0}})
    em = _serve(cfg)
    try:
        em.update(-12.5, 101.25, 98.75)  # forces in N (the emulator stores raw = (F - offset)/scale)
        rd = LoadCellReader(cfg)
        rd.connect()
        regs = rd.read_raw()
        assert em.n_requests == 1  # one request covers counter, status and the three channels
        assert regs[0] == em.counter and regs[1] == 0
        assert regs[2:4] == encode_value(-6.75, "float32", "big")
        assert regs[4:8] == encode_value(101.25, "float32", "big") + encode_value(98.75, "float32", "big")
        f, n1, n2 = rd.read()
        assert (f, n1, n2) == pytest.approx((-12.5, 101.25, 98.75), abs=1e-5)
        # tare: the current readings become the zeros
        tares = rd.tare(n=3)
        assert tares["normal_1"] == pytest.approx(101.25, abs=1e-5)
        assert rd.read() == pytest.approx((0.0, 0.0, 0.0), abs=1e-5)
        rd.close()
    finally:
        em.stop()


def test_tcp_int16_scaled_little_endian_holding(tcp_cfg):
    cfg = LoadCellConfig.model_validate({
        **tcp_cfg.model_dump(), "encoding": "int16", "register_type": "holding", "word_order": "little",
        "counter_address": 10, "status_address": None,
        "friction": {"address": 11, "scale": 0.01}, "normal_1": {"address": 12, "scale": 0.01},
        "normal_2": {"address": 13, "scale": 0.01}})
    assert cfg.span() == (10, 4)
    em = _serve(cfg)
    try:
        em.update(3.21, 100.0, -0.5)
        rd = LoadCellReader(cfg)
        rd.connect()
        assert rd.read_raw()[1:] == [321, 10000, 0xFFCE]
        assert rd.read() == pytest.approx((3.21, 100.0, -0.5))
        rd.close()
    finally:
        em.stop()


def test_exception_slow_silent_and_recovery(tcp_cfg):
    em = _serve(tcp_cfg)
    rd = LoadCellReader(tcp_cfg)
    try:
        rd.connect()
        rd.read()
        em.faults["exception"] = True
        with pytest.raises(DeviceError) as ei:
            rd.read()
        assert "exception" in str(ei.value) and f"127.0.0.1:{tcp_cfg.port}" in str(ei.value)
        assert ei.value.kind == "protocol"
        em.faults.clear()
        em.faults["slow_s"] = 0.2  # slower than the 50 ms timeout
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as ei:
            rd.read()
        assert time.monotonic() - t0 < 0.15
        assert "load-cell conditioner" in str(ei.value) and "no answer" in str(ei.value)
        em.faults.clear()
        time.sleep(0.25)
        # a late answer must not be taken for the next one (the driver reconnects)
        em.update(7.0, 100.0, 100.0)
        assert rd.read()[0] == pytest.approx(7.0)
        assert rd.consecutive_errors == 0 and rd.n_errors == 2
        # frozen sample counter: the data ages
        em.faults["freeze_counter"] = True
        rd.read()
        time.sleep(0.03)
        em.update(8.0, 100.0, 100.0)
        rd.read()
        assert rd.reads_since_new >= 1 and rd.age_s() >= 0.03
    finally:
        rd.close()
        em.stop()


def test_connection_refused_names_device_and_address():
    port = free_tcp_port()
    rd = LoadCellReader(LoadCellConfig(port=port, timeout_s=0.05))
    with pytest.raises(DeviceError) as ei:
        rd.connect()
    assert f"load-cell conditioner at modbus-tcp://127.0.0.1:{port}" in str(ei.value)


def test_server_lost_mid_run(tcp_cfg):
    em = _serve(tcp_cfg)
    rd = LoadCellReader(tcp_cfg)
    rd.connect()
    rd.read()
    em.stop()
    with pytest.raises(DeviceError) as ei:
        for _ in range(3):
            rd.read()
    assert str(tcp_cfg.port) in str(ei.value)
    rd.close()


def test_rtu_over_bridged_ptys(tmp_path):
    cfg = LoadCellConfig(transport="rtu", serial_port=str(tmp_path / "lc"), baudrate=115200,
                         timeout_s=0.2, device_id=3)
    bridge = PtyBridge(cfg.serial_port, cfg.serial_port + ".server")
    em = _serve(cfg, rtu_server_port=cfg.serial_port + ".server")
    rd = LoadCellReader(cfg)
    try:
        em.update(1.5, 99.0, 101.0)
        rd.connect()
        assert rd.read() == pytest.approx((1.5, 99.0, 101.0))
        assert "modbus-rtu" in rd.address
    finally:
        rd.close()
        em.stop()
        bridge.close()


@pytest.mark.parametrize("encoding,word_order", [("float32", "big"), ("float32", "little"), ("int32", "little"),
                                                 ("int16", "big")])
def test_pipelined_decodes_as_the_blocking_read(tcp_cfg, encoding, word_order):
    """The loop's pipelined reader (one prebuilt request per tick, the answer collected the next tick)
    decodes every encoding and word order exactly as the blocking pymodbus read does."""
    cfg = LoadCellConfig.model_validate({**tcp_cfg.model_dump(), "encoding": encoding, "word_order": word_order,
                                         "friction": {"address": 2, "scale": 0.5 if encoding != "float32" else 1.0,
                                                      "offset": 0.25},
                                         "normal_1": {"address": 6, "scale": 0.01 if encoding != "float32" else 1.0},
                                         "normal_2": {"address": 9, "scale": 0.01 if encoding != "float32" else 1.0}})
    em = _serve(cfg)
    blocking, pipe = LoadCellReader(cfg), LoadCellReader(cfg, pipelined=True)
    try:
        em.update(-12.25, 101.25, 98.75)
        blocking.connect()
        pipe.connect()
        want = blocking.read()
        assert want == pytest.approx((-12.25, 101.25, 98.75), abs=0.01)
        assert pipe.read() == (pytest.approx(float("nan"), nan_ok=True),) * 3  # request sent, nothing yet
        got = None
        t_end = time.monotonic() + 2.0
        while got is None and time.monotonic() < t_end:
            time.sleep(0.002)
            if pipe.n_reads == 0:
                pipe.read()
            got = pipe.forces_N if pipe.n_reads else None
        assert got == want  # bit for bit (nothing updated the registers in between)
        assert pipe.status == 0 and pipe.consecutive_errors == 0
    finally:
        blocking.close()
        pipe.close()
        em.stop()


class _RawModbusServer:
    """A Modbus TCP server on a real socket that answers each request with ``answer(request)`` bytes."""

    def __init__(self, answer):
        import socket
        import threading

        self.answer = answer
        self.lst = socket.create_server(("127.0.0.1", 0))
        self.port = self.lst.getsockname()[1]
        self.th = threading.Thread(target=self._serve, daemon=True)
        self.th.start()

    def _serve(self):
        try:
            c, _ = self.lst.accept()
            with c:
                while True:
                    req = c.recv(12)
                    if len(req) < 12:
                        return
                    c.sendall(self.answer(req))
        except OSError:  # the client hung up (its close after the test)
            return

    def close(self):
        self.lst.close()


def _answer(req, *, unit=None, pid=0, fc=None, regs=8, exception=None):
    import struct

    tid, _, _, u, f, _first, count = struct.unpack(">HHHBBHH", req)
    if exception is not None:
        pdu = bytes((unit if unit is not None else u, f | 0x80, exception))
    else:
        pdu = bytes((unit if unit is not None else u, fc if fc is not None else f, 2 * regs)) + b"\x00\x01" * regs
    return struct.pack(">HHH", tid, pid, len(pdu)) + pdu


@pytest.mark.parametrize("kw,words", [({"unit": 9}, "unit 9"), ({"exception": 2}, "exception response (code 2)"),
                                      ({"fc": 3}, "malformed"), ({"regs": 7}, "malformed"),
                                      ({"pid": 5}, "no answer")])
def test_pipelined_validates_every_answer(kw, words):
    """Every answer is checked: unit id, exception, function code, byte count; not Modbus TCP at all
    (a protocol id other than 0) is never used and times out."""
    srv = _RawModbusServer(lambda req: _answer(req, **kw))
    rd = LoadCellReader(LoadCellConfig(port=srv.port, timeout_s=0.05), pipelined=True)
    try:
        rd.connect()
        rd.read()  # sends the first request
        with pytest.raises(DeviceError) as ei:
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                time.sleep(0.002)
                rd.read()
        assert words in str(ei.value) and f"127.0.0.1:{srv.port}" in str(ei.value)
        assert rd.n_reads == 0 and rd.n_errors == 1
    finally:
        rd.close()
        srv.close()


def test_pipelined_server_gone_is_lost_at_once_and_stays_lost(tcp_cfg):
    """The conditioner's process dies mid-run (its TCP connection closed or reset): the pipelined
    reader says so as a ``lost`` error, which the loop trips on at once, and every later read says
    so again; it never returns the last forces as if they were new (that kept a trial running on
    frozen forces before)."""
    em = _serve(tcp_cfg)
    rd = LoadCellReader(tcp_cfg, pipelined=True)
    try:
        rd.connect()
        t_end = time.monotonic() + 2.0
        while rd.n_reads < 3 and time.monotonic() < t_end:
            rd.read()
            time.sleep(0.002)
        assert rd.n_reads >= 3
        em.stop()
        with pytest.raises(DeviceError) as ei:
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                time.sleep(0.002)
                rd.read()
        assert ei.value.kind == "lost" and str(tcp_cfg.port) in str(ei.value)
        with pytest.raises(DeviceError) as again:
            rd.read()
        assert again.value.kind == "lost"
    finally:
        rd.close()
