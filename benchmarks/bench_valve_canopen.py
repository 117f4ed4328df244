"""Per-tick cost of the CANopen valve link: ``read()`` + ``write()`` of :class:`drivers.valve.CanopenValve`.

    python benchmarks/bench_valve_canopen.py [--seconds 10]

The emulator (``python -m drivers.emulators.valve_controller``) runs in its own
process on a private channel of the machine-local bus; this process ticks at 1 kHz
(sleeping to deadlines) and times read() (drain + dispatch of the TPDO/heartbeat
frames) and write() (RPDO + SYNC + heartbeat when due) with perf_counter_ns.
Prints p50/p99/p99.9/max in µs, the TPDO count and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from drivers.valve import CanopenValve, CanopenValveConfig  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--timeouts-s", type=float, default=0.5,
                    help="heartbeat timeout and set-point watchdog (the profile default is 0.05/0.02 s; "
                         "longer here so a loaded machine's stalls do not end the measurement)")
    a = ap.parse_args()
    cfg = CanopenValveConfig(channel=f"bench-{uuid.uuid4().hex[:8]}", node_id=3, heartbeat_timeout_s=a.timeouts_s,
                             watchdog_s=a.timeouts_s, tpdo_timeout_s=a.timeouts_s)
    p = subprocess.Popen([sys.executable, "-m", "drivers.emulators.valve_controller", "--channel", cfg.channel,
                          "--node-id", "3"], cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert json.loads(p.stdout.readline())["ready"]
    v = CanopenValve(cfg)
    try:
        v.connect()
        v.start()
        n = int(a.seconds * 1000)
        t_read = np.empty(n)
        t_write = np.empty(n)
        load0 = os.getloadavg()
        t_next = time.monotonic()
        for i in range(n):
            t_next += 1e-3
            d = t_next - time.monotonic()
            if d > 0:
                time.sleep(d)
            cmd = 0.3 * np.sin(i * 2e-3 * np.pi)
            t0 = time.perf_counter_ns()
            st = v.read()
            t1 = time.perf_counter_ns()
            v.send(cmd)
            t2 = time.perf_counter_ns()
            t_read[i] = (t1 - t0) / 1e3
            t_write[i] = (t2 - t1) / 1e3
        probs = [msg for _, msg in v.problems()]
        ok = v.safe_stop()
        load1 = os.getloadavg()
    finally:
        v.close()
        p.stdin.write("quit\n")
        p.stdin.flush()
        p.wait(5)
    both = t_read + t_write

    def row(name, x):
        q = np.percentile(x, [50, 99, 99.9])
        print(f"{name:<14} p50 {q[0]:7.1f}  p99 {q[1]:7.1f}  p99.9 {q[2]:7.1f}  max {x.max():8.1f} µs")

    print(f"CANopen valve link, {n} ticks at 1 kHz, emulator in its own process (rig_unix bus)")
    row("read()", t_read)
    row("write()", t_write)
    row("read+write", both)
    print(f"TPDOs received {st.n_tpdo} of {n} SYNCs, health {probs or 'ok'}, safe_stop verified {ok}")
    print(f"load average {load0[0]:.2f} -> {load1[0]:.2f} on {os.cpu_count()} CPUs")
    emulator_cost(cfg, min(n, 5000))
    return 0


def emulator_cost(cfg0: CanopenValveConfig, n: int) -> None:
    """The emulator's side: one ``poll(0)`` that takes the tick's RPDO + SYNC and sends the TPDO.

    Host and emulator in this one process, stepped alternately (no thread), so only
    the emulator's work is timed."""
    from drivers.emulators.valve_controller import ValveControllerEmulator

    cfg = cfg0.model_copy(update={"channel": cfg0.channel + "-em"})
    em = ValveControllerEmulator(cfg, on_sync=lambda spool: None)
    em.start()
    v = CanopenValve(cfg)
    stop = False

    import threading

    def pump():  # only while connecting (SDO needs the emulator to answer)
        while not stop:
            em.poll(0.001)

    th = threading.Thread(target=pump, daemon=True)
    th.start()
    try:
        v.connect()
        v.start()
        stop = True
        th.join()
        t_poll = np.empty(n)
        for i in range(n):
            v.read()
            v.send(0.2)
            time.sleep(0.0002)  # let the frames land
            t0 = time.perf_counter_ns()
            em.poll(0.0)
            t_poll[i] = (time.perf_counter_ns() - t0) / 1e3
        q = np.percentile(t_poll, [50, 99])
        print(f"emulator poll (RPDO+SYNC in, TPDO out): p50 {q[0]:.1f}  p99 {q[1]:.1f}  max {t_poll.max():.1f} µs, "
              f"{em.n_tpdo} TPDOs")
    finally:
        stop = True
        v.close()
        em.stop()


if __name__ == "__main__":
    sys.exit(main())
