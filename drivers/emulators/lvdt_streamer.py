"""LVDT conditioner emulator: streams :mod:`drivers.lvdt` frames on a pty.

The slave side of the pty is linked at ``cfg.port`` so the driver opens it by
name like a real serial port. A pty never drops bytes, so loss is made here:
faults (``self.faults``) ``drop_every`` (skip every n-th frame), ``corrupt_every``
(flip a byte of every n-th frame), ``garbage_every`` (n-th frame preceded by
junk bytes), ``silent`` (stop sending), and :meth:`vanish` (close the pty and
remove the link, as if the device was unplugged).
"""

from __future__ import annotations

import os

from drivers.config import LvdtConfig
from drivers.emulators.pty import open_pty
from drivers.lvdt import encode_frame


class LvdtStreamer:
    def __init__(self, cfg: LvdtConfig):
        self.cfg = cfg
        self.faults: dict = {}
        self.seq = 0
        self.sent = 0
        self.dropped = 0
        self.overflow = 0
        self.master = self.slave = None
        self.vanished = False

    def start(self) -> None:
        self.master, self.slave, self.name = open_pty(self.cfg.port)

    def counts_of(self, position_um: float) -> int:
        pos = position_um - self.cfg.offset_um
        if self.cfg.invert:
            pos = -pos
        return int(round(pos / self.cfg.um_per_count))

    def send(self, position_um: float, status: int = 0) -> None:
        """Emit the frame of one conversion (with the configured faults)."""
        if self.master is None or self.vanished:
            return
        self.seq = (self.seq + 1) & 0xFFFF
        f = self.faults
        n = self.seq
        if f.get("silent"):
            return
        if f.get("drop_every") and n % int(f["drop_every"]) == 0:
            self.dropped += 1
            return
        frame = encode_frame(self.seq, self.counts_of(position_um), status)
        if f.get("corrupt_every") and n % int(f["corrupt_every"]) == 0:
            b = bytearray(frame)
            b[5] ^= 0x5A
            frame = bytes(b)
        if f.get("garbage_every") and n % int(f["garbage_every"]) == 0:
            frame = b"\x00\xa5\x13\x37garbage\xa5" + frame
        try:
            os.write(self.master, frame)
            self.sent += 1
        except BlockingIOError:
            self.overflow += 1  # nobody reading: the tty buffer is full
        except OSError:
            self.overflow += 1

    def vanish(self) -> None:
        """The device disappears: pty closed, link removed."""
        self.vanished = True
        self.stop()

    def stop(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None
        try:
            if os.path.islink(self.cfg.port):
                os.unlink(self.cfg.port)
        except OSError:
            pass
