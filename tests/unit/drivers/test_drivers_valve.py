"""The CANopen servovalve link: host driver against the LocalNode emulator on the machine-local bus.

In-process tests run the emulator on a thread; cross-process tests run
``python -m drivers.emulators.valve_controller`` in a subprocess. All use the real
transport (:mod:`drivers.canopen_bus`), each test on its own channel. Timeouts are
generous (polling with deadlines), never tight latency asserts.
"""

from __future__ import annotations

import subprocess

import can
import pytest

from drivers.canopen_bus import BATCH_MAX, decode_frame, decode_frames, encode_frame, encode_frames


pytestmark = pytest.mark.timeout(120)


def test_frame_codec_exact_bytes_and_rejects():
    m = can.Message(arbitration_id=0x203, data=b"\x01\x02\x03", is_extended_id=False)
    raw = encode_frame(m)
    assert raw.hex() == "000003020000" + "03" + "010203"
    back = decode_frame(raw)
    assert back.arbitration_id == 0x203 and bytes(back.data) == b"\x01\x02\x03"
    for bad in (b"", b"\x00" * 3, raw + b"\x00", raw[:-1], b"\x07" + raw[1:],
                bytes.fromhex("0000ff0f0000") + b"\x00",              # 11-bit id out of range
                bytes.fromhex("000003020000") + b"\x09" + b"\x00" * 9):  # dlc 9
        assert decode_frame(bad) is None


def test_batch_codec_exact_bytes_and_rejects():
    """Several frames in one message (the set-point PDO and the SYNC: one send, one wake-up of the
    peer): exact bytes; anything that does not add up exactly is rejected whole."""
    raw = encode_frames(((0x203, b"\x10\x00\x01\x00\x07"), (0x080, b"\x05")))
    assert raw.hex() == "0102" + "000003020000" + "05" + "1000010007" + "000080000000" + "01" + "05"
    assert decode_frames(raw) == [(0x203, 0, b"\x10\x00\x01\x00\x07"), (0x080, 0, b"\x05")]
    assert encode_frames(((0x080, b"\x05"),)) == encode_frame(can.Message(arbitration_id=0x80, data=b"\x05",
                                                                             is_extended_id=False))
    one = encode_frames(((0x080, b"\x05"),))
    for bad in (raw[:-1], raw + b"\x00", b"\x01\x02" + one, b"\x01\x01" + one, b"\x01\x00",
                bytes((1, BATCH_MAX + 1)) + one * (BATCH_MAX + 1),
                b"\x01\x02" + raw + one,                               # a batch inside a batch
                b"\x01\x02" + one + bytes.fromhex("0000ff0f000000")):  # 11-bit id out of range
        assert decode_frames(bad) is None
    assert decode_frame(raw) is None  # one frame expected: a batch is not one
    for bad in ([], [(0x80, b"")] * (BATCH_MAX + 1), [(0x800, b"")], [(0x80, b"\x00" * 9)]):
        with pytest.raises(ValueError):
            encode_frames(bad)


def test_dither_check_judges_only_a_dithered_command():
    """No dither in the command (or one below dither_min_command): nothing to judge, no trip;
    a lag of one tick (sign flipped) or a constant offset is still following."""
    from drivers.valve import DitherCheck

    d = DitherCheck(32, 3.3, 0.1)
    for k in range(200):
        d.add(k & 0xFF, 5, 5)                  # constant command, a spool that sits: not judged
    assert not d.failed and d.gain != d.gain   # NaN: never judged
    for k in range(200):
        c = 16 if k % 2 else -16
        d.add(k & 0xFF, c, -c // 3 + 40)       # one tick late (inverted), offset, attenuated to 1/3
    assert not d.failed and d.gain == pytest.approx(1 / 3, abs=0.02)
    for k in range(200, 240):
        d.add(k & 0xFF, 16 if k % 2 else -16, 40)  # the spool stops
    assert d.failed and d.gain < 0.1
