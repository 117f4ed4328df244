"""A machine-local CAN bus for python-can: Unix seqpacket sockets in the abstract namespace.

Why: python-can's ``udp_multicast`` binds 0.0.0.0 and joins the multicast group on
the default interface (eth0, TTL 1), so the valve's frames reached the LAN and anyone
on it could move the actuator. ``virtual`` only works inside one process and
``socketcan`` (vcan) needs root. This bus uses ``AF_UNIX`` sockets only: the kernel
never routes them off the machine, nothing binds an IP address, and no file is left
behind (Linux abstract namespace; the name vanishes with the last process).

Semantics: a broadcast bus like CAN. Every bus object on the same ``channel`` listens
on one of ``SLOTS`` addresses ``\\0rig-can/<channel>/<slot>`` and connects to the
nodes already there (a full mesh of ``SOCK_SEQPACKET`` connections: message
boundaries kept, ~270 queued frames per peer, where datagram sockets would queue only
``net.unix.max_dgram_qlen`` = 10). Each frame goes to every peer; a bus does not
receive its own frames (``receive_own_messages``
is not supported). Different channels never see each other: give each rig its own
channel name (e.g. its run directory).

Message layout (little-endian), one CAN frame each::

    u8 kind (0 = frame)  u8 flags (bit0 extended id, bit1 remote,
    bit2 error frame)  u32 arbitration id  u8 dlc  dlc bytes of data (0..8)

Anything else (wrong length, dlc > 8, id out of range, unknown kind) is dropped and
counted in :attr:`UnixCanBus.n_malformed`; it never raises.

Use: ``UnixCanBus(channel="rig-A")`` or, through python-can's plugin entry point,
``can.Bus(interface="rig_unix", channel="rig-A")``.
"""

from __future__ import annotations

import errno
import select
import socket
import struct
import threading
import time

import can

SLOTS = 16
_HDR = struct.Struct("<BBIB")
KIND_FRAME = 0
F_EXT, F_RTR, F_ERR = 0x01, 0x02, 0x04


def slot_address(channel: str, slot: int) -> bytes:
    """The abstract-namespace address of ``slot`` on ``channel``."""
    return b"\0rig-can/" + channel.encode() + b"/" + str(slot).encode()


def encode_frame(msg: can.Message) -> bytes:
    flags = (F_EXT if msg.is_extended_id else 0) | (F_RTR if msg.is_remote_frame else 0) \
        | (F_ERR if msg.is_error_frame else 0)
    data = bytes(msg.data or b"")
    return _HDR.pack(KIND_FRAME, flags, msg.arbitration_id, len(data)) + data


def decode_frame(buf: bytes) -> can.Message | None:
    """A received datagram as a frame, or None when it is not a valid one."""
    if len(buf) < _HDR.size:
        return None
    kind, flags, arb, dlc = _HDR.unpack_from(buf)
    if kind != KIND_FRAME or dlc > 8 or len(buf) != _HDR.size + dlc or flags & ~0x07:
        return None
    ext = bool(flags & F_EXT)
    if arb > (0x1FFFFFFF if ext else 0x7FF):
        return None
    return can.Message(arbitration_id=arb, is_extended_id=ext, is_remote_frame=bool(flags & F_RTR),
                       is_error_frame=bool(flags & F_ERR), dlc=dlc, data=buf[_HDR.size:],
                       timestamp=time.time(), check=False)


def _peer_closed(sock: socket.socket) -> bool:
    """After a zero-length read: EOF (the peer hung up) or an empty seqpacket message?"""
    p = select.poll()
    p.register(sock, select.POLLIN | select.POLLHUP | getattr(select, "POLLRDHUP", 0x2000))
    return any(ev & (select.POLLHUP | getattr(select, "POLLRDHUP", 0x2000)) for _, ev in p.poll(0))


