"""The safety chain's I/O frames, byte by byte with no I/O (pymeasure's expected_protocol style), and the
I/O module emulator's answers and relay logic through the same codec."""

from __future__ import annotations

import multiprocessing as mp
import time

from drivers.config import SafetyConfig
from drivers.emulators.modbus_io import IoModuleEmulator, IoState
from drivers.safety_io import decode_answer, encode_read_inputs, encode_write_coils, unpack_bits


CFG = SafetyConfig(port=1502, estop_input=0, pressure_ok_input=1, enable_output=0, watchdog_output=1,
                   watchdog_s=0.05)


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
