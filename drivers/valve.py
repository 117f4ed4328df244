"""Servovalve controller on CANopen (CiA 301 + a subset of the CiA 408 fluid-power profile).

The host is the bus's one NMT master and SYNC producer; the valve controller is node
``node_id`` with the object dictionary ``drivers/eds/servovalve.eds``. Everything goes
through the ``canopen`` package (Network, RemoteNode, PDO maps read from the EDS, NMT,
EMCY consumer, SDO, SYNC) over a python-can bus; the default bus is the machine-local
:class:`drivers.canopen_bus.UnixCanBus` (AF_UNIX only, nothing binds an IP address).

Objects used (the CiA 408 subset; ``n`` = node id, ``h`` = host id)
-------------------------------------------------------------------
The indexes follow CiA 408 (device control/status word, spool set-point/actual
value); the bits inside the control and status words are this project's simplified
assignment (``CW_*``, ``SW_*`` below), not the profile's full device state machine.

==============  =======================================================================
0x1000          device type 0x00000198 (profile 408), checked by SDO at connect
0x1016:01       consumer heartbeat time: ``h << 16 | ms`` (written by SDO at connect)
0x1017          producer heartbeat time, ms (written by SDO at connect)
0x2003          set-point watchdog time, ms (written by SDO at connect)
0x6040          device control word (bit0 enable, bit3 fault reset), RPDO1
0x6041          device status word, TPDO1 (``SW_*`` bits below)
0x6300:01       spool position set-point, int16 (+-16384 = +-100 %), RPDO1
0x6301:01       spool position actual value, int16, TPDO1
0x2000          set-point counter, u8, +1 every tick, RPDO1
0x2001          accepted set-point counter (echo of the counter applied), TPDO1
0x2002          rejected frame counter (foreign/malformed frames the valve saw), TPDO1
==============  =======================================================================

Frames: RPDO1 ``0x200+n`` (5 bytes: set-point, control word, counter, transmission
type 1 = applied at the next SYNC); SYNC ``0x080`` with a counter 1..240; TPDO1
``0x180+n`` (6 bytes, sent by the valve on every SYNC while OPERATIONAL); heartbeats
``0x700+n`` (valve) and ``0x700+h`` (host); EMCY ``0x080+n``.

The valve's rules (see :mod:`drivers.emulators.valve_controller`): it enters
OPERATIONAL only on the host's NMT start and then starts disabled; it follows only
while enabled (an enable *rising edge* of the control word); it nulls, disables and
latches ``SW_RESET_REQUIRED`` on a fault, on a set-point watchdog (no RPDO within
0x2003), on a lost host heartbeat (then also leaves OPERATIONAL) and on a protocol
error (a second set-point within one SYNC period, a counter out of sequence, a
wrong-length PDO); each of these sends an EMCY. Only the control word's fault-reset
bit clears the latch, then enable must go low and high again.

What the real-time loop calls (:class:`rig.hardware.loop.RtLoop`)
-------------------------------------------------------------------
``v = CanopenValve(cfg)`` is a :class:`drivers.device.Device`: ``v.connect()`` (bus, valve
heartbeat, SDO checks and configuration); ``v.start()`` (NMT start, fault reset, enable, verified by
TPDO; the explicit reset after a trip, never called again by the loop on its own); each tick
``v.read(now)``, then ``v.health(now)``: a :class:`DeviceHealth` whose ``problems`` (from
:meth:`CanopenValve.problems`: foreign/malformed frames, EMCY/fault, watchdog, lost heartbeat, not
OPERATIONAL/not enabled, stale TPDO, a spool that does not follow its command for
``follow_time_s``, a spool without the command's 500 Hz dither (:class:`DitherCheck`), non-finite
set-points) each trip the loop (:mod:`rig.hardware.interlocks`); then ``v.command``/``v.enable``
and ``v.write(now)`` (RPDO + SYNC, + host heartbeat when due; ``v.send(setpoint, enable, reset)``
underneath: setpoint in [-1, 1], saturated, NaN -> 0 and counted). On a trip or at the end
``v.safe_stop()`` nulls and disables and returns True only when a TPDO (or the valve leaving
OPERATIONAL) confirms it (``v.final_state()`` for the log); ``v.close()``. Frames are packed and
unpacked by the pure codec (:func:`encode_setpoint`, :func:`encode_sync`, :func:`decode_status`,
:class:`StatusFrame`'s bits), tested frame by frame without a bus. Nothing here blocks inside
``read``/``write``: frames are drained without waiting (on ``rig_unix`` its ``drain_frames()``,
elsewhere ``recv(0)``) and dispatched on the caller's thread (the status PDO here, the rest to
canopen); on ``rig_unix`` the set-point PDO and the SYNC go out as one message (``send_frames``).

``st.spool_actual`` vs ``st.spool_command_echoed`` is the valve's own following; ``st.enabled``,
``st.watchdog_tripped``, ``st.nulled``, ``st.fault``, ``st.reset_required``, ``st.emcy`` are the
valve's bits. In the emulated rig, the emulator's ``on_sync(spool)`` callback steps the plant
(lock step with SYNC); when no SYNC arrives (``em.n_sync`` unchanged after ``em.poll``) the plant
free-runs with ``em.spool`` (which the watchdog/heartbeat consumer null).

Limits: CAN has no sender address, so a foreign node is detected by what only the
master sends (NMT, SYNC, RPDO, the host heartbeat), by what only the valve sends
arriving too often (more TPDOs than SYNCs), by COB-IDs nobody should use, and by the
valve's counter checks; not prevented. The transport keeps all of it on one machine.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from drivers.canopen_bus import F_ERR, F_EXT, F_RTR
from drivers.config import CanopenValveConfig
from drivers.device import DeviceHealth, release_quietly
from drivers.errors import DeviceError

DEVICE = "servovalve controller"
EDS_PATH = Path(__file__).with_name("eds") / "servovalve.eds"
DEVICE_TYPE_408 = 0x00000198
FULL_SCALE = 16384  # CiA 408: 0x4000 = 100 %

# control word 0x6040
CW_ENABLE, CW_FAULT_RESET = 0x0001, 0x0008
# status word 0x6041
SW_ENABLED, SW_FAULT, SW_WATCHDOG, SW_NULL, SW_RESET_REQUIRED, SW_HEARTBEAT_LOST, SW_PROTOCOL = (
    0x0001, 0x0002, 0x0004, 0x0008, 0x0010, 0x0020, 0x0040)

# EMCY codes (CiA 301 / device specific)
EMCY_DEVICE_HW = 0x5000      # device hardware fault
EMCY_PROTOCOL = 0x8200       # protocol error: foreign set-point, counter out of sequence
EMCY_PDO_LENGTH = 0x8210     # PDO not processed due to length error
EMCY_HEARTBEAT = 0x8130      # life guard / heartbeat error
EMCY_RPDO_TIMEOUT = 0x8250   # RPDO timeout (set-point watchdog)

RPDO_FMT = struct.Struct("<hHB")   # set-point, control word, counter
TPDO_FMT = struct.Struct("<hHBB")  # actual, status word, accepted counter, rejected frames
SYNC_COB, NMT_COB = 0x080, 0x000
SYNC_OVERFLOW = 240
RECENT = 128  # ticks of set-points the host remembers to check the valve's counter echo (half of u8)


def open_bus(cfg: CanopenValveConfig):
    """The python-can bus of ``cfg`` (``rig_unix``: the machine-local bus)."""
    import can

    if cfg.interface == "rig_unix":
        from drivers.canopen_bus import UnixCanBus

        return UnixCanBus(channel=cfg.channel)
    kwargs = {"interface": cfg.interface, "channel": cfg.channel}
    if cfg.interface == "virtual":
        kwargs["receive_own_messages"] = False
    return can.Bus(**kwargs)


def to_counts(x: float) -> int:
    """Spool fraction [-1, 1] -> int16 counts (saturated)."""
    return int(round(max(-1.0, min(1.0, x)) * FULL_SCALE))


# -- the codec: frames <-> values, pure (no bus, no clock); tested frame by frame ---------------------

@dataclass(frozen=True, slots=True)
class StatusFrame:
    """One decoded TPDO1: the spool's actual position (fraction of full scale), the status word and its
    bits, the accepted set-point counter (0x2001) and the valve's rejected-frame counter (0x2002)."""

    spool_actual: float
    status_word: int
    accepted_counter: int
    rejected: int

    @property
    def enabled(self) -> bool:
        return bool(self.status_word & SW_ENABLED)

    @property
    def fault(self) -> bool:
        """A fault the valve latched: its own, a protocol error, a lost host heartbeat."""
        return bool(self.status_word & (SW_FAULT | SW_PROTOCOL | SW_HEARTBEAT_LOST))

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.status_word & SW_WATCHDOG)

    @property
    def nulled(self) -> bool:
        return bool(self.status_word & SW_NULL)

    @property
    def reset_required(self) -> bool:
        return bool(self.status_word & SW_RESET_REQUIRED)


