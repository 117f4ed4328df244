"""The servovalve's frames, frame by frame, with no bus (in the manner of pymeasure's expected_protocol):
each value packs to the exact bytes a CiA 408 valve expects, and each status frame unpacks to its bits."""

from __future__ import annotations

import pytest

from drivers.valve import (
    SYNC_OVERFLOW, StatusFrame, control_word, decode_status, encode_setpoint, encode_sync, next_sync_count,
)


@pytest.mark.parametrize("setpoint,enable,reset,counter,frame", [
    (0.0, True, False, 1, bytes([0x00, 0x00, 0x01, 0x00, 0x01])),
    (1.0, True, False, 2, bytes([0x00, 0x40, 0x01, 0x00, 0x02])),       # +16384 = +100 %
    (-1.0, True, False, 3, bytes([0x00, 0xC0, 0x01, 0x00, 0x03])),      # -16384
    (2.5, True, False, 4, bytes([0x00, 0x40, 0x01, 0x00, 0x04])),       # saturated
    (0.5, False, False, 5, bytes([0x00, 0x00, 0x00, 0x00, 0x05])),      # disabled: nulled, enable bit clear
    (0.0, False, True, 255, bytes([0x00, 0x00, 0x08, 0x00, 0xFF])),     # fault reset
    (0.25, True, False, 256 + 7, bytes([0x00, 0x10, 0x01, 0x00, 0x07])),  # counter wraps at u8
    (1e-3, True, False, 9, bytes([0x10, 0x00, 0x01, 0x00, 0x09])),      # 16.384 counts -> 16
])
def test_setpoint_frames(setpoint, enable, reset, counter, frame):
    assert encode_setpoint(setpoint, enable, reset, counter) == frame


def test_control_word_bits():
    assert (control_word(False), control_word(True), control_word(False, True), control_word(True, True)) == \
        (0x0, 0x1, 0x8, 0x9)


def test_sync_counter_runs_1_to_240():
    c, seen = 0, []
    for _ in range(SYNC_OVERFLOW + 2):
        c = next_sync_count(c)
        seen.append(c)
    assert seen[0] == 1 and seen[SYNC_OVERFLOW - 1] == SYNC_OVERFLOW and seen[SYNC_OVERFLOW] == 1
    assert encode_sync(240) == b"\xf0"


@pytest.mark.parametrize("frame,want", [
    # actual (int16 LE), status word (u16 LE), accepted counter, rejected frames
    (bytes([0x00, 0x20, 0x01, 0x00, 0x11, 0x00]), dict(spool_actual=0.5, enabled=True, fault=False,
                                                        watchdog_tripped=False, nulled=False,
                                                        reset_required=False, accepted_counter=0x11, rejected=0)),
    (bytes([0x00, 0x00, 0x1C, 0x00, 0x12, 0x03]), dict(spool_actual=0.0, enabled=False, fault=False,
                                                        watchdog_tripped=True, nulled=True, reset_required=True,
                                                        accepted_counter=0x12, rejected=3)),
    (bytes([0x00, 0xC0, 0x02, 0x00, 0x00, 0x00]), dict(spool_actual=-1.0, enabled=False, fault=True)),
    (bytes([0x00, 0x00, 0x40, 0x00, 0x00, 0x00]), dict(fault=True)),   # protocol error
    (bytes([0x00, 0x00, 0x20, 0x00, 0x00, 0x00]), dict(fault=True)),   # host heartbeat lost
])
def test_status_frames(frame, want):
    st = decode_status(frame)
    assert isinstance(st, StatusFrame)
    for k, v in want.items():
        assert getattr(st, k) == v, k


@pytest.mark.parametrize("n", [0, 5, 7, 8])
def test_a_status_frame_of_another_length_is_refused(n):
    with pytest.raises(ValueError, match=f"{n} bytes"):
        decode_status(bytes(n))
