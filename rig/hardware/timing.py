"""Pacing and timing statistics of the real-time loop.

Pacing (Dupont & Dunlap 1995: "The control loop operates at 1 kHz"): absolute
deadlines ``t0 + k * period`` on ``time.monotonic`` (CLOCK_MONOTONIC).

* Under SCHED_FIFO: sleep to the deadline only (``time.sleep`` is an absolute
  ``clock_nanosleep`` on Linux/CPython 3.11, timer slack is 0 for RT threads).
  Never spin: the RT throttle parks a spinning FIFO thread for ~50 ms.
* Otherwise: timer slack set to 1 ns (prctl), sleep to ``deadline - spin_s``,
  then spin on the clock for the rest.
* A cycle that wakes more than a period late skips the missed deadlines (they
  are counted), rather than running them back to back.

Statistics in the style of LinuxCNC's latency-test / latency-histogram:
lateness (wake - deadline, signed), period (wake - previous wake), execution
time, jitter = max(max_period - T, T - min_period), misses over 100 µs,
500 µs and 1 ms, skipped cycles.
"""

from __future__ import annotations

import ctypes
import os
import time

import numpy as np

from drivers.linux import PR_SET_TIMERSLACK, prctl, set_pdeathsig, set_process_name

# signed lateness histogram edges (µs); first/last bins are open
HIST_EDGES_US = np.array([-1e9, -100, -50, -20, -10, 0, 10, 20, 50, 100, 200, 500, 1000, 2000,
                          5000, 1e9])
MISS_THRESHOLDS_US = (100, 500, 1000)


__all__ = ["Pacer", "StallProbe", "TimingStats", "attribute_skips", "format_stats", "setup_realtime",
           "set_pdeathsig", "set_process_name"]


def setup_realtime(sched_fifo: bool = True, priority: int = 80, cpu: int | None = None) -> dict:
    """Best-effort real-time setup of the calling process; says what it got and why not."""
    info = {"sched": "SCHED_OTHER", "priority": 0, "timer_slack_ns": None, "cpu": None,
            "mlockall": False, "note": ""}
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            info["cpu"] = cpu
        except (OSError, AttributeError) as exc:
            info["note"] += f"affinity refused ({exc}); "
    if sched_fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            info["sched"] = "SCHED_FIFO"
            info["priority"] = priority
        except (OSError, AttributeError) as exc:
            info["note"] += f"SCHED_FIFO refused ({exc}); sleep-then-spin under SCHED_OTHER; "
    if prctl(PR_SET_TIMERSLACK, 1):  # 1 ns
        info["timer_slack_ns"] = 1
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        if libc.mlockall(3) == 0:  # MCL_CURRENT | MCL_FUTURE
            info["mlockall"] = True
    except Exception:  # noqa: BLE001
        pass
    return info


class Pacer:
    """Absolute-deadline pacing with skip-on-overrun."""

    def __init__(self, period_s: float, fifo: bool, spin_s: float = 50e-6, clock=time.monotonic,
                 sleep=time.sleep):
        """``clock`` / ``sleep``: CLOCK_MONOTONIC and time.sleep; a simulated clock in tests
        (:class:`rig.hardware.fake.FakeClock`)."""
        self.period_s = period_s
        self.fifo = fifo
        self.spin_s = 0.0 if fifo else spin_s
        self.clock, self.sleep = clock, sleep
        self.t0 = 0.0
        self.k = 0
        self.skipped = 0

    def start(self, t0: float | None = None) -> None:
        self.t0 = self.clock() + 0.002 if t0 is None else t0
        self.k = 0

    def deadline(self, k: int | None = None) -> float:
        return self.t0 + (self.k if k is None else k) * self.period_s

    def wait(self) -> tuple[int, float, float]:
        """Wait for the deadline of tick ``k``; returns (k, deadline, wake time)."""
        mono = self.clock
        dl = self.t0 + self.k * self.period_s
        now = mono()
        rem = dl - now - self.spin_s
        if rem > 0:
            self.sleep(rem)
        if self.spin_s:
            while mono() < dl:
                pass
        return self.k, dl, mono()

    def due_skips(self, now: float) -> int:
        """The deadlines :meth:`advance` would skip if the current tick ended at ``now`` (a late wake:
        the cycles a stall already cost before the tick ran)."""
        if now > self.t0 + (self.k + 2) * self.period_s:
            return max(0, int((now - self.t0) / self.period_s) - self.k)
        return 0

    def advance(self, now: float | None = None) -> int:
        """Move to the next tick, skipping deadlines already past; returns ticks skipped."""
        now = self.clock() if now is None else now
        self.k += 1
        nxt = self.t0 + self.k * self.period_s
        skip = 0
        if now > nxt + self.period_s:  # woke/finished more than a period late: skip
            k_now = int((now - self.t0) / self.period_s)
            skip = k_now - self.k + 1
            if skip > 0:
                self.k += skip
                self.skipped += skip
            else:
                skip = 0
        return skip