def control_word(enable: bool, reset: bool = False) -> int:
    """Control word 0x6040: bit0 enable, bit3 fault reset."""
    return (CW_ENABLE if enable else 0) | (CW_FAULT_RESET if reset else 0)


def encode_setpoint(setpoint: float, enable: bool, reset: bool, counter: int) -> bytes:
    """RPDO1 (5 bytes): set-point in counts (saturated; nulled when not enabled), control word, counter."""
    cmd = max(-1.0, min(1.0, setpoint)) if enable else 0.0
    return RPDO_FMT.pack(to_counts(cmd), control_word(enable, reset), counter & 0xFF)


def encode_sync(count: int) -> bytes:
    """SYNC with its counter (1..240)."""
    return bytes((count,))


def next_sync_count(count: int) -> int:
    """The SYNC counter after ``count``: 1..SYNC_OVERFLOW, then 1 again."""
    return count % SYNC_OVERFLOW + 1


def decode_status(data: bytes) -> StatusFrame:
    """TPDO1 (6 bytes) -> :class:`StatusFrame`; ValueError for a frame of another length."""
    if len(data) != TPDO_FMT.size:
        raise ValueError(f"status PDO of {len(data)} bytes, not {TPDO_FMT.size}")
    actual, sw, acc, rej = TPDO_FMT.unpack(data)
    return StatusFrame(actual / FULL_SCALE, sw, acc, rej)


