"""Why the loop's LVDT read once blocked: a SCHED_FIFO reader of a pty, plain vs TIOCINQ-gated.

    python benchmarks/bench_loop_pty.py [--seconds 30]

A writer process (SCHED_FIFO 70) writes one 11-byte LVDT frame per millisecond to a pty master; a
reader (SCHED_FIFO 80) polls the slave every millisecond, non-blocking, and times each poll:

* ``read``: ``os.read`` straight away (what drivers/lvdt.py did). With nothing in the line
  discipline's buffer the kernel first waits for the flush_to_ldisc work item
  (``tty_buffer_flush_work``), which runs in a SCHED_OTHER kworker: on a busy machine the
  real-time reader sleeps inside a "non-blocking" read until that kworker gets a CPU;
* ``inq``: ``ioctl(TIOCINQ)`` first and ``os.read`` only when bytes are there (drivers/lvdt.py now).

Prints per mode the poll time p50 / p99.9 / max, the polls over 1 ms and the longest time without
new bytes (how stale the position got), with the load average.
Needs SCHED_FIFO (root or CAP_SYS_NICE); runs without it, but then measures something else.
"""

from __future__ import annotations

import argparse
import array
import fcntl
import multiprocessing as mp
import os
import pty
import termios
import time
import tty

import numpy as np

FRAME = b"\xa5\x5a" + bytes(9)


def _fifo(prio: int) -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        return True
    except OSError:
        return False


def _ticks(seconds: float):
    """Sleep to each 1 ms deadline for ``seconds``; yields once per tick."""
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < seconds:
        k += 1
        r = t0 + k * 1e-3 - time.monotonic()
        if r > 0:
            time.sleep(r)
        yield k


def _writer(master: int, seconds: float) -> None:
    _fifo(70)
    for _ in _ticks(seconds):
        os.write(master, FRAME)


def run(mode: str, seconds: float) -> dict:
    master, slave = pty.openpty()
    tty.setraw(slave)
    w = mp.get_context("fork").Process(target=_writer, args=(master, seconds))
    w.start()
    fifo = _fifo(80)
    fcntl.fcntl(slave, fcntl.F_SETFL, fcntl.fcntl(slave, fcntl.F_GETFL) | os.O_NONBLOCK)
    inq = array.array("i", [0])
    dt = []
    last_data = time.monotonic()
    data_gap = 0.0
    for _ in _ticks(seconds):
        a = time.perf_counter()
        got = b""
        if mode == "inq":
            fcntl.ioctl(slave, termios.FIONREAD, inq, True)
            if inq[0]:
                got = os.read(slave, 65536)
        else:
            try:
                got = os.read(slave, 65536)
            except BlockingIOError:
                pass
        dt.append(time.perf_counter() - a)
        if got:
            now = time.monotonic()
            data_gap = max(data_gap, now - last_data)
            last_data = now
    w.join()
    if fifo:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.close(master)
    os.close(slave)
    us = np.array(dt) * 1e6
    return {"mode": mode, "fifo": fifo, "polls": us.size, "p50_us": float(np.median(us)),
            "p999_us": float(np.percentile(us, 99.9)), "max_us": float(us.max()),
            "over_1ms": int((us > 1000).sum()), "load": os.getloadavg()[0], "data_gap_ms": data_gap * 1e3}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    a = ap.parse_args(argv)
    for mode in ("read", "inq"):
        r = run(mode, a.seconds)
        print(f"{r['mode']:>4}: {r['polls']} polls, p50 {r['p50_us']:.1f} µs, p99.9 {r['p999_us']:.1f} µs, "
              f"max {r['max_us']:.0f} µs, {r['over_1ms']} over 1 ms; longest time without new bytes "
              f"{r['data_gap_ms']:.1f} ms (SCHED_FIFO {r['fifo']}; load average "
              f"{r['load']:.2f})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