class UnixCanBus(can.BusABC):
    """python-can bus over abstract Unix seqpacket sockets (one machine, one channel)."""

    def __init__(self, channel: str = "rig", can_filters=None, slots: int = SLOTS, **kwargs):
        if not channel or "/" in str(channel) or "\0" in str(channel):
            raise can.CanInitializationError(f"rig_unix channel name {channel!r} is empty or has '/'")
        self.channel = str(channel)
        self.channel_info = f"rig_unix:{self.channel}"
        self.n_malformed = 0
        self.n_tx_dropped = 0
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._gone: set[socket.socket] = set()
        self._listener = None
        self._next_accept = 0.0
        lst = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.slot = -1
        for s in range(slots):
            try:
                lst.bind(slot_address(self.channel, s))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    continue
                lst.close()
                raise can.CanInitializationError(f"rig_unix:{self.channel}: {exc}") from exc
            self.slot = s
            break
        if self.slot < 0:
            lst.close()
            raise can.CanInitializationError(f"rig_unix:{self.channel}: all {slots} slots in use")
        lst.listen(slots)
        lst.setblocking(False)
        self._listener = lst
        for s in range(slots):  # join the mesh: connect to every node already on the channel
            if s == self.slot:
                continue
            c = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                c.connect(slot_address(self.channel, s))
            except OSError:
                c.close()
                continue
            c.setblocking(False)
            self._conns.append(c)
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    # -- the mesh ------------------------------------------------------------------------
    def _accept(self) -> None:
        lst = self._listener
        while lst is not None:
            try:
                c, _ = lst.accept()
            except (BlockingIOError, OSError):
                return
            c.setblocking(False)
            with self._lock:
                self._conns.append(c)

    def _drop(self, c: socket.socket) -> None:
        with self._lock:
            if c in self._conns:
                self._conns.remove(c)
            self._gone.discard(c)
        c.close()

    @property
    def n_peers(self) -> int:
        self._accept()
        return len(self._conns)

    # -- python-can ----------------------------------------------------------------------
    def _send_datagram(self, data: bytes) -> None:
        if self._listener is None:
            raise can.CanOperationError(f"rig_unix:{self.channel}: bus is shut down")
        now = time.monotonic()
        if now >= self._next_accept:  # new peers: also accepted on every recv
            self._next_accept = now + 0.005
            self._accept()
        for c in tuple(self._conns):
            if c in self._gone:
                continue
            try:
                c.send(data)
            except BlockingIOError:
                self.n_tx_dropped += 1  # that peer's queue is full: a lost frame, as on a busy bus
            except OSError:
                # the peer left; what it sent may still be queued: recv reads it, then drops c
                self._gone.add(c)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._send_datagram(encode_frame(msg))

    def send_raw(self, datagram: bytes) -> None:
        """Send arbitrary bytes to every peer (fault injection: malformed frames)."""
        self._send_datagram(bytes(datagram))

    def _recv_internal(self, timeout: float | None):
        if self._listener is None:
            raise can.CanOperationError(f"rig_unix:{self.channel}: bus is shut down")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            for c in tuple(self._conns):
                while True:  # this peer's queue, until a valid frame or empty
                    try:
                        buf = c.recv(256)
                    except BlockingIOError:
                        break
                    except ConnectionResetError:
                        continue  # the peer left with unread frames; what it sent is still queued
                    except OSError:
                        self._drop(c)
                        break
                    if not buf:
                        if _peer_closed(c):
                            self._drop(c)
                            break
                        self.n_malformed += 1  # an empty message, not the end of the connection
                        continue
                    msg = decode_frame(buf)
                    if msg is None:
                        self.n_malformed += 1
                        continue
                    msg.channel = self.channel
                    return msg, False
            now = time.monotonic()
            if now >= self._next_accept:
                self._next_accept = now + 0.005
                self._accept()
            wait = None if deadline is None else deadline - now
            if wait is not None and wait <= 0:
                return None, False
            lst = self._listener
            if lst is None:
                return None, False
            r, _, _ = select.select([lst, *self._conns], [], [], wait)
            if not r:
                return None, False
            if lst in r:
                self._accept()

    def fileno(self) -> int:
        return -1  # several sockets: python-can's Notifier falls back to polling recv(timeout)

    def linger(self, seconds: float = 0.05) -> None:
        """Stay on the bus ``seconds`` reading (and discarding) what arrives, so that peers
        accept this node's connection and read its frames before it leaves (a node that
        closes with unread frames resets its connections, and the kernel may discard what
        it sent to a peer that had not accepted yet)."""
        t_end = time.monotonic() + seconds
        while (left := t_end - time.monotonic()) > 0:
            self.recv(min(left, 0.005))

    def shutdown(self) -> None:
        super().shutdown()
        lst, self._listener = self._listener, None
        with self._lock:
            conns, self._conns = self._conns, []
        for s in (lst, *conns):
            if s is not None:
                s.close()

    @staticmethod
    def _detect_available_configs():
        return []


def local_pids_on_channel(channel: str) -> list[int]:  # pragma: no cover - diagnostics
    """Slots of ``channel`` currently bound (from /proc/net/unix)."""
    prefix = "@rig-can/" + channel + "/"
    out = []
    with open("/proc/net/unix") as f:
        for line in f:
            parts = line.split()
            if len(parts) >= 8 and parts[7].startswith(prefix):
                out.append(int(parts[7][len(prefix):]))
    return sorted(out)


__all__ = ["UnixCanBus", "encode_frame", "decode_frame", "slot_address", "SLOTS"]
