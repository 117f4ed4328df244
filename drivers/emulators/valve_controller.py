"""Servovalve controller emulator: a ``canopen.LocalNode`` with ``drivers/eds/servovalve.eds``.

The protocol and the objects are documented in :mod:`drivers.valve`. Behaviour:

* boots (boot-up message) into PRE-OPERATIONAL and produces its heartbeat (0x1017);
  follows nothing until the host's NMT start; entering OPERATIONAL starts disabled.
* RPDO1 (set-point, control word, counter) is buffered and applied on the next SYNC
  (transmission type 1); each SYNC answers with TPDO1 (actual spool, status word,
  accepted counter, rejected frames).
* Nulls, disables and latches ``SW_RESET_REQUIRED`` (with an EMCY) on: an injected
  ``fault``; no set-point for 0x2003 ms while enabled (watchdog); the host's heartbeat
  (0x1016) lost, which also sends it back to PRE-OPERATIONAL; a protocol error (two
  set-points in one SYNC period, a set-point or SYNC counter out of sequence, a PDO of
  the wrong length). The latch clears only on the control word's fault-reset bit with
  the cause gone; then enable must go low and high again.
* Foreign or malformed frames are counted (0x2002) and never raise: a frame with one
  of the valve's own COB-IDs, a wrong-length NMT/SYNC/heartbeat, garbage datagrams.

API (what the emulated rig calls)::

    em = ValveControllerEmulator(cfg, on_sync=lambda spool: plant.step(spool))
    em.start()                    # bus, LocalNode, boot-up, heartbeat
    while ...: em.poll(0.001)     # process frames, run the heartbeat/watchdog timers
    em.inject("fault")            # or "ignore_setpoints", "stuck", "silent"; value None clears
    em.inject("spool_noise", 2.0) # not a fault: rms noise (set-point counts) on the reported spool
    em.spool, em.enabled, em.nmt_state, em.status_word, em.stats()
    em.stop()

``on_sync(spool)`` is called once per SYNC (lock step with the host's tick) with the
spool drive (fraction of full scale) after the set-point was applied. If it returns a
number, that is the spool position the valve reports (0x6301: the plant's spool, with
its lag and stiction band), else the drive is reported as it is. ``stuck`` and
``ignore_setpoints`` freeze the drive: the plant's spool settles and the reported
position loses the 500 Hz dither the host checks for (:mod:`drivers.valve`).

Fault injection from a second node (for the ``--hardware`` fault tests):
:func:`send_foreign` (``rpdo``, ``sync``, ``nmt``, ``status``, ``other_node``) and
:func:`send_malformed` (garbage datagrams and wrong-length frames).

Its own process: ``python -m drivers.emulators.valve_controller --channel C --node-id N``
prints one JSON line ``{"ready": ...}`` and reads commands from stdin: ``inject NAME
[VALUE]``, ``clear NAME``, ``stats`` (prints a JSON line), ``quit``. With
``--send-foreign KIND`` or ``--send-malformed`` it is instead a short-lived intruder
process that sends those frames on the channel and exits.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import threading
import time
from typing import Callable

import canopen

from drivers.valve import (
    CW_ENABLE, CW_FAULT_RESET, EDS_PATH, EMCY_DEVICE_HW, EMCY_HEARTBEAT, EMCY_PDO_LENGTH,
    EMCY_PROTOCOL, EMCY_RPDO_TIMEOUT, FULL_SCALE, NMT_COB, RPDO_FMT, SW_ENABLED, SW_FAULT,
    SW_HEARTBEAT_LOST, SW_NULL, SW_PROTOCOL, SW_RESET_REQUIRED, SW_WATCHDOG, SYNC_COB,
    SYNC_OVERFLOW, TPDO_FMT, CanopenValveConfig, open_bus,
)

FAULTS = ("fault", "ignore_setpoints", "stuck", "silent", "spool_noise")
# spool_noise (value: rms in set-point counts) is not a fault: white noise on the reported spool position,
# as a real valve's spool LVDT has (seeded), to show the host's following checks do not trip on it


class ValveControllerEmulator:
    def __init__(self, cfg: CanopenValveConfig, on_sync: Callable[[float], float | None] | None = None,
                 spool_tau_s: float = 0.0, eds=EDS_PATH, seed: int = 1):
        self.cfg = cfg
        self._rng = random.Random(seed)
        self.spool_measured = None  # what on_sync returned: the plant's spool position (None: the drive)
        self.on_sync = on_sync
        self.spool_tau_s = spool_tau_s
        self.eds = str(eds)
        self.faults: dict = {}
        self.bus = self.network = self.node = None
        self.spool = 0.0
        self.setpoint = 0.0
        self.enabled = False
        self.latched = 0          # SW_* causes that need a fault reset
        self._armed = False       # enable seen low since the last latch/reset/start
        self._pending: list[bytes] = []
        self._last_counter = None
        self._last_sync = None
        self._t_rpdo = math.inf
        self._t_host_hb = None
        self._t_last_sync = None
        self._state = 0
        self.rejected = 0
        self.n_sync = self.n_setpoints = self.n_tpdo = 0
        self.emcy_sent: list[int] = []
        self._lock = threading.Lock()

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        n = self.cfg.node_id
        self.bus = open_bus(self.cfg)
        self.network = canopen.Network(self.bus)
        self.node = canopen.LocalNode(n, canopen.import_od(self.eds, n))
        self.network.add_node(self.node)
        self.node.rpdo.read(from_od=True)
        self.node.tpdo.read(from_od=True)
        self._rpdo, self._tpdo = self.node.rpdo[1], self.node.tpdo[1]
        self.node.data_store.setdefault(0x1017, {})[0] = int(
            round(self.cfg.heartbeat_period_s * 1e3)).to_bytes(2, "little")
        self.node.add_write_callback(self._on_od_write)
        self._consumer_s = 0.0
        self._watchdog_s = self.cfg.watchdog_s
        self._accept = {NMT_COB: (2,), SYNC_COB: (0, 1), self._rpdo.cob_id: (RPDO_FMT.size,),
                        0x600 + n: (8,), 0x700 + self.cfg.host_node_id: (1,)}
        self._own = {self._tpdo.cob_id, 0x700 + n, 0x080 + n, 0x580 + n}
        self.node.nmt.send_command(0x81)   # INITIALISING: boot-up message
        self.node.nmt.send_command(0x80)   # PRE-OPERATIONAL: heartbeat producer starts
        self._state = self.node.nmt._state

    def stop(self) -> None:
        if self.node is not None:
            self.node.nmt.stop_heartbeat()
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def _on_od_write(self, index, subindex, od, data):
        if self._state == 5 and index in (0x1016, 0x1017, 0x2003) or 0x1400 <= index <= 0x1BFF:
            # no reconfiguring the safety timers or the PDOs while OPERATIONAL
            raise canopen.SdoAbortedError(0x08000022)
        if index == 0x1016 and subindex == 1:
            v = int.from_bytes(data, "little")
            self._consumer_s = (v & 0xFFFF) / 1e3 if (v >> 16) & 0x7F == self.cfg.host_node_id else 0.0
        elif index == 0x2003:
            self._watchdog_s = int.from_bytes(data, "little") / 1e3

    def inject(self, fault: str, value=True) -> None:
        if fault not in FAULTS:
            raise ValueError(f"valve emulator: unknown fault {fault!r} (one of {', '.join(FAULTS)})")
        with self._lock:
            if value is None or value is False:
                self.faults.pop(fault, None)
            else:
                self.faults[fault] = value
                if fault == "silent":
                    self.node.nmt.stop_heartbeat()
            if fault == "silent" and not value:
                self.node.nmt.start_heartbeat(int(round(self.cfg.heartbeat_period_s * 1e3)))

    # -- state --------------------------------------------------------------------------------
    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state if self.node is not None else "OFF"

    @property
    def status_word(self) -> int:
        sw = self.latched
        if self.enabled:
            sw |= SW_ENABLED
        if self.faults.get("fault"):
            sw |= SW_FAULT
        if self.latched:
            sw |= SW_RESET_REQUIRED
        if self.spool == 0.0:
            sw |= SW_NULL
        return sw

    def _latch(self, cause: int, emcy: int) -> None:
        first = not (self.latched & cause)
        self.latched |= cause
        self.enabled = False
        self._armed = False
        self.setpoint = 0.0
        self.spool = 0.0
        if first:
            self.emcy_sent.append(emcy)
            try:
                self.node.emcy.send(emcy, 0x01)
            except Exception:  # noqa: BLE001 - the host sees the status word anyway
                pass

    def _reject(self, protocol: bool = False, emcy: int = EMCY_PROTOCOL) -> None:
        self.rejected += 1
        if protocol and self._state == 5:
            self._latch(SW_PROTOCOL, emcy)

    # -- frames --------------------------------------------------------------------------------
    def poll(self, timeout: float = 0.0) -> int:
        """Process the frames that arrive within ``timeout`` s, then the timers; returns frames seen."""
        n = 0
        t = timeout
        while True:
            try:
                msg = self.bus.recv(t)
            except Exception:  # noqa: BLE001
                break
            t = 0.0
            if msg is None:
                break
            n += 1
            with self._lock:
                self._on_frame(msg)
        with self._lock:
            self._timers(time.monotonic())
        return n

    def _on_frame(self, msg) -> None:
        cid = msg.arbitration_id
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self._reject()
            return
        if cid in self._own:
            self._reject()  # someone sends with my COB-IDs
            return
        lens = self._accept.get(cid)
        if lens is None:
            return  # another node's traffic: not mine
        data = bytes(msg.data)
        if len(data) not in lens:
            self._reject(protocol=cid in (self._rpdo.cob_id, SYNC_COB), emcy=EMCY_PDO_LENGTH)
            return
        now = time.monotonic()
        if cid == 0x700 + self.cfg.host_node_id:
            self._t_host_hb = now
            return
        if cid == self._rpdo.cob_id:
            if self._state == 5:
                self._pending.append(data)
            return
        if cid == SYNC_COB:
            self._on_sync(data, now)
            return
        try:
            self.network.notify(cid, data, msg.timestamp)  # NMT, SDO: canopen's LocalNode
        except Exception:  # noqa: BLE001
            self._reject()
        self._nmt_transition(now)

    def _nmt_transition(self, now: float) -> None:
        new = self.node.nmt._state
        if new == self._state:
            return
        old, self._state = self._state, new
        if new == 0:  # reset node / communication: boot again (the latch survives)
            self.node.nmt.send_command(0x80)
            self._state = self.node.nmt._state
        if old == 5 or new == 5:  # entering or leaving OPERATIONAL: start disabled, nulled
            self.enabled = self._armed = False
            self.setpoint = self.spool = 0.0
            self._pending.clear()
            self._last_counter = self._last_sync = None
            self._t_rpdo = now

    def _on_sync(self, data: bytes, now: float) -> None:
        self.n_sync += 1
        if data:
            c = data[0]
            if self._last_sync is not None and c != self._last_sync % SYNC_OVERFLOW + 1:
                self._reject(protocol=True)
            self._last_sync = c
        if self._state != 5:
            return
        pending, self._pending = self._pending, []
        if len(pending) > 1:
            self._reject(protocol=True)  # a second set-point producer
        elif pending:
            sp, cw, counter = RPDO_FMT.unpack(pending[0])
            if self._last_counter is not None and counter != (self._last_counter + 1) & 0xFF:
                self._reject(protocol=True)
            self._last_counter = counter
            self._t_rpdo = now
            self.n_setpoints += 1
            self._control(cw)
            if not self.faults.get("ignore_setpoints"):  # the link works, the spool does not follow
                self.setpoint = sp / FULL_SCALE if self.enabled else 0.0
        self._move(now)
        if self.on_sync is not None:
            self.spool_measured = self.on_sync(self.spool)
        self._send_tpdo()

    def _control(self, cw: int) -> None:
        if cw & CW_FAULT_RESET and self.latched and not self.faults.get("fault") \
                and self._host_alive(time.monotonic()):
            self.latched = 0
            self._armed = False
            try:
                self.node.emcy.reset()
            except Exception:  # noqa: BLE001
                pass
        if not cw & CW_ENABLE:
            self._armed = not self.latched and not self.faults.get("fault")
            self.enabled = False
        elif self._armed and not self.latched and not self.faults.get("fault"):
            self.enabled = True

    def _move(self, now: float) -> None:
        if self.faults.get("fault"):
            self._latch(SW_FAULT, EMCY_DEVICE_HW)
        target = self.setpoint if self.enabled else 0.0
        if self.faults.get("stuck") or self.faults.get("ignore_setpoints"):
            return
        dt = now - self._t_last_sync if self._t_last_sync is not None else 0.0
        self._t_last_sync = now
        if self.spool_tau_s > 0 and self.enabled:
            self.spool += (target - self.spool) * (1.0 - math.exp(-dt / self.spool_tau_s))
        else:
            self.spool = target

    def _send_tpdo(self) -> None:
        if self.faults.get("silent"):
            return
        # 0x6301 is the spool position measured (the plant's spool when the plant models one: its lag and
        # stiction band show), else the drive; the valve's own null/enable logic uses the drive (self.spool)
        x = self.spool if self.spool_measured is None else self.spool_measured
        noise = self.faults.get("spool_noise")
        x_counts = x * FULL_SCALE + (self._rng.gauss(0.0, float(noise)) if noise else 0.0)
        data = TPDO_FMT.pack(int(round(max(-FULL_SCALE, min(FULL_SCALE, x_counts)))), self.status_word,
                             self._last_counter or 0, self.rejected & 0xFF)
        self._tpdo.data = bytearray(data)
        try:
            self._tpdo.transmit()
            self.n_tpdo += 1
        except Exception:  # noqa: BLE001 - a lost frame; the host sees the gap
            pass

    def _host_alive(self, now: float) -> bool:
        return self._t_host_hb is not None and (self._consumer_s <= 0 or now - self._t_host_hb <= self._consumer_s)

    def _timers(self, now: float) -> None:
        if self.node is None:
            return
        if self._t_host_hb is not None and self._consumer_s > 0 and now - self._t_host_hb > self._consumer_s:
            if not self.latched & SW_HEARTBEAT_LOST and self._state in (5, 127, 4):
                self._latch(SW_HEARTBEAT_LOST, EMCY_HEARTBEAT)
                if self._state == 5:
                    self.node.nmt.send_command(0x80)   # leave OPERATIONAL
                    self._nmt_transition(now)
        if self.enabled and now - self._t_rpdo > self._watchdog_s:
            self._latch(SW_WATCHDOG, EMCY_RPDO_TIMEOUT)

    def stats(self) -> dict:
        return {"nmt": self.nmt_state, "enabled": self.enabled, "spool": self.spool,
                "status_word": self.status_word, "latched": self.latched, "rejected": self.rejected,
                "n_sync": self.n_sync, "n_setpoints": self.n_setpoints, "n_tpdo": self.n_tpdo,
                "emcy_sent": list(self.emcy_sent), "faults": dict(self.faults),
                "bus_malformed": getattr(self.bus, "n_malformed", 0)}


# -- fault injection from outside: a second node on the same bus --------------------------------

FOREIGN_KINDS = ("rpdo", "sync", "nmt", "status", "other_node")


def send_foreign(channel: str, kind: str, node_id: int = 1, counter: int = 0, sync_count: int = 1) -> None:
    """Send, from a bus of its own on ``channel``, a frame only the master or the valve may send:
    ``rpdo`` (a full-scale set-point with counter ``counter``), ``sync`` (count ``sync_count``),
    ``nmt`` (start all nodes), ``status`` (two spoofed TPDOs), ``other_node`` (a TPDO of node
    ``node_id + 2``). Used by the fault-injection tests; the host must report it in ``health()``."""
    import can

    from drivers.canopen_bus import UnixCanBus

    frames = {
        "rpdo": [(0x200 + node_id, RPDO_FMT.pack(FULL_SCALE, CW_ENABLE, counter & 0xFF))],
        "sync": [(SYNC_COB, bytes([sync_count]))],
        "nmt": [(NMT_COB, b"\x01\x00")],
        "status": [(0x180 + node_id, TPDO_FMT.pack(0, SW_ENABLED, counter & 0xFF, 0))] * 2,
        "other_node": [(0x180 + node_id + 2, bytes(6))],
    }
    if kind not in frames:
        raise ValueError(f"foreign frame kind {kind!r} is not one of {', '.join(FOREIGN_KINDS)}")
    bus = UnixCanBus(channel=channel)
    try:
        for cid, data in frames[kind]:
            bus.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))
        bus.linger(0.05)
    finally:
        bus.shutdown()


def send_malformed(channel: str, node_id: int = 1, host_node_id: int = 127, seed: int = 1) -> None:
    """Send garbage datagrams and wrong-length CANopen frames to both sides of ``channel``."""
    import random

    import can

    from drivers.canopen_bus import UnixCanBus

    rnd = random.Random(seed)
    bus = UnixCanBus(channel=channel)
    try:
        for junk in (b"\xff" * 10, b"", b"\x00", bytes(rnd.getrandbits(8) for _ in range(64)), bytes(range(15)),
                     bytes.fromhex("000003020000") + b"\x09" + b"\x00" * 9):
            bus.send_raw(junk)
        for cid, data in ((NMT_COB, b"\x01"), (SYNC_COB, b"\x01\x02\x03"), (0x200 + node_id, b"\x00\x01"),
                          (0x600 + node_id, b"\x40"), (0x700 + host_node_id, b""),
                          (0x180 + node_id, b"\x01\x02\x03"), (0x080 + node_id, b"\x10"),
                          (0x700 + node_id, b"\x05\x05\x05")):
            bus.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))
        bus.linger(0.05)
    finally:
        bus.shutdown()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="CANopen servovalve controller emulator")
    p.add_argument("--channel", required=True)
    p.add_argument("--node-id", type=int, default=1)
    p.add_argument("--host-node-id", type=int, default=127)
    p.add_argument("--spool-tau-s", type=float, default=0.0)
    p.add_argument("--send-foreign", choices=FOREIGN_KINDS, help="send one foreign frame and exit")
    p.add_argument("--send-malformed", action="store_true", help="send malformed frames and exit")
    a = p.parse_args(argv)
    if a.send_foreign or a.send_malformed:
        if a.send_foreign:
            send_foreign(a.channel, a.send_foreign, a.node_id)
        if a.send_malformed:
            send_malformed(a.channel, a.node_id, a.host_node_id)
        return 0
    cfg = CanopenValveConfig(channel=a.channel, node_id=a.node_id, host_node_id=a.host_node_id)
    em = ValveControllerEmulator(cfg, spool_tau_s=a.spool_tau_s)
    em.start()
    cmds: list[str] = []
    done = threading.Event()

    def reader():
        for line in sys.stdin:
            cmds.append(line.strip())
        done.set()

    threading.Thread(target=reader, daemon=True).start()
    print(json.dumps({"ready": True, "slot": getattr(em.bus, "slot", None)}), flush=True)
    try:
        while not done.is_set():
            em.poll(0.002)
            while cmds:
                parts = cmds.pop(0).split()
                if not parts:
                    continue
                if parts[0] == "quit":
                    return 0
                if parts[0] == "inject":
                    em.inject(parts[1], True if len(parts) < 3 else json.loads(parts[2]))
                elif parts[0] == "clear":
                    em.inject(parts[1], None)
                elif parts[0] == "stats":
                    print(json.dumps(em.stats()), flush=True)
        return 0
    finally:
        em.stop()


if __name__ == "__main__":
    sys.exit(main())
