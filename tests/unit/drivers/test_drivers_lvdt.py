"""LVDT frames: exact bytes, a parser that survives garbage, and the driver over a pty."""

from __future__ import annotations

from drivers.lvdt import FrameParser, encode_frame


def test_frame_exact_bytes():
    # sync A5 5A | seq 0x1234 LE | counts 6579 LE | status 0 | CRC-16/CCITT-FALSE big-endian
    assert encode_frame(0x1234, 6579, 0).hex() == "a55a3412b319000000d07d"
    assert len(encode_frame(1, -5)) == 11


def test_parser_split_garbage_corruption_and_loss():
    p = FrameParser()
    stream = encode_frame(1, 100) + b"\x00\xff\xa5junk" + encode_frame(2, 200)
    bad = bytearray(encode_frame(3, 300))
    bad[6] ^= 0x01
    stream += bytes(bad) + encode_frame(5, 500)  # seq 4 lost, 3 corrupted
    out = []
    for i in range(0, len(stream), 4):  # arbitrary split points
        out += p.feed(stream[i:i + 4])
    assert [f[1] for f in out] == [100, 200, 500]
    assert p.bad_frames == 1
    assert p.garbage_bytes >= 6
    assert p.lost_frames == 2  # 3 (bad) and 4 (dropped)
    # a sync pair inside garbage, then a truncated frame at the end: kept for later
    assert p.feed(b"\xa5\x5a\x01") == []
    assert p.feed(b"") == []


def test_parser_random_garbage_never_crashes():
    import random

    rnd = random.Random(5)
    p = FrameParser()
    n_good = 0
    for k in range(200):
        junk = bytes(rnd.randrange(256) for _ in range(rnd.randrange(20)))
        n_good += len(p.feed(junk + encode_frame(k, k)))
    assert n_good >= 190  # at most a few frames eaten by a junk prefix ending in A5 5A...
    assert len(p.buf) < 64


def test_parser_one_frame_per_read_counts_as_the_general_path():
    """The usual tick hands the parser exactly one frame: a good one, a corrupted one (bad CRC: counted,
    nothing kept), a gap in the sequence (lost frames counted), then a split frame: same counts as ever."""
    p = FrameParser()
    assert p.feed(encode_frame(1, 100)) == [(1, 100, 0)]
    bad = bytearray(encode_frame(2, 200))
    bad[5] ^= 0x01
    assert p.feed(bytes(bad)) == [] and p.bad_frames == 1
    assert p.feed(encode_frame(5, -7, 2)) == [(5, -7, 2)] and p.lost_frames == 3
    f = encode_frame(6, 9)
    assert p.feed(f[:4]) == [] and p.feed(f[4:]) == [(6, 9, 0)]
    assert (p.good_frames, p.bad_frames, p.lost_frames, p.buf) == (3, 1, 3, bytearray())
