"""LVDT frames: exact bytes, a parser that survives garbage, and the driver over a pty."""

from __future__ import annotations

import time

import pytest

from drivers.config import LvdtConfig
from drivers.emulators.lvdt_streamer import LvdtStreamer
from drivers.errors import DeviceError
from drivers.lvdt import LvdtReader


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
