"""LVDT frames: exact bytes, a parser that survives garbage, and the driver over a pty."""

from __future__ import annotations

import time

import pytest

from drivers.config import LvdtConfig
from drivers.emulators.lvdt_streamer import LvdtStreamer
from drivers.errors import DeviceError
from drivers.lvdt import FrameParser, LvdtReader, encode_frame


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


@pytest.fixture
def streamer(tmp_path):
    cfg = LvdtConfig(port=str(tmp_path / "lvdt"), baudrate=921600, um_per_count=0.076, offset_um=10.0)
    st = LvdtStreamer(cfg)
    st.start()
    yield st
    st.stop()


def test_reader_over_pty(streamer):
    rd = LvdtReader(streamer.cfg)
    rd.connect()
    try:
        for x in (500.0, 500.5, 501.0):
            streamer.send(x)
        time.sleep(0.01)
        assert rd.poll() == 3
        assert rd.position_um == pytest.approx(501.0, abs=0.038)  # half a 0.076 µm step
        assert rd.seq == streamer.seq
        # faults: every 3rd frame corrupted, every 4th dropped, garbage before every 5th
        streamer.faults.update(corrupt_every=3, drop_every=4, garbage_every=5)
        for k in range(60):
            streamer.send(600.0 + k)
        time.sleep(0.02)
        rd.poll()
        pr = rd.parser
        assert pr.bad_frames >= 10 and pr.garbage_bytes > 0 and pr.lost_frames >= 20
        assert rd.position_um > 600.0
        # silent device: nothing new, the data ages
        streamer.faults = {"silent": True}
        t = time.monotonic()
        time.sleep(0.02)
        assert rd.poll() == 0 and rd.age_s() >= time.monotonic() - t - 1e-3
    finally:
        rd.close()


def test_port_vanishes(streamer):
    rd = LvdtReader(streamer.cfg)
    rd.connect()
    streamer.send(1.0)
    time.sleep(0.005)
    rd.poll()
    streamer.vanish()
    with pytest.raises(DeviceError) as ei:
        for _ in range(20):
            rd.poll()
            time.sleep(0.002)
    assert "LVDT conditioner at serial:" in str(ei.value) and streamer.cfg.port in str(ei.value)
    rd.close()
    with pytest.raises(DeviceError) as ei:
        LvdtReader(streamer.cfg).connect()
    assert "cannot open port" in str(ei.value)


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
