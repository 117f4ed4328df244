"""The CANopen servovalve link: host driver against the LocalNode emulator on the machine-local bus.

In-process tests run the emulator on a thread; cross-process tests run
``python -m drivers.emulators.valve_controller`` in a subprocess. All use the real
transport (:mod:`drivers.canopen_bus`), each test on its own channel. Timeouts are
generous (polling with deadlines), never tight latency asserts.
"""

from __future__ import annotations

from pathlib import Path
import json
import os
import subprocess
import sys
import threading
import time
import uuid

import can
import pytest

import rig
from drivers.canopen_bus import F_RTR, UnixCanBus, encode_frames
from drivers.emulators.valve_controller import ValveControllerEmulator, send_foreign, send_malformed
from drivers.errors import DeviceError
from drivers.valve import EMCY_DEVICE_HW, EMCY_HEARTBEAT, EMCY_RPDO_TIMEOUT, SW_HEARTBEAT_LOST, SW_PROTOCOL, SW_WATCHDOG, CanopenValve, CanopenValveConfig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install


pytestmark = pytest.mark.timeout(120)


NODE = 3


def _cfg(**kw) -> CanopenValveConfig:
    """A private channel; timeouts generous so that a loaded machine's stalls do not trip tests
    that are about something else (the profile defaults are 0.05 s heartbeat, 0.02 s watchdog)."""
    kw = {"heartbeat_timeout_s": 0.5, "watchdog_s": 0.3, "tpdo_timeout_s": 0.5, **kw}
    return CanopenValveConfig(channel=f"test-{uuid.uuid4().hex[:12]}", node_id=NODE, **kw)


def _until(pred, timeout_s=3.0, every=None):
    """Poll ``pred`` (calling ``every`` between polls) until true or ``timeout_s``; returns its value."""
    t_end = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v or time.monotonic() > t_end:
            return v
        if every is not None:
            every()
        time.sleep(0.001)


class EmuThread:
    """The emulator polled on a thread of this process."""

    def __init__(self, cfg, **kw):
        self.em = ValveControllerEmulator(cfg, **kw)
        self._stop = threading.Event()
        self.em.start()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self):
        while not self._stop.is_set():
            self.em.poll(0.001)

    def close(self):
        self._stop.set()
        self._th.join(2)
        self.em.stop()