@dataclass
class ValveStatus:
    """What the valve last reported (TPDO1, heartbeat, EMCY) and what the host saw on the bus."""

    spool_actual: float = 0.0        # 0x6301:01, fraction of full scale
    spool_command: float = 0.0       # the set-point the host sent last
    spool_command_echoed: float = 0.0  # the set-point of the tick the valve reports (0x2001)
    status_word: int = 0
    enabled: bool = False
    fault: bool = False
    watchdog_tripped: bool = False
    nulled: bool = True
    reset_required: bool = False
    nmt_state: str = "UNKNOWN"       # from the valve's heartbeat
    accepted_counter: int = -1       # 0x2001 echo
    valve_rejected: int = 0          # 0x2002: frames the valve rejected (total, unwrapped)
    emcy: list = field(default_factory=list)   # active EMCYs: (code, register)
    foreign_frames: int = 0          # frames only the master may send, or from nobody expected
    malformed_frames: int = 0        # wrong length / undecodable CANopen frames, host side
    bus_malformed: int = 0           # datagrams the transport could not decode at all
    counter_errors: int = 0          # TPDO echo not a counter the host sent recently
    n_tpdo: int = 0
    tpdo_age_s: float = math.inf
    heartbeat_age_s: float = math.inf

    @property
    def operational(self) -> bool:
        return self.nmt_state == "OPERATIONAL"


class DitherCheck:
    """Does the spool follow the controller's 500 Hz dither? (The physical check that the valve
    follows its set-points at all, whatever their level.)

    Per status PDO the pair (command of the tick it echoes, spool position reported), in set-point
    counts, and the sign s = ±1 of that tick (counter parity: the 500 Hz dither at 1 kHz is
    cos(pi n), one sign per tick). Over the last ``window`` pairs, the Nyquist amplitude of each,
    with the window's mean removed (so a constant level, a drifting command or an unequal number
    of signs adds nothing):  A_x = |sum s_i (x_i - mean x)| / n.  The check judges only when the
    command's A_c >= ``min_command_counts`` and fails when A_spool < ``min_gain`` * A_c. A
    lag of whole ticks only flips the sign (absolute values); a first-order spool of time constant
    tau keeps (1 - e^(-T/tau)) / (1 + e^(-T/tau)) of it; white position noise of rms sigma adds
    about sigma / sqrt(n). Integer sums, O(1) per PDO."""

    __slots__ = ("window", "min_command", "min_gain", "_ring", "_i", "n", "_ss", "_sx", "_sc", "_x", "_c",
                 "failed", "gain", "spool_amp", "command_amp", "min_gain_seen")

    def __init__(self, window: int, min_command_counts: float, min_gain: float):
        self.window, self.min_command, self.min_gain = int(window), float(min_command_counts), float(min_gain)
        self._ring: list = [None] * self.window
        self.failed = False
        self.min_gain_seen = math.inf   # the lowest gain judged this run (healthy margin, for the log)
        self.n = 1
        self.clear()

    def clear(self) -> None:
        """Forget the window (disabled, a counter the host did not send): judge afresh."""
        if self.n == 0:
            return
        self._ring[:] = [None] * self.window
        self._i = self.n = 0
        self._ss = self._sx = self._sc = self._x = self._c = 0
        self.gain = math.nan
        self.spool_amp = self.command_amp = 0.0

    def add(self, counter: int, command_counts: int, spool_counts: int) -> None:
        s = 1 if counter & 1 else -1
        old = self._ring[self._i]
        if old is not None:
            os_, oc, ox = old
            self._ss -= os_
            self._sc -= os_ * oc
            self._sx -= os_ * ox
            self._c -= oc
            self._x -= ox
        else:
            self.n += 1
        self._ring[self._i] = (s, command_counts, spool_counts)
        self._i = (self._i + 1) % self.window
        self._ss += s
        self._sc += s * command_counts
        self._sx += s * spool_counts
        self._c += command_counts
        self._x += spool_counts
        if self.n < self.window:
            return
        n = self.n
        a_c = abs(self._sc - self._c * self._ss / n) / n
        if a_c < self.min_command:
            return
        a_x = abs(self._sx - self._x * self._ss / n) / n
        self.command_amp, self.spool_amp, self.gain = a_c, a_x, a_x / a_c
        if self.gain < self.min_gain_seen:
            self.min_gain_seen = self.gain
        if self.gain < self.min_gain:
            self.failed = True


