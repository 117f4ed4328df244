"""The safety chain's I/O frames, byte by byte with no I/O (pymeasure's expected_protocol style), and the
I/O module emulator's answers and relay logic through the same codec."""

from __future__ import annotations

import pytest

from drivers.safety_io import decode_answer, encode_read_inputs, encode_write_coils, pack_bits, unpack_bits


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
