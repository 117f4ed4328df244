"""Linux process helpers (prctl) for the device processes: the loop and the emulators."""

from __future__ import annotations

import ctypes
import signal

PR_SET_PDEATHSIG = 1
PR_SET_NAME = 15
PR_SET_TIMERSLACK = 29


def _libc():
    return ctypes.CDLL("libc.so.6", use_errno=True)


def prctl(option: int, arg: int) -> bool:
    try:
        return _libc().prctl(option, ctypes.c_ulong(arg), 0, 0, 0) == 0
    except Exception:  # noqa: BLE001 - not Linux
        return False


def set_process_name(name: str) -> bool:
    """Set the kernel's name of this process (``/proc/PID/comm``, 15 bytes: PR_SET_NAME)."""
    try:
        return _libc().prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0) == 0
    except Exception:  # noqa: BLE001
        return False


def set_pdeathsig(sig: int = signal.SIGTERM) -> bool:
    """Deliver ``sig`` to this process when its parent dies (PR_SET_PDEATHSIG)."""
    return prctl(PR_SET_PDEATHSIG, sig)


def serve_private_socket(path, handle_line, name: str):
    """A Unix stream socket at ``path`` only this user may use (mode 0600), served on a daemon thread:
    each connection sends one line, ``handle_line(line)`` returns the one-line answer (without its
    newline). Returns the listening socket (close it, then unlink ``path``, to stop)."""
    import os
    import socket
    import threading

    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)
    try:
        s.bind(str(path))
    finally:
        os.umask(old)
    s.listen(4)

    def serve():
        while True:
            try:
                conn, _ = s.accept()
            except OSError:
                return
            with conn:
                try:
                    conn.settimeout(2.0)
                    conn.sendall(handle_line(conn.makefile("r").readline().strip()).encode() + b"\n")
                except OSError:
                    pass

    threading.Thread(target=serve, name=name, daemon=True).start()
    return s


def open_tcp_nodelay(host: str, port: int, timeout_s: float, device: str, address: str):
    """A connected, non-blocking TCP socket with Nagle off (the devices' per-tick requests);
    :class:`drivers.errors.DeviceError` naming ``device`` at ``address`` when it cannot connect."""
    import socket

    from drivers.errors import DeviceError

    try:
        sk = socket.create_connection((host, port), timeout=max(0.5, timeout_s))
    except OSError as exc:
        raise DeviceError(device, address, f"cannot connect: {exc}") from exc
    sk.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sk.setblocking(False)
    return sk


def serve_requests(conn, on_request, poll_s: float = 0.1) -> None:
    """An emulator process's control loop: ``on_request(req)`` for each request on the pipe ``conn``
    until a ``("stop",)`` request, SIGTERM or the pipe closed."""
    stop = {"flag": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    while not stop["flag"]:
        if conn.poll(poll_s):
            try:
                req = conn.recv()
            except EOFError:
                break
            if req[0] == "stop":
                break
            on_request(req)


def close_quietly(sock) -> None:
    """Close a socket (or None) whatever state it is in."""
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass


def recv_available(sock, rx: bytearray, need: int, lost, peer: str) -> None:
    """Append to ``rx`` what a non-blocking socket has, stopping once ``rx`` holds ``need`` bytes (no
    second recv just to hear EAGAIN); a closed or failed connection raises ``lost(message)`` (the
    device's error for a lost link: ``peer`` is who closed it)."""
    import errno

    try:
        while True:
            chunk = sock.recv(4096)
            if not chunk:
                raise lost(f"connection lost (closed by the {peer})")
            rx += chunk
            if len(rx) >= need:
                return
    except BlockingIOError:
        pass
    except OSError as exc:
        if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK):
            raise lost(f"connection lost: {exc}") from exc
