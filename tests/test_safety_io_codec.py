"""The safety chain's I/O frames, byte by byte with no I/O (pymeasure's expected_protocol style), and the
I/O module emulator's answers and relay logic through the same codec."""

from __future__ import annotations

import multiprocessing as mp
import time

import pytest

from drivers.config import SafetyConfig
from drivers.emulators.modbus_io import IoModuleEmulator, IoState
from drivers.safety_io import decode_answer, encode_read_inputs, encode_write_coils, pack_bits, unpack_bits

CFG = SafetyConfig(port=1502, estop_input=0, pressure_ok_input=1, enable_output=0, watchdog_output=1,
                   watchdog_s=0.05)


def test_bits_pack_lsb_first():
    assert pack_bits([True, False, True]) == b"\x05"
    assert pack_bits([False] * 8 + [True]) == b"\x00\x01"
    assert unpack_bits(b"\x05", 3) == [True, False, True]


def test_request_frames():
    # MBAP: tid 0x0102, protocol 0, length 6, unit 1; PDU: function 2, first 0, count 2
    assert encode_read_inputs(0x0102, 1, 0, 2) == bytes.fromhex("0102 0000 0006 01 02 0000 0002")
    # function 15 from coil 0, 2 coils, 1 byte: enable on, watchdog off
    assert encode_write_coils(7, 1, 0, [True, False]) == bytes.fromhex("0007 0000 0008 01 0f 0000 0002 01 01")


@pytest.mark.parametrize("frame,fc,bits,exc", [
    (bytes.fromhex("0005 0000 0004 01 02 01 03"), 2, b"\x03", 0),           # both inputs healthy
    (bytes.fromhex("0006 0000 0004 01 02 01 02"), 2, b"\x02", 0),           # e-stop open
    (bytes.fromhex("0007 0000 0006 01 0f 0000 0002"), 15, b"", 0),          # coils written
    (bytes.fromhex("0008 0000 0003 01 82 02"), 0x82, b"", 2),               # exception 2
])
def test_answer_frames(frame, fc, bits, exc):
    ans, used = decode_answer(frame + b"\x00\x09")  # the next frame's first bytes stay in the buffer
    assert used == len(frame) and ans.fc == fc and ans.bits == bits and ans.exception == exc


def test_partial_and_foreign_frames():
    assert decode_answer(bytes.fromhex("0005 0000 0004 01 02"))[0] is None  # not whole yet
    with pytest.raises(ValueError, match="not a Modbus TCP frame"):
        decode_answer(bytes.fromhex("0005 0001 0004 01 02 01 03"))
    with pytest.raises(ValueError, match="byte count"):
        decode_answer(bytes.fromhex("0005 0000 0004 01 02 02 03"))


def test_emulator_answers_and_its_relay():
    st = IoState(mp.get_context("spawn"), CFG.watchdog_s)
    em = IoModuleEmulator(CFG, st)
    ans, _ = decode_answer(em.answer(1, 1, encode_read_inputs(1, 1, 0, 2)[7:]))
    assert unpack_bits(ans.bits, 2) == [True, True]
    em.answer(2, 1, encode_write_coils(2, 1, 0, [True, True])[7:])  # enable on, watchdog toggled
    assert st.amplifier_enabled()
    st.press_estop()
    assert not st.amplifier_enabled()  # the e-stop opens the relay, whatever the software says
    ans, _ = decode_answer(em.answer(3, 1, encode_read_inputs(3, 1, 0, 2)[7:]))
    assert unpack_bits(ans.bits, 2) == [False, True]
    st.press_estop(False)
    assert st.amplifier_enabled()
    time.sleep(CFG.watchdog_s * 1.5)  # the watchdog output stopped toggling: the relay drops the enable
    assert not st.amplifier_enabled()
    ans, _ = decode_answer(em.answer(4, 1, bytes([0x05, 0, 0, 0xFF, 0])))  # function 5: not served
    assert ans.exception == 1


def test_the_driver_against_the_emulator_tick_by_tick():
    """The per-tick path (outputs + inputs in one send, the answers taken the next tick): the watchdog
    toggles, the amplifier's enable follows, an open e-stop becomes the `estop` problem."""
    from drivers.emulators.modbus_conditioner import free_tcp_port
    from drivers.safety_io import SafetyIO

    cfg = CFG.model_copy(update={"port": free_tcp_port(), "timeout_s": 0.5})
    st = IoState(mp.get_context("spawn"), 0.5)
    em = IoModuleEmulator(cfg, st)
    em.start()
    io = SafetyIO(cfg)
    try:
        io.connect()
        io.poll()
        assert io.estop_ok and io.pressure_ok and io.outputs == [False, False]

        def tick():
            t_end = time.monotonic() + 1.0
            n = io.health().frames_ok
            io.write()
            while io.health().frames_ok == n and time.monotonic() < t_end:
                time.sleep(0.001)
                io.read()

        io.enable = True
        for _ in range(4):
            tick()
        assert st.amplifier_enabled() and io.health().problems == []
        st.press_estop()
        tick()
        assert [p[0] for p in io.health().problems] == ["estop"] and not st.amplifier_enabled()
        st.press_estop(False)
        st.lose_pressure()
        tick()
        assert [p[0] for p in io.health().problems] == ["hydraulic_pressure"]
        assert io.safe_stop() and not st.snapshot()["enable_coil"]
    finally:
        io.close()
        em.stop()