class CanopenValve:
    """Host side (NMT master, SYNC producer) of the CANopen servovalve controller, a
    :class:`drivers.device.Device` (``name`` "valve"): set ``command`` (spool fraction in [-1, 1]) and
    ``enable`` before ``write(now)``; with ``enable`` false the set-point goes out nulled with the
    enable bit cleared. ``start()`` (NMT start, fault reset, enable, verified by the valve's status) is
    the explicit operator action the loop calls once, before the first tick, never after a trip;
    ``safe_stop()`` nulls and disables and says whether the valve confirmed it."""

    name = "valve"

    def __init__(self, cfg: CanopenValveConfig, eds: str | Path = EDS_PATH):
        self.cfg = cfg
        self.eds = str(eds)
        self.address = cfg.address_text
        self.command = 0.0
        self.enable = False
        self._health = DeviceHealth(DEVICE, self.address)
        self.bus = None
        self.network = None
        self.node = None
        self._st = ValveStatus()
        self._counter = 0
        self._sync_count = 0
        self._n_sync = 0
        self._recent: dict[int, float] = {}   # counter -> command, last RECENT ticks
        self._next_hb = 0.0
        self._t_tpdo = -math.inf
        self._t_hb = -math.inf
        self._t_follow_bad = None
        self.dither = DitherCheck(cfg.dither_window_ticks, cfg.dither_min_command * FULL_SCALE,
                                   cfg.dither_min_gain)
        self._cw = 0
        self._rej_last: int | None = None  # the valve's 0x2002 at this host's first TPDO: the baseline
        self._sdo_open = False
        self._pump_lock = threading.Lock()
        self.nan_setpoints = 0
        self.send_errors = 0
        self.foreign_ids: dict[int, int] = {}

    # -- setup -----------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the bus, find the valve's heartbeat, check and configure it by SDO (pre-operational)."""
        import can
        import canopen

        try:
            self.bus = open_bus(self.cfg)
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(DEVICE, self.address, f"cannot open CAN bus: {exc}") from exc
        self.network = canopen.Network(self.bus)
        self.node = canopen.RemoteNode(self.cfg.node_id, self.eds)
        self.network.add_node(self.node)
        n = self.cfg.node_id
        self.node.tpdo.read(from_od=True)
        self.node.rpdo.read(from_od=True)
        self._tpdo, self._rpdo = self.node.tpdo[1], self.node.rpdo[1]
        self._check_layout()
        self._tpdo.add_callback(self._on_tpdo)
        # the per-tick frames, built once from canopen's maps (COB-IDs, sizes) and reused
        self._rpdo_cob = self._rpdo.cob_id
        self._rpdo_msg = can.Message(arbitration_id=self._rpdo.cob_id, data=bytearray(RPDO_FMT.size),
                                     is_extended_id=False)
        self._sync_msg = can.Message(arbitration_id=self.network.sync.cob_id, data=bytearray(1),
                                     is_extended_id=False)
        self._expected = {self._tpdo.cob_id: TPDO_FMT.size, 0x700 + n: 1, 0x080 + n: 8, 0x580 + n: 8}
        self._tpdo_cob, self._hb_cob, self._sdo_tx = self._tpdo.cob_id, 0x700 + n, 0x580 + n
        self._sync_cob = self.network.sync.cob_id
        self._send_frames = getattr(self.bus, "send_frames", None)  # RPDO + SYNC in one message
        self._master_ids = {NMT_COB, SYNC_COB, self._rpdo.cob_id, 0x600 + n, 0x700 + self.cfg.host_node_id}
        stop = threading.Event()
        pump = threading.Thread(target=self._pump_until, args=(stop,), daemon=True, name="canopen-connect")
        pump.start()
        try:
            t_end = time.monotonic() + self.cfg.connect_timeout_s
            while self._t_hb == -math.inf:
                if time.monotonic() > t_end:
                    raise DeviceError(DEVICE, self.address,
                                      f"no heartbeat from node {n} within {self.cfg.connect_timeout_s:g} s")
                time.sleep(0.002)
            self._sdo_open = True
            self.node.nmt.state = "PRE-OPERATIONAL"
            sdo = self.node.sdo
            dtype = sdo[0x1000].raw
            if dtype != DEVICE_TYPE_408:
                raise DeviceError(DEVICE, self.address, f"device type 0x{dtype:08x} is not a CiA 408 valve")
            hb_ms = max(1, round(self.cfg.heartbeat_period_s * 1e3))
            sdo[0x1016][1].raw = (self.cfg.host_node_id << 16) | max(1, round(self.cfg.heartbeat_timeout_s * 1e3))
            sdo[0x1017].raw = hb_ms
            sdo[0x2003].raw = max(1, round(self.cfg.watchdog_s * 1e3))
        except DeviceError:
            raise
        except Exception as exc:  # noqa: BLE001 - SDO timeout/abort
            raise DeviceError(DEVICE, self.address, f"configuration by SDO failed: {exc}") from exc
        finally:
            self._sdo_open = False
            stop.set()
            pump.join(1.0)

    def _check_layout(self) -> None:
        """The PDO layouts the EDS defines must be the ones this driver packs."""
        want_r = [(0x6300, 1, 16), (0x6040, 0, 16), (0x2000, 0, 8)]
        want_t = [(0x6301, 1, 16), (0x6041, 0, 16), (0x2001, 0, 8), (0x2002, 0, 8)]
        got_r = [(v.index, v.subindex, v.length) for v in self._rpdo.map]
        got_t = [(v.index, v.subindex, v.length) for v in self._tpdo.map]
        if got_r != want_r or got_t != want_t:
            raise DeviceError(DEVICE, self.address, f"EDS {self.eds}: PDO mapping {got_r} / {got_t} "
                                                    f"is not {want_r} / {want_t}")

    def _pump_until(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._heartbeat_if_due(time.monotonic())
            self._pump(0.002)

    def start(self, timeout_s: float | None = None) -> None:
        """NMT start, fault reset, enable; returns once a TPDO shows the valve enabled.

        The host's heartbeat goes out first: between connect and start the host may have been
        silent for longer than the valve's consumer time (a loaded machine), and a valve that then
        left OPERATIONAL gets the NMT start again while this explicit start sequence lasts (at
        most every 50 ms); it never does so outside it."""
        timeout_s = self.cfg.start_timeout_s if timeout_s is None else timeout_s
        self._next_hb = 0.0
        self._heartbeat_if_due(time.monotonic())
        self.node.nmt.state = "OPERATIONAL"
        t_nmt = time.monotonic()
        t_end = t_nmt + timeout_s
        phase = 0
        n0 = self.read().n_tpdo
        while True:
            st = self.read()
            if not st.operational and time.monotonic() - t_nmt >= 0.05:
                self.node.nmt.state = "OPERATIONAL"  # left it (heartbeat lost): again, from phase 0
                t_nmt = time.monotonic()
                phase = 0
            # phase 0: enable low (+ fault reset) until 3 fresh TPDOs show OPERATIONAL, no latch
            if phase == 0 and st.operational and st.n_tpdo >= n0 + 3 and not st.reset_required \
                    and not st.enabled:
                phase = 1
            if phase == 1 and st.enabled:
                return
            if time.monotonic() > t_end:
                raise DeviceError(DEVICE, self.address,
                                  f"did not enable within {timeout_s:g} s (NMT {st.nmt_state}, status word "
                                  f"0x{st.status_word:04x}, EMCY {st.emcy})")
            if phase == 0:
                self.send(0.0, enable=False, reset=st.reset_required or st.n_tpdo < n0 + 3)
            else:
                self.send(0.0, enable=True)
            time.sleep(0.001)

    # -- the Device protocol (drivers.device): what the real-time loop calls ---------------------
    def write(self, now: float | None = None) -> None:
        """This tick's ``command`` (spool fraction) as set-point, or a nulled, disabled set-point when
        ``enable`` is false."""
        if self.enable:
            self.send(self.command)
        else:
            self.send(0.0, enable=False)

    def health(self, now: float | None = None) -> DeviceHealth:
        """The valve's :class:`DeviceHealth` (after :meth:`read`); ``problems`` each trip the loop."""
        st, h = self._st, self._health
        h.frames_ok = st.n_tpdo or (1 if st.heartbeat_age_s < math.inf else 0)  # heartbeats before start
        h.frames_bad = st.malformed_frames + st.bus_malformed + st.foreign_frames
        h.errors = self.send_errors
        h.age_s = st.heartbeat_age_s
        h.status, h.fault_code = st.status_word, st.emcy[0][0] if st.emcy else 0
        h.fault = st.fault
        h.problems = self.problems()
        return h

    @property
    def status(self) -> ValveStatus:
        """What the valve last reported (after :meth:`read`)."""
        return self._st

    @property
    def enabled(self) -> bool:
        """The controller reports itself enabled (last status PDO)."""
        return self._st.enabled

    @property
    def dither_gain_min(self) -> float | None:
        """The lowest spool/command 500 Hz gain the dither check judged this run (None: never judged)."""
        g = self.dither.min_gain_seen
        return round(g, 4) if g != math.inf else None

    def final_state(self) -> dict:
        """The valve's state for the log. A valve that left OPERATIONAL (its heartbeat says so) is nulled
        and disabled by its own rules and sends no status PDO any more: its last PDO (from before, e.g. a
        stall) is not what it is now, so the state is the heartbeat's (``source``)."""
        st = self._st
        fresh_hb = st.heartbeat_age_s < self.cfg.heartbeat_timeout_s
        if fresh_hb and not st.operational and st.nmt_state != "UNKNOWN":
            return {"status_bits": st.status_word, "enabled": False, "output": 0.0, "nmt": st.nmt_state,
                    "nulled": True, "source": f"heartbeat: {st.nmt_state} (no PDO moves the valve)"}
        return {"status_bits": st.status_word, "enabled": st.enabled, "output": st.spool_actual,
                "nmt": st.nmt_state, "nulled": st.nulled, "source": "status PDO"}

    # -- per tick ----------------------------------------------------------------------------
    def send(self, setpoint: float, enable: bool = True, reset: bool = False) -> None:
        """This tick's set-point (fraction of full spool, saturated) as RPDO1, then SYNC."""
        if self.bus is None:
            raise DeviceError(DEVICE, self.address, "CAN bus not open")
        if not math.isfinite(setpoint):
            self.nan_setpoints += 1
            setpoint, enable = 0.0, False
        self._counter = (self._counter + 1) & 0xFF
        self._cw = control_word(enable, reset)
        cmd = max(-1.0, min(1.0, setpoint)) if enable else 0.0
        self._recent[self._counter] = cmd
        self._recent.pop((self._counter - RECENT) & 0xFF, None)
        self._st.spool_command = cmd
        self._sync_count = next_sync_count(self._sync_count)
        rpdo = encode_setpoint(cmd, enable, reset, self._counter)
        try:
            with self.network.send_lock:
                if self._send_frames is not None:  # one socket operation, split back into frames
                    self._send_frames(((self._rpdo_cob, rpdo), (self._sync_cob, encode_sync(self._sync_count))))
                else:
                    rp, sy = self._rpdo_msg, self._sync_msg
                    rp.data[:] = rpdo
                    sy.data[0] = self._sync_count
                    self.bus.send(rp)
                    self.bus.send(sy)
            self._n_sync += 1
            self._heartbeat_if_due(time.monotonic())
        except Exception as exc:  # noqa: BLE001 - can.CanError, OSError
            self.send_errors += 1
            raise DeviceError(DEVICE, self.address, f"CAN send failed: {exc}", kind="bus") from exc

    def _heartbeat_if_due(self, now: float) -> None:
        if now >= self._next_hb:
            self._next_hb = now + self.cfg.heartbeat_period_s
            self.network.send_message(0x700 + self.cfg.host_node_id, b"\x05")

    def read(self, now: float | None = None) -> ValveStatus:
        """Drain the received frames (non-blocking) and return the valve's status."""
        if self.bus is None:
            raise DeviceError(DEVICE, self.address, "CAN bus not open")
        self._pump(0.0)
        st = self._st
        now = time.monotonic()
        st.tpdo_age_s = now - self._t_tpdo
        st.heartbeat_age_s = now - self._t_hb
        st.emcy = [(e.code, e.register) for e in self.node.emcy.active]
        st.bus_malformed = getattr(self.bus, "n_malformed", 0)
        return st

    def _pump(self, timeout: float) -> None:
        """Dispatch what arrived; wait up to ``timeout`` for the first frame. On the machine-local bus
        the frames are drained straight from its sockets (no ``can.Message``, no per-call filter and
        timeout logic of python-can's ``recv``: the per-tick path)."""
        bus = self.bus
        drain = getattr(bus, "drain_frames", None)
        with self._pump_lock:
            try:
                if drain is not None:
                    if timeout > 0.0:
                        msg = bus.recv(timeout)
                        if msg is not None:
                            self._on_message(msg)
                    for cid, flags, data in drain():
                        self._on_frame(cid, flags, data)
                    return
                first = True
                while True:
                    msg = bus.recv(timeout if first else 0.0)
                    first = False
                    if msg is None:
                        return
                    self._on_message(msg)
            except DeviceError:
                raise
            except Exception as exc:  # noqa: BLE001
                raise DeviceError(DEVICE, self.address, f"CAN receive failed: {exc}", kind="bus") from exc

    def _on_message(self, msg) -> None:
        flags = (F_EXT if msg.is_extended_id else 0) | (F_RTR if msg.is_remote_frame else 0) \
            | (F_ERR if msg.is_error_frame else 0)
        self._on_frame(msg.arbitration_id, flags, bytes(msg.data))

    def _on_frame(self, cid: int, flags: int, data: bytes) -> None:
        """One received frame (``flags``: the transport's F_EXT / F_RTR / F_ERR bits)."""
        st = self._st
        if flags & F_ERR:
            st.malformed_frames += 1
            return
        if flags or cid in self._master_ids or (cid == self._sdo_tx and not self._sdo_open):
            self._foreign(cid)
            return
        if cid == self._tpdo_cob:
            if len(data) != TPDO_FMT.size:
                st.malformed_frames += 1
                return
            if st.n_tpdo >= self._n_sync:  # more status frames than SYNCs: someone else sends them
                self._foreign(cid)
                return
            self._t_tpdo = time.monotonic()
            # the per-tick status: unpacked here with the layout checked against the EDS at connect
            # (canopen's generic PDO dispatch costs ~20 µs a tick); canopen handles everything else
            self._on_tpdo_data(data)
            return
        want = self._expected.get(cid)
        if want is None:
            self._foreign(cid)
            return
        if len(data) != want and cid != self._sdo_tx:
            st.malformed_frames += 1
            return
        if cid == self._hb_cob:
            self._t_hb = time.monotonic()
        try:
            self.network.notify(cid, data, time.time())
        except Exception:  # noqa: BLE001 - canopen could not decode it
            st.malformed_frames += 1
        if cid == self._hb_cob:
            st.nmt_state = self.node.nmt.state

    def _foreign(self, cid: int) -> None:
        self._st.foreign_frames += 1
        self.foreign_ids[cid] = self.foreign_ids.get(cid, 0) + 1

    def _on_tpdo(self, pdo_map) -> None:
        self._on_tpdo_data(bytes(pdo_map.data))

    def _on_tpdo_data(self, data: bytes) -> None:
        st = self._st
        fr = decode_status(data)
        actual, rej, acc = int(round(fr.spool_actual * FULL_SCALE)), fr.rejected, fr.accepted_counter
        st.n_tpdo += 1
        st.spool_actual = fr.spool_actual
        st.status_word = fr.status_word
        st.enabled = fr.enabled
        st.fault = fr.fault
        st.watchdog_tripped = fr.watchdog_tripped
        st.nulled = fr.nulled
        st.reset_required = fr.reset_required
        if self._rej_last is None:
            self._rej_last = rej  # what the valve rejected before this host connected is not this run's
        st.valve_rejected += (rej - self._rej_last) & 0xFF  # 0x2002 is a wrapping u8: keep the total
        self._rej_last = rej
        st.accepted_counter = acc
        cmd = self._recent.get(acc)
        if cmd is None:
            if st.enabled:
                st.counter_errors += 1
            cmd = 0.0
            self.dither.clear()
        elif st.enabled:
            self.dither.add(acc, to_counts(cmd), actual)
        else:
            self.dither.clear()
        now = time.monotonic()
        st.spool_command_echoed = cmd
        if st.enabled and abs(cmd - st.spool_actual) > self.cfg.follow_max:
            if self._t_follow_bad is None:
                self._t_follow_bad = now
        else:
            self._t_follow_bad = None

    # -- health and shutdown -------------------------------------------------------------------
    def problems(self) -> list[tuple[str, str]]:
        """Problems that must trip the loop, each ``(trip name, message naming the valve)``; empty:
        healthy. Call after :meth:`read` (it uses that status). The names: ``can_foreign_frames``,
        ``can_malformed_frames``, ``valve_rejected_frames``, ``valve_counter``, ``valve_fault``,
        ``valve_watchdog``, ``valve_heartbeat``, ``valve_nmt_state``, ``valve_status_stale``,
        ``valve_disabled``, ``valve_following``, ``valve_dither``, ``non_finite_setpoint``."""
        st, c, a = self._st, self.cfg, self.address
        out = []
        if st.foreign_frames:
            ids = ", ".join(f"0x{i:03x}" for i in sorted(self.foreign_ids))
            out.append(("can_foreign_frames", f"{st.foreign_frames} foreign CAN frames (COB-ID {ids}) on the bus "
                        f"of {a}: another master or node is sending"))
        if st.malformed_frames or st.bus_malformed:
            out.append(("can_malformed_frames", f"{st.malformed_frames + st.bus_malformed} malformed CAN frames "
                        f"on {a}"))
        if st.valve_rejected:
            out.append(("valve_rejected_frames", f"{a} rejected {st.valve_rejected} frames (foreign or malformed)"))
        if st.counter_errors:
            out.append(("valve_counter", f"{a} applied {st.counter_errors} set-points the host did not send"))
        if st.fault or st.emcy:
            out.append(("valve_fault", f"{a} reports a fault (status word 0x{st.status_word:04x}, EMCY "
                        f"{', '.join(f'0x{e[0]:04x}' for e in st.emcy) or 'none'})"))
        if st.watchdog_tripped:
            out.append(("valve_watchdog", f"{a} nulled on its set-point watchdog"))
        if st.heartbeat_age_s > c.heartbeat_timeout_s:
            out.append(("valve_heartbeat", f"no heartbeat from {a} for {st.heartbeat_age_s * 1e3:.0f} ms"))
        elif not st.operational:
            out.append(("valve_nmt_state", f"{a} is {st.nmt_state}, not OPERATIONAL"))
        if self._n_sync and st.tpdo_age_s > c.tpdo_timeout_s:
            out.append(("valve_status_stale", f"no status PDO from {a} for {st.tpdo_age_s * 1e3:.0f} ms"))
        if self._n_sync and st.n_tpdo and not st.enabled:
            out.append(("valve_disabled", f"{a} is not enabled"))
        if self._t_follow_bad is not None and time.monotonic() - self._t_follow_bad > c.follow_time_s:
            out.append(("valve_following", f"{a} does not follow: spool {st.spool_actual:+.3f} vs command "
                        f"{st.spool_command_echoed:+.3f} for over {c.follow_time_s * 1e3:.0f} ms"))
        d = self.dither
        if d.failed:
            out.append(("valve_dither", f"{a} does not follow its set-points: the spool's 500 Hz dither is "
                        f"{d.spool_amp:.2f} counts vs the command's {d.command_amp:.1f} (gain {d.gain:.3f} < "
                        f"{c.dither_min_gain:g}) over the last {d.n} status PDOs"))
        if self.nan_setpoints:
            out.append(("non_finite_setpoint", f"{self.nan_setpoints} non-finite set-points for {a} "
                        "(sent as null)"))
        return out

    def safe_stop(self, timeout_s: float = 0.1) -> bool:
        """Null and disable; True once the valve confirms (TPDO disabled and nulled, or it left
        OPERATIONAL, which nulls it). Then NMT pre-operational: no PDO moves it any more."""
        if self.bus is None:
            return False
        ok = False
        t_end = time.monotonic() + timeout_s
        n0 = self._st.n_tpdo
        try:
            while time.monotonic() < t_end:
                self.send(0.0, enable=False)
                time.sleep(0.001)
                st = self.read()
                if st.n_tpdo > n0 and not st.enabled and st.nulled:
                    ok = True
                    break
                if st.heartbeat_age_s < self.cfg.heartbeat_timeout_s and not st.operational:
                    ok = True
                    break
            self.node.nmt.state = "PRE-OPERATIONAL"
        except DeviceError:
            return False
        return ok

    def close(self) -> None:
        if self.bus is not None:
            release_quietly(self.bus.shutdown)
            self.bus = None


__all__ = ["CanopenValve", "CanopenValveConfig", "StatusFrame", "ValveStatus", "decode_status", "encode_setpoint",
           "encode_sync", "open_bus", "EDS_PATH", "to_counts"]
