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

or several frames sent together (:meth:`UnixCanBus.send_frames`: the host's set-point
PDO and its SYNC in one socket operation, one wake-up of the peer instead of two)::

    u8 kind (1 = batch)  u8 n (2..BATCH_MAX)  then n frames as above, back to back

A receiver splits a batch back into its frames, in order: ``recv()`` returns them one by
one as ordinary ``can.Message`` s (canopen on the other side sees normal frames).
Anything else (wrong length, dlc > 8, id out of range, unknown kind, a batch whose frames
do not add up to the message exactly or that holds a batch) is dropped whole and counted
once in :attr:`UnixCanBus.n_malformed`; it never raises.

Per tick the host does not go through python-can's ``BusABC.recv`` (its filter and
timeout logic per call): :meth:`UnixCanBus.drain_frames` reads everything queued on
every connection and returns it as ``(arbitration id, flags, data)`` tuples.

Use: ``UnixCanBus(channel="rig-A")`` or, through python-can's plugin entry point,
``can.Bus(interface="rig_unix", channel="rig-A")``.
"""

from __future__ import annotations

import array
import collections
import errno
import fcntl
import select
import socket
import struct
import termios
import threading
import time

import can

SLOTS = 16
_HDR = struct.Struct("<BBIB")
_BATCH_HDR = struct.Struct("<BB")
KIND_FRAME, KIND_BATCH = 0, 1
BATCH_MAX = 16
F_EXT, F_RTR, F_ERR = 0x01, 0x02, 0x04
ACCEPT_EVERY_S = 0.005  # new peers accepted (and hung-up ones noticed) at least this often
RECV_SIZE = 2 + BATCH_MAX * (_HDR.size + 8) + 1  # a longer message is malformed (and seen as too long)


def slot_address(channel: str, slot: int) -> bytes:
    """The abstract-namespace address of ``slot`` on ``channel``."""
    return b"\0rig-can/" + channel.encode() + b"/" + str(slot).encode()


def encode_frame(msg: can.Message) -> bytes:
    flags = (F_EXT if msg.is_extended_id else 0) | (F_RTR if msg.is_remote_frame else 0) \
        | (F_ERR if msg.is_error_frame else 0)
    data = bytes(msg.data or b"")
    return _HDR.pack(KIND_FRAME, flags, msg.arbitration_id, len(data)) + data


def encode_frames(frames) -> bytes:
    """Standard (11-bit) data frames ``(arbitration id, data)`` as one message: a single frame as
    :func:`encode_frame` does, two or more (up to ``BATCH_MAX``) as a batch."""
    n = len(frames)
    if not 1 <= n <= BATCH_MAX:
        raise ValueError(f"rig_unix: {n} frames in one message (1..{BATCH_MAX})")
    parts = [] if n == 1 else [_BATCH_HDR.pack(KIND_BATCH, n)]
    for arb, data in frames:
        if not 0 <= arb <= 0x7FF or len(data) > 8:
            raise ValueError(f"rig_unix: frame id 0x{arb:x} with {len(data)} bytes is not a standard CAN frame")
        parts.append(_HDR.pack(KIND_FRAME, 0, arb, len(data)))
        parts.append(data)
    return b"".join(parts)


def _frame_at(buf: bytes, off: int):
    """The frame at ``off``: ((arbitration id, flags, data), end offset), or None if not a valid one."""
    if len(buf) - off < _HDR.size:
        return None
    kind, flags, arb, dlc = _HDR.unpack_from(buf, off)
    end = off + _HDR.size + dlc
    if kind != KIND_FRAME or dlc > 8 or end > len(buf) or flags & ~0x07 \
            or arb > (0x1FFFFFFF if flags & F_EXT else 0x7FF):
        return None
    return (arb, flags, buf[off + _HDR.size:end]), end


def decode_frames(buf: bytes) -> list | None:
    """A received message as its frames ``[(arbitration id, flags, data), ...]`` (one, or a batch's
    in order), or None when it is not exactly a valid frame or batch."""
    if len(buf) >= 2 and buf[0] == KIND_BATCH:
        n = buf[1]
        if not 2 <= n <= BATCH_MAX:
            return None
        out, off = [], 2
        for _ in range(n):
            fr = _frame_at(buf, off)
            if fr is None:
                return None
            out.append(fr[0])
            off = fr[1]
        return out if off == len(buf) else None
    fr = _frame_at(buf, 0)
    if fr is None or fr[1] != len(buf):
        return None
    return [fr[0]]


def to_message(arb: int, flags: int, data: bytes, channel: str | None = None) -> can.Message:
    """A decoded frame as a python-can message."""
    return can.Message(arbitration_id=arb, is_extended_id=bool(flags & F_EXT), is_remote_frame=bool(flags & F_RTR),
                       is_error_frame=bool(flags & F_ERR), dlc=len(data), data=data, timestamp=time.time(),
                       channel=channel, check=False)


def decode_frame(buf: bytes) -> can.Message | None:
    """A received datagram holding one frame as a message, or None when it is not a valid one."""
    frames = decode_frames(buf)
    if frames is None or len(frames) != 1 or buf[0] != KIND_FRAME:
        return None
    return to_message(*frames[0])


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
        self._next_full = 0.0    # the next drain that reads until EAGAIN/EOF even when gated
        self._rx: collections.deque = collections.deque()  # decoded frames not yet returned by recv
        self._inq = array.array("i", [0])  # SIOCINQ result
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
            self._next_accept = now + ACCEPT_EVERY_S
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

    def send_frames(self, frames) -> None:
        """Send standard data frames ``(arbitration id, data)`` in one message (one socket send per
        peer): the receivers get them as separate frames, in this order."""
        self._send_datagram(encode_frames(frames))

    def send_raw(self, datagram: bytes) -> None:
        """Send arbitrary bytes to every peer (fault injection: malformed frames)."""
        self._send_datagram(bytes(datagram))

    def _drain(self, gated: bool = False) -> None:
        """Read every message queued on every connection (non-blocking) into ``self._rx``.

        ``gated``: ask each connection first how many bytes it holds (SIOCINQ, which counts every
        queued message of a seqpacket socket) and read only those, instead of reading until EAGAIN
        (a Python exception per connection per tick). A peer that hung up queues nothing that
        SIOCINQ counts, so every ``ACCEPT_EVERY_S`` (and for a connection a send found gone) the
        drain reads until EAGAIN or EOF as the ungated one does."""
        if self._listener is None:
            raise can.CanOperationError(f"rig_unix:{self.channel}: bus is shut down")
        rx = self._rx
        now = time.monotonic()
        full = not gated or now >= self._next_full
        if full:
            self._next_full = now + ACCEPT_EVERY_S
        inq = self._inq
        for c in tuple(self._conns):
            left = -1
            if not full and c not in self._gone:
                try:
                    fcntl.ioctl(c.fileno(), termios.FIONREAD, inq, True)
                except OSError:
                    inq[0] = 1  # let recv say what is wrong
                left = inq[0]
                if left <= 0:
                    continue
            while left:  # this peer's queue, until empty (ungated: left stays negative)
                try:
                    buf = c.recv(RECV_SIZE)
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
                if left > 0:
                    left = max(0, left - len(buf))
                frames = decode_frames(buf)
                if frames is None:
                    self.n_malformed += 1
                    continue
                rx.extend(frames)
        if now >= self._next_accept:
            self._next_accept = now + ACCEPT_EVERY_S
            self._accept()

    def drain_frames(self) -> list:
        """Every frame received so far, non-blocking, as ``(arbitration id, flags, data)`` tuples
        (``F_EXT``, ``F_RTR``, ``F_ERR`` in flags), oldest first; what a real-time caller uses
        instead of ``recv(0)`` one frame at a time (gated by SIOCINQ: see :meth:`_drain`)."""
        self._drain(gated=True)
        rx = self._rx
        out = list(rx)
        rx.clear()
        return out

    def _recv_internal(self, timeout: float | None):
        if self._listener is None:
            raise can.CanOperationError(f"rig_unix:{self.channel}: bus is shut down")
        deadline = None if timeout is None else time.monotonic() + timeout
        rx = self._rx
        while True:
            if not rx:
                self._drain()
            if rx:
                return to_message(*rx.popleft(), channel=self.channel), False
            now = time.monotonic()
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


__all__ = ["UnixCanBus", "encode_frame", "encode_frames", "decode_frame", "decode_frames", "to_message",
           "slot_address", "SLOTS", "BATCH_MAX", "F_EXT", "F_RTR", "F_ERR"]
