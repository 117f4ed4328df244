"""Pseudo-terminals for the serial emulators (no socat on these machines).

:func:`open_pty` gives one pty whose slave is reachable under a stable path
(a symlink), for a device that writes to the master side. :class:`PtyBridge`
joins two ptys with a Python thread copying bytes both ways, so that two
programs that both open a serial *port by name* (a pymodbus RTU server and
client) talk to each other.
"""

from __future__ import annotations

import fcntl
import os
import select
import threading
import tty
from pathlib import Path


def _symlink(target: str, link: str | os.PathLike) -> None:
    link = Path(link)
    link.parent.mkdir(parents=True, exist_ok=True)
    tmp = link.with_name(link.name + ".tmp")
    try:
        tmp.unlink()
    except FileNotFoundError:
        pass
    os.symlink(target, tmp)
    os.replace(tmp, link)


def open_pty(link: str | os.PathLike | None = None) -> tuple[int, int, str]:
    """(master_fd non-blocking, slave_fd, slave_name); the slave in raw mode, linked at ``link``."""
    master, slave = os.openpty()
    tty.setraw(slave)
    fl = fcntl.fcntl(master, fcntl.F_GETFL)
    fcntl.fcntl(master, fcntl.F_SETFL, fl | os.O_NONBLOCK)
    name = os.ttyname(slave)
    if link is not None:
        _symlink(name, link)
    return master, slave, name


class PtyBridge:
    """Two ptys joined back to back: whatever is written to port A is read on port B and back."""

    def __init__(self, link_a: str | os.PathLike, link_b: str | os.PathLike):
        self.ma, self.sa, self.name_a = open_pty(link_a)
        self.mb, self.sb, self.name_b = open_pty(link_b)
        self.link_a, self.link_b = str(link_a), str(link_b)
        self._r, self._w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)
        self._thread.start()

    def _run(self):
        pairs = {self.ma: self.mb, self.mb: self.ma}
        while True:
            try:
                ready, _, _ = select.select([self.ma, self.mb, self._r], [], [], 1.0)
            except (OSError, ValueError):
                return
            if self._r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    continue  # EIO while nobody has the slave open
                if data:
                    try:
                        os.write(pairs[fd], data)
                    except OSError:
                        pass

    def close(self):
        try:
            os.write(self._w, b"x")
        except OSError:
            pass
        self._thread.join(timeout=2)
        for fd in (self.ma, self.sa, self.mb, self.sb, self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass
        for link in (self.link_a, self.link_b):
            try:
                os.unlink(link)
            except OSError:
                pass