class TimingStats:
    """Accumulates lateness / period / execution time (seconds) and summarises them."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.reset_window()
        self.total_hist = np.zeros(len(HIST_EDGES_US) - 1, dtype=np.int64)
        self.total = {"n": 0, "skipped": 0, "max_late_us": -1e9, "min_period_us": 1e9,
                      "max_period_us": 0.0, "max_exec_us": 0.0,
                      **{f"late_over_{t}us": 0 for t in MISS_THRESHOLDS_US}}
        self._all_late: list[np.ndarray] = []
        self._all_exec: list[np.ndarray] = []
        self._all_period: list[np.ndarray] = []

    def reset_window(self):
        self.w_late: list[np.ndarray] = []
        self.w_period: list[np.ndarray] = []
        self.w_exec: list[np.ndarray] = []
        self.w_skipped = 0

    def add(self, late_s: np.ndarray, period_s: np.ndarray, exec_s: np.ndarray, skipped: int = 0):
        late_us = np.asarray(late_s) * 1e6
        per_us = np.asarray(period_s) * 1e6
        exe_us = np.asarray(exec_s) * 1e6
        per_us = per_us[np.isfinite(per_us)]
        self.w_late.append(late_us)
        self.w_period.append(per_us)
        self.w_exec.append(exe_us)
        self.w_skipped += skipped
        self._all_late.append(late_us)
        self._all_exec.append(exe_us)
        self._all_period.append(per_us)
        t = self.total
        t["n"] += late_us.size
        t["skipped"] += skipped
        if late_us.size:
            t["max_late_us"] = max(t["max_late_us"], float(late_us.max()))
            t["max_exec_us"] = max(t["max_exec_us"], float(exe_us.max()))
        if per_us.size:
            t["min_period_us"] = min(t["min_period_us"], float(per_us.min()))
            t["max_period_us"] = max(t["max_period_us"], float(per_us.max()))
        for thr in MISS_THRESHOLDS_US:
            t[f"late_over_{thr}us"] += int((late_us > thr).sum())
        self.total_hist += np.histogram(late_us, HIST_EDGES_US)[0]

    @staticmethod
    def summarize(late_us: np.ndarray, per_us: np.ndarray, exe_us: np.ndarray, skipped: int,
                  period_s: float) -> dict:
        T = period_s * 1e6
        out = {"n": int(late_us.size), "skipped": int(skipped), "period_us": T}
        if late_us.size:
            p = np.percentile(late_us, [50, 99, 99.9])
            out.update(late_p50_us=float(p[0]), late_p99_us=float(p[1]), late_p999_us=float(p[2]),
                       late_max_us=float(late_us.max()), late_min_us=float(late_us.min()))
            pe = np.percentile(exe_us, [50, 99])
            out.update(exec_mean_us=float(exe_us.mean()), exec_p50_us=float(pe[0]),
                       exec_p99_us=float(pe[1]), exec_max_us=float(exe_us.max()))
            for thr in MISS_THRESHOLDS_US:
                out[f"late_over_{thr}us"] = int((late_us > thr).sum())
            out["late_hist_edges_us"] = HIST_EDGES_US[1:-1].tolist()
            out["late_hist"] = np.histogram(late_us, HIST_EDGES_US)[0].tolist()
        if per_us.size:
            out.update(period_mean_us=float(per_us.mean()), period_std_us=float(per_us.std()),
                       period_min_us=float(per_us.min()), period_max_us=float(per_us.max()),
                       jitter_us=float(max(per_us.max() - T, T - per_us.min())))
        return out

    def window(self) -> dict:
        cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
        s = self.summarize(cat(self.w_late), cat(self.w_period), cat(self.w_exec), self.w_skipped,
                           self.period_s)
        self.reset_window()
        return s

    def final(self) -> dict:
        cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
        return self.summarize(cat(self._all_late), cat(self._all_period), cat(self._all_exec),
                              self.total["skipped"], self.period_s)


def format_stats(s: dict, title: str = "loop timing") -> str:
    """A LinuxCNC-latency-test-like text report."""
    if not s.get("n"):
        return f"{title}: no cycles"
    lines = [
        f"{title}: {s['n']} cycles at {1e6 / s['period_us']:.0f} Hz, {s['skipped']} skipped",
        f"  lateness  p50 {s['late_p50_us']:8.1f} µs   p99 {s['late_p99_us']:8.1f} µs   "
        f"p99.9 {s['late_p999_us']:8.1f} µs   max {s['late_max_us']:8.1f} µs",
        f"  period    min {s.get('period_min_us', float('nan')):8.1f} µs   "
        f"max {s.get('period_max_us', float('nan')):8.1f} µs   jitter {s.get('jitter_us', float('nan')):8.1f} µs",
        f"  exec      p50 {s['exec_p50_us']:8.1f} µs   p99 {s['exec_p99_us']:8.1f} µs   "
        f"max {s['exec_max_us']:8.1f} µs",
        (f"  device reads max {s['read_max_us']:8.1f} µs, {s['read_over_1ms']} over 1 ms\n"
         if "read_max_us" in s else "") +
        f"  late > 100 µs: {s['late_over_100us']}   > 500 µs: {s['late_over_500us']}   "
        f"> 1 ms: {s['late_over_1000us']}",
    ]
    edges = s.get("late_hist_edges_us", [])
    hist = s.get("late_hist", [])
    if hist:
        labels = [f"< {edges[0]:g}"] + [f"{a:g}..{b:g}" for a, b in zip(edges[:-1], edges[1:])] + [f">= {edges[-1]:g}"]
        lines.append("  lateness histogram (µs): " + ", ".join(
            f"{lab}: {c}" for lab, c in zip(labels, hist) if c))
    return "\n".join(lines)


# -- whose were the skipped cycles: the VM's or the loop's ------------------------------------------------

def _probe_main(conn, period_s: float, threshold_s: float, priority: int, cpu: int | None) -> None:
    """A bare sleeper: wakes every ``period_s`` and keeps each gap over ``threshold_s`` as (start, end) on
    CLOCK_MONOTONIC until told to stop; then sends them."""
    set_process_name("rig-stall-probe")
    set_pdeathsig()
    setup_realtime(priority > 0, max(1, priority), cpu)
    gaps, mono = [], time.monotonic
    last = mono()
    while not conn.poll():
        time.sleep(period_s)
        now = mono()
        if now - last > threshold_s:
            gaps.append((last, now))
        last = now
    conn.send(gaps)


class StallProbe:
    """A second process that does nothing but sleep ``period_s`` at a time (SCHED_FIFO ``priority`` where
    permitted, on the loop's ``cpu``) and notes when it woke late. When the loop skipped cycles and the
    probe stalled over the same time, the machine (the VM's vCPU, the host) stalled both: the skip is
    the VM's; when the probe ran on time, the loop itself was late."""

    def __init__(self, period_s: float = 1e-3, threshold_s: float = 2e-3, priority: int = 0,
                 cpu: int | None = None):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_probe_main, name="rig-stall-probe", daemon=True,
                                args=(child, period_s, threshold_s, priority, cpu))
        self.gaps: list[tuple[float, float]] = []

    def start(self) -> "StallProbe":
        self.proc.start()
        return self

    def stop(self) -> list[tuple[float, float]]:
        try:
            self._conn.send("stop")
            if self._conn.poll(5.0):
                self.gaps = [tuple(g) for g in self._conn.recv()]
        except (OSError, EOFError):
            pass
        self.proc.join(2.0)
        if self.proc.is_alive():
            self.proc.kill()
        return self.gaps


def attribute_skips(skips, probe_gaps, period_s: float) -> dict:
    """Each late tick (``(end, cycles skipped)``; it was late over ``[end - (n + 1) period, end]``) to the
    VM when a gap of the probe overlaps that time, else to the loop. Counts of cycles and of episodes."""
    out = {"vm_cycles": 0, "loop_cycles": 0, "vm_episodes": 0, "loop_episodes": 0, "loop_at": []}
    gaps = sorted(probe_gaps)
    for end, n in skips:
        start = end - (n + 1) * period_s
        vm = any(g0 < end and g1 > start for g0, g1 in gaps)
        key = "vm" if vm else "loop"
        out[f"{key}_cycles"] += int(n)
        out[f"{key}_episodes"] += 1
        if not vm:
            out["loop_at"].append((round(end, 6), int(n)))
    return out