class EmuProcess:
    """The emulator in its own process (stdin commands, JSON lines on stdout)."""

    def __init__(self, cfg):
        self.p = subprocess.Popen(
            [sys.executable, "-m", "drivers.emulators.valve_controller", "--channel", cfg.channel,
             "--node-id", str(cfg.node_id)], cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        line = self.p.stdout.readline()
        assert json.loads(line)["ready"], line + self.p.stderr.read()

    def cmd(self, text):
        self.p.stdin.write(text + "\n")
        self.p.stdin.flush()

    def stats(self) -> dict:
        self.cmd("stats")
        return json.loads(self.p.stdout.readline())

    def close(self):
        if self.p.poll() is None:
            try:
                self.cmd("quit")
                self.p.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.p.kill()
                self.p.wait()


@pytest.fixture
def inproc():
    cfg = _cfg()
    emu = EmuThread(cfg)
    v = CanopenValve(cfg)
    yield cfg, emu.em, v
    v.close()
    emu.close()


@pytest.fixture
def xproc():
    cfg = _cfg()
    emu = EmuProcess(cfg)
    v = CanopenValve(cfg)
    yield cfg, emu, v
    v.close()
    emu.close()


def _drive(v, cmd, pred, timeout_s=5.0):
    """Tick (read + write ``cmd``) until ``pred()`` is true or ``timeout_s``; returns its value."""
    return _until(pred, timeout_s, every=lambda: (v.read(), v.send(cmd)))


def _ticks(v, n, cmd=0.3, **kw):
    st = None
    for _ in range(n):
        st = v.read()
        v.send(cmd, **kw)
        time.sleep(0.001)
    return v.read() if st is None else st


def test_batch_over_the_bus_arrives_as_ordinary_frames_in_order():
    a = UnixCanBus(channel="t-" + uuid.uuid4().hex)
    b = UnixCanBus(channel=a.channel)
    try:
        a.send_frames(((0x203, b"\x01\x02\x03\x04\x05"), (0x080, b"\x07")))
        first = b.recv(2.0)
        second = b.recv(0.5)
        assert (first.arbitration_id, bytes(first.data)) == (0x203, b"\x01\x02\x03\x04\x05")
        assert (second.arbitration_id, bytes(second.data)) == (0x080, b"\x07")
        assert not first.is_extended_id and first.channel == a.channel
        # the real-time drain: every frame queued, as tuples, oldest first; a bad batch counted once
        a.send(can.Message(arbitration_id=0x181, data=b"\x00" * 6, is_extended_id=False))
        a.send_raw(encode_frames(((0x203, b"\x01"), (0x080, b"\x07")))[:-1])
        a.send_frames(((0x701, b"\x05"), (0x081, b"\x00" * 8)))
        a.send(can.Message(arbitration_id=0x600, is_remote_frame=True, is_extended_id=False))
        time.sleep(0.05)
        b._next_full = time.monotonic() + 10.0  # the gated drain (SIOCINQ: every queued message's bytes)
        got = b.drain_frames()
        assert [(cid, flags, len(d)) for cid, flags, d in got] == [(0x181, 0, 6), (0x701, 0, 1), (0x081, 0, 8),
                                                                   (0x600, F_RTR, 0)]
        assert b.n_malformed == 1 and b.drain_frames() == [] and b.recv(0.02) is None
        # a peer that hung up is noticed by the drain too (SIOCINQ counts nothing for it)
        a.shutdown()
        b._next_full = 0.0
        assert _until(lambda: (b.drain_frames(), b.n_peers == 0)[1], 2.0)
    finally:
        a.shutdown()
        b.shutdown()


def test_bus_broadcast_isolated_channels_and_garbage():
    a, b = UnixCanBus(channel="t-" + uuid.uuid4().hex), None
    try:
        b = can.Bus(interface="rig_unix", channel=a.channel)  # python-can's plugin entry point
        assert isinstance(b, UnixCanBus)
        other = UnixCanBus(channel=a.channel + "x")  # another rig on the same host
        a.send(can.Message(arbitration_id=0x80, data=b"\x01", is_extended_id=False))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x80
        assert other.recv(0.05) is None
        a.send_raw(b"garbage 10 bytes!")
        a.send(can.Message(arbitration_id=0x81, data=b"", is_extended_id=False))
        got = b.recv(2.0)
        assert got.arbitration_id == 0x81 and b.n_malformed == 1
        assert a.recv(0.02) is None  # no own frames
        # a node that sends and leaves at once, with unread frames, while a keeps sending:
        # its frame is still read (the reset connection is drained before it is dropped)
        c = UnixCanBus(channel=a.channel)
        a.send(can.Message(arbitration_id=0x82, data=b"", is_extended_id=False))
        c.send(can.Message(arbitration_id=0x000, data=b"\x01\x00", is_extended_id=False))
        c.shutdown()
        for _ in range(3):
            time.sleep(0.006)
            a.send(can.Message(arbitration_id=0x83, data=b"", is_extended_id=False))
        got = [a.recv(0.5) for _ in range(1)]
        assert got[0] is not None and got[0].arbitration_id == 0x000
        assert a.recv(0.05) is None and a.n_peers == 1   # c is gone, b stays
        other.shutdown()
    finally:
        a.shutdown()
        if b is not None:
            b.shutdown()


def test_no_valve_names_device():
    cfg = _cfg(connect_timeout_s=0.2)
    v = CanopenValve(cfg)
    with pytest.raises(DeviceError) as ei:
        v.connect()
    assert f"servovalve controller at canopen-rig_unix:{cfg.channel} node 3" in str(ei.value)
    assert "no heartbeat" in str(ei.value)
    v.close()
    with pytest.raises(DeviceError, match="not open"):
        v.read()


def test_nmt_start_required_then_follows(inproc):
    cfg, em, v = inproc
    v.connect()
    assert em.nmt_state == "PRE-OPERATIONAL"
    assert em._consumer_s == pytest.approx(cfg.heartbeat_timeout_s)  # configured by SDO
    st = _ticks(v, 30, 0.5)          # set-points before NMT start are ignored
    assert em.spool == 0.0 and em.n_setpoints == 0 and st.n_tpdo == 0
    v.start()
    assert em.nmt_state == "OPERATIONAL" and em.enabled
    st = _until(lambda: abs(v.read().spool_actual - 0.5) < 1e-3, every=lambda: v.send(0.5))
    assert st and [msg for _, msg in v.problems()] == []
    st = v.read()
    assert st.operational and st.enabled and not st.nulled and st.counter_errors == 0
    assert v.safe_stop() is True
    assert em.spool == 0.0 and not em.enabled
    assert _until(lambda: em.nmt_state == "PRE-OPERATIONAL")
    v.start()                        # a clean restart after a verified stop
    assert _drive(v, -0.1, lambda: abs(em.spool + 0.1) < 1e-3)


def test_heartbeat_loss_nulls_and_leaves_operational(inproc):
    cfg, em, v = inproc
    v.connect()
    v.start()
    assert _drive(v, 0.4, lambda: abs(em.spool - 0.4) < 1e-3)
    # the loop dies: no set-point, no SYNC, no host heartbeat
    assert _until(lambda: em.nmt_state == "PRE-OPERATIONAL", 3.0)
    assert em.spool == 0.0 and not em.enabled
    assert em.latched & SW_HEARTBEAT_LOST and EMCY_HEARTBEAT in em.emcy_sent
    st = _until(lambda: (s := v.read()).nmt_state == "PRE-OPERATIONAL" and s, 3.0)
    assert st and (EMCY_HEARTBEAT, 1) in st.emcy
    assert any("not OPERATIONAL" in p for p in [msg for _, msg in v.problems()])
    # set-points alone do not bring it back; an explicit start (NMT + fault reset + enable) does
    _ticks(v, 20, 0.4)
    assert em.spool == 0.0
    v.start()
    assert _drive(v, -0.2, lambda: em.enabled and abs(em.spool + 0.2) < 1e-3 and em.latched == 0)


def test_host_heartbeat_alone_is_consumed():
    """Set-points keep coming but the host's heartbeat stops: the valve still nulls."""
    cfg = _cfg()
    emu = EmuThread(cfg)
    v = CanopenValve(cfg)
    try:
        v.connect()
        v.start()
        _ticks(v, 10, 0.3)
        v._next_hb = float("inf")   # heartbeat producer stalls, the tick goes on
        _until(lambda: emu.em.nmt_state == "PRE-OPERATIONAL", 3.0, every=lambda: (v.read(), v.send(0.3)))
        assert emu.em.nmt_state == "PRE-OPERATIONAL" and emu.em.spool == 0.0
        assert EMCY_HEARTBEAT in emu.em.emcy_sent and EMCY_RPDO_TIMEOUT not in emu.em.emcy_sent
    finally:
        v.close()
        emu.close()


def test_silent_valve_is_unhealthy(inproc):
    cfg, em, v = inproc
    v.connect()
    v.start()
    _ticks(v, 5, 0.1)
    assert [msg for _, msg in v.problems()] == []
    em.inject("silent")
    def both():
        v.read()
        h = [msg for _, msg in v.problems()]
        return any("no heartbeat" in p for p in h) and any("no status PDO" in p for p in h)

    assert _until(both, 5.0, every=lambda: v.send(0.1))


def test_emcy_on_fault_and_reset_required(inproc):
    cfg, em, v = inproc
    v.connect()
    v.start()
    _ticks(v, 10, 0.3)
    em.inject("fault")
    st = _until(lambda: (s := v.read()).fault and s.emcy and s, 3.0, every=lambda: v.send(0.3))
    assert st and (EMCY_DEVICE_HW, 1) in st.emcy and st.spool_actual == 0.0 and not st.enabled
    assert any("reports a fault" in p and "0x5000" in p for p in [msg for _, msg in v.problems()])
    em.inject("fault", None)
    st = _ticks(v, 30, 0.3)          # the cause is gone, enable is still set: stays off
    assert not st.enabled and st.reset_required and em.spool == 0.0
    v.start()                        # fault reset, enable low, enable high
    st = _until(lambda: (s := v.read()).enabled and abs(s.spool_actual - 0.3) < 1e-3 and s, 3.0,
                every=lambda: v.send(0.3))
    assert st and st.emcy == [] and not st.reset_required


def test_watchdog_null_needs_reset():
    cfg = _cfg(heartbeat_timeout_s=2.0, watchdog_s=0.02)
    emu = EmuThread(cfg)
    v = CanopenValve(cfg)
    try:
        v.connect()
        v.start()
        _ticks(v, 10, 0.3)
        t_end = time.monotonic() + 0.3      # the loop pauses (heartbeat goes on)
        while time.monotonic() < t_end:
            v._heartbeat_if_due(time.monotonic())
            time.sleep(0.005)
        assert _until(lambda: emu.em.latched & SW_WATCHDOG, 3.0)
        st = _drive(v, 0.3, lambda: (s := v.read()).watchdog_tripped and s)
        assert st and st.watchdog_tripped and not st.enabled and emu.em.spool == 0.0
        assert (EMCY_RPDO_TIMEOUT, 1) in st.emcy
        assert emu.em.nmt_state == "OPERATIONAL"   # the heartbeat was fine
        v.start()
        st = _drive(v, 0.3, lambda: (s := v.read()).enabled and abs(s.spool_actual - 0.3) < 1e-3 and s)
        assert st and not st.watchdog_tripped and emu.em.spool == pytest.approx(0.3, abs=1e-3)
    finally:
        v.close()
        emu.close()


@pytest.mark.parametrize("fault", ["ignore_setpoints", "stuck"])
def test_valve_not_following_is_unhealthy_within_100_ticks(fault):
    """Profile defaults (follow_max 0.1, follow_time_s 0.05): caught within 100 ms of ticks."""
    cfg = _cfg(follow_max=0.1, follow_time_s=0.05)
    emu = EmuThread(cfg)
    v = CanopenValve(cfg)
    try:
        v.connect()
        v.start()
        _ticks(v, 10, 0.3)
        emu.em.inject(fault)
        ticks = 0
        while ticks < 1000:
            v.read()
            if any("does not follow" in p for p in [msg for _, msg in v.problems()]):
                break
            v.send(-0.3)
            ticks += 1
            time.sleep(0.001)
        assert 0 < ticks <= 100, ticks
        st = v.read()
        assert st.enabled and abs(st.spool_actual - st.spool_command_echoed) > 0.1
    finally:
        v.close()
        emu.close()


def _dithered(k: int, level: float = 2e-5, dither: float = 1e-3) -> float:
    """The trial's command: a tiny level (1e-5..1e-3 of full scale) plus the 500 Hz dither cos(pi k)."""
    return level + dither * (1.0 if k % 2 == 0 else -1.0)


@pytest.mark.parametrize("fault", ["ignore_setpoints", "stuck"])
def test_valve_ignoring_small_setpoints_is_caught_by_its_dither_within_100_ticks(fault):
    """At this rig's operating point the command is far below any level check (2e-5 of full scale,
    under one count): only the missing 500 Hz dither in the reported spool shows the dead valve. Profile
    defaults (dither window 32, min gain 0.1); a healthy first-order spool (tau 1 ms) with 2 counts rms
    noise on its position runs first without a trip."""
    cfg = _cfg()
    emu = EmuThread(cfg, spool_tau_s=0.001)
    v = CanopenValve(cfg)
    try:
        v.connect()
        v.start()
        emu.em.inject("spool_noise", 2.0)
        for k in range(400):
            v.read()
            assert [msg for _, msg in v.problems()] == [], (k, [msg for _, msg in v.problems()])
            v.send(_dithered(k))
            time.sleep(0.001)
        assert 0.1 < v.dither.min_gain_seen < 1.0 and v.dither.command_amp > 15   # it was judged
        emu.em.inject(fault)
        ticks = 0
        while ticks < 1000:
            v.read()
            probs = v.problems()
            if probs:
                break
            v.send(_dithered(400 + ticks))
            ticks += 1
            time.sleep(0.001)
        assert [n for n, _ in probs] == ["valve_dither"], probs
        assert 0 < ticks <= 100, ticks
        assert "does not follow its set-points" in probs[0][1] and cfg.address_text in probs[0][1]
    finally:
        v.close()
        emu.close()


def test_nan_setpoint_is_sent_as_null_and_reported(inproc):
    cfg, em, v = inproc
    v.connect()
    v.start()
    _ticks(v, 5, 0.3)
    _ticks(v, 5, float("nan"))
    assert em.spool == 0.0 and not em.enabled
    assert any("non-finite" in p for p in [msg for _, msg in v.problems()])


def _raw(channel):
    return UnixCanBus(channel=channel)


def _while_ticking(v, cmd, fn, *args, **kw):
    """Run ``fn`` (a second node on the bus) on a thread while the host keeps ticking."""
    th = threading.Thread(target=fn, args=args, kwargs=kw, daemon=True)
    th.start()
    while th.is_alive():
        v.read()
        v.send(cmd)
        time.sleep(0.001)


@pytest.mark.parametrize("kind", ["rpdo", "sync", "nmt", "status", "other_node"])
def test_foreign_frame_detected(inproc, kind):
    cfg, em, v = inproc
    v.connect()
    v.start()
    _ticks(v, 10, 0.1)
    assert [msg for _, msg in v.problems()] == []
    _while_ticking(v, 0.1, send_foreign, cfg.channel, kind, NODE, counter=v._counter + 2,
                   sync_count=v._sync_count % 240 + 2)
    probs = _until(lambda: (v.read(), [msg for _, msg in v.problems()])[1], 3.0, every=lambda: v.send(0.1))
    assert any("foreign CAN frames" in p for p in probs), probs
    if kind == "rpdo":   # the valve saw two set-points in one SYNC period or a broken sequence
        assert _until(lambda: em.latched & SW_PROTOCOL, 3.0, every=lambda: v.send(0.1))
        assert em.spool == 0.0 and not em.enabled
        assert em.n_setpoints > 0


def test_foreign_sdo_cannot_disable_the_heartbeat_consumer(inproc):
    import canopen

    cfg, em, v = inproc
    v.connect()
    v.start()
    _ticks(v, 5, 0.1)
    consumer = em._consumer_s
    net = canopen.Network(_raw(cfg.channel))
    node = canopen.RemoteNode(NODE, str(v.eds))
    net.add_node(node)
    stop = threading.Event()

    def pump():
        while not stop.is_set():
            m = net.bus.recv(0.002)
            if m is not None:
                net.notify(m.arbitration_id, m.data, m.timestamp)

    th = threading.Thread(target=pump, daemon=True)
    th.start()
    try:
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo[0x1016][1].raw = 0
        assert em._consumer_s == consumer
        assert _until(lambda: 0x603 in (v.read(), v.foreign_ids)[1], 3.0, every=lambda: v.send(0.1))
        assert any("foreign CAN frames" in p and "0x603" in p for p in [msg for _, msg in v.problems()])
    finally:
        stop.set()
        th.join(2)
        net.bus.shutdown()


def test_two_rigs_on_one_channel_detected():
    cfg = _cfg()
    e1, e2 = EmuThread(cfg), EmuThread(cfg.model_copy(update={"node_id": NODE + 1}))
    v1 = CanopenValve(cfg)
    v2 = CanopenValve(cfg.model_copy(update={"node_id": NODE + 1}))
    try:
        v1.connect()
        v1.start()
        _ticks(v1, 5)
        v2.connect()
        _ticks(v2, 5)
        probs = _until(lambda: (v1.read(), [msg for _, msg in v1.problems()])[1], 3.0, every=lambda: v1.send(0.1))
        assert any("foreign CAN frames" in p for p in probs)
    finally:
        for x in (v1, v2, e1, e2):
            x.close()


def test_two_rigs_on_one_host_do_not_see_each_other():
    rigs = []
    try:
        for _ in range(2):
            cfg = _cfg()
            rigs.append((EmuThread(cfg), CanopenValve(cfg)))
            rigs[-1][1].connect()
            rigs[-1][1].start()
        for k in range(100):
            for i, (_, v) in enumerate(rigs):
                v.read()
                v.send(0.1 * (i + 1))
            time.sleep(0.001)
        for i, (e, v) in enumerate(rigs):
            assert _drive(v, 0.1 * (i + 1), lambda: abs(e.em.spool - 0.1 * (i + 1)) < 1e-3)
            st = v.read()
            assert st.foreign_frames == 0 and st.valve_rejected == 0 and e.em.rejected == 0
    finally:
        for e, v in rigs:
            v.close()
            e.close()


def test_malformed_frames_never_crash(xproc):
    cfg, emu, v = xproc
    v.connect()
    v.start()
    _ticks(v, 10, 0.2)
    _while_ticking(v, 0.2, send_malformed, cfg.channel, NODE, cfg.host_node_id)
    probs = _until(lambda: (v.read(), [msg for _, msg in v.problems()])[1], 3.0, every=lambda: v.send(0.2))
    assert probs
    st = emu.stats()                                # the emulator process is alive and answers
    assert emu.p.poll() is None and st["bus_malformed"] >= 5 and st["rejected"] >= 4
    assert st["latched"] & SW_PROTOCOL and st["spool"] == 0.0   # wrong-length set-point nulls
    st_h = v.read()
    assert st_h.malformed_frames >= 1 and any("malformed" in p for p in [msg for _, msg in v.problems()])
    assert _until(lambda: any("rejected" in p for p in (v.read(), [msg for _, msg in v.problems()])[1]), 3.0,
                  every=lambda: v.send(0.2))
    v.start()                                       # and it recovers by the explicit reset
    assert _drive(v, 0.2, lambda: v.read().enabled and abs(emu.stats()["spool"] - 0.2) < 1e-3)


def test_cross_process_follow_fault_and_heartbeat_loss(xproc):
    cfg, emu, v = xproc
    v.connect()
    v.start()
    assert _until(lambda: abs(v.read().spool_actual - 0.25) < 1e-3, 5.0, every=lambda: v.send(0.25))
    assert [msg for _, msg in v.problems()] == []
    emu.cmd("inject fault")
    st = _until(lambda: (s := v.read()).fault and s.emcy and s, 5.0, every=lambda: v.send(0.25))
    assert st and (EMCY_DEVICE_HW, 1) in st.emcy and st.spool_actual == 0.0
    emu.cmd("clear fault")
    v.start()
    assert _until(lambda: abs(v.read().spool_actual - 0.1) < 1e-3, 5.0, every=lambda: v.send(0.1))
    # host stops: the valve process nulls and leaves OPERATIONAL
    assert _until(lambda: emu.stats()["nmt"] == "PRE-OPERATIONAL", 5.0)
    s = emu.stats()
    assert s["spool"] == 0.0 and not s["enabled"] and EMCY_HEARTBEAT in s["emcy_sent"]


def test_cross_process_intruder_detected(xproc):
    """A foreign set-point from a third process: the host reports it, the valve nulls."""
    cfg, emu, v = xproc
    v.connect()
    v.start()
    _ticks(v, 10, 0.2)
    _while_ticking_proc(v, 0.2, [sys.executable, "-m", "drivers.emulators.valve_controller", "--channel",
                                 cfg.channel, "--node-id", str(NODE), "--send-foreign", "rpdo"])
    probs = _until(lambda: any("foreign" in p for p in (v.read(), [msg for _, msg in v.problems()])[1]), 5.0, every=lambda: v.send(0.2))
    assert probs, [msg for _, msg in v.problems()]
    assert _until(lambda: emu.stats()["latched"] & SW_PROTOCOL, 5.0)
    assert emu.stats()["spool"] == 0.0


def _while_ticking_proc(v, cmd, argv):
    p = subprocess.Popen(argv, cwd=REPO)
    while p.poll() is None:
        v.read()
        v.send(cmd)
        time.sleep(0.001)
    assert p.returncode == 0


def _inet_sockets_of(pid: int) -> list[str]:
    """Local addresses of the AF_INET/AF_INET6 sockets ``pid`` holds (from /proc)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = []
    for proto in ("tcp", "udp", "raw", "tcp6", "udp6", "raw6"):
        try:
            lines = open(f"/proc/{pid}/net/{proto}").read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            if len(parts) > 9 and parts[9] in inodes:
                out.append(f"{proto} {parts[1]}")
    return out


def _is_loopback(entry: str) -> bool:
    addr = entry.split()[1].split(":")[0]
    return addr in ("0100007F", "00000000000000000000000001000000")


def test_loopback_only(xproc):
    cfg, emu, v = xproc
    before = set(_inet_sockets_of(os.getpid()))   # other tests' sockets in this process are not ours
    v.connect()
    v.start()
    _ticks(v, 10, 0.1)
    mine = set(_inet_sockets_of(os.getpid())) - before
    theirs = set(_inet_sockets_of(emu.p.pid))
    for who, socks in (("host", mine), ("emulator", theirs)):
        bad = [e for e in socks if not _is_loopback(e)]
        assert bad == [], f"the {who} holds non-loopback sockets: {bad}"
    assert mine == set() and theirs == set()   # in fact no IP socket at all
    # the bus's sockets are AF_UNIX in the abstract namespace, named by the channel
    names = [ln.split()[-1] for ln in open("/proc/net/unix") if f"rig-can/{cfg.channel}/" in ln]
    assert len(names) >= 2 and all(n.startswith("@rig-can/") for n in names)


def test_a_host_silent_between_connect_and_start_still_starts(inproc):
    """A loaded host can be silent for longer than the valve's heartbeat consumer time between
    connect and the explicit start: the valve then leaves OPERATIONAL (heartbeat lost, latched),
    and start() (heartbeat first, NMT start again, fault reset) still brings it up enabled."""
    cfg, em, v = inproc
    v.connect()
    time.sleep(3 * cfg.heartbeat_timeout_s)  # no tick, no heartbeat: the consumer fires
    assert em.latched and em.nmt_state == "PRE-OPERATIONAL"  # the valve saw the host go silent
    v.start()
    st = v.read()
    assert st.operational and st.enabled and not st.reset_required
    assert _drive(v, 0.2, lambda: abs(em.spool - 0.2) < 1e-3)


def test_a_host_stall_inside_start_is_recovered_by_start(inproc):
    """The host stalls inside start() for longer than the consumer time (one write takes 2x the
    heartbeat timeout, as a descheduled process would): the valve leaves OPERATIONAL, and start()
    sends the NMT start again and finishes enabled within its time."""
    cfg, em, v = inproc
    v.connect()
    write, calls = v.send, []

    def stalling_write(*a, **kw):
        calls.append(1)
        if len(calls) == 3:
            time.sleep(2 * cfg.heartbeat_timeout_s)
        return write(*a, **kw)

    v.send = stalling_write
    v.start(timeout_s=5.0)
    v.send = write
    assert EMCY_HEARTBEAT in em.emcy_sent  # the stall was seen by the valve
    st = v.read()
    assert st.operational and st.enabled and not st.reset_required
    assert _drive(v, 0.2, lambda: abs(em.spool - 0.2) < 1e-3)
