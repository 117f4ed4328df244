"""kill -9 durability of a running trial (issue 21; not a timed test).

    python benchmarks/bench_kill.py [--backend hardware|sim] [--kills 10] [--seed 1] [--json OUT.json]

Runs ``rig run config/recipes/smoke.yaml`` (22.6 s of trial) ``--kills`` times, on the emulated
rig (``--hardware``, a private copy of config/rigs/emulated.yaml) or on the simulated rig at real
time (``--sim --pace 1``), each in its own process group, and kills the whole group with SIGKILL
at a random moment between 1 s after the trial's first sample and 1 s before its end. The
moment of the first sample is read from the growing log itself (its ``trial`` metadata,
written and flushed at the first block: ``clock: first_sample``; a log written before issue 21,
e.g. ``PYTHONPATH=<an export of an older commit>``, has no such record: its start_time_ns once
its first raw block is on disk).

The loss of each kill: the wall-clock time of the kill minus the ``log_time`` of the last sample
``rig recover`` keeps (log_time is the wall-clock time each sample was taken, docs/hardware.md).
Prints each loss beside the load average, then the median and the worst.
Targets: median <= 0.5 s, worst <= 1 s.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "config" / "recipes" / "smoke.yaml"
TRIAL_S = 22.5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _profile(tmp: Path, k: int, repo: Path) -> Path:
    """The emulated rig on a free port, its LVDT pty and CAN channel private to this run."""
    p = tmp / f"rig-{k}.yaml"
    p.write_text(f"""extends: {repo / 'config/rigs/emulated.yaml'}
hardware:
  loadcells: {{port: {_free_port()}}}
  lvdt: {{port: {tmp / f'lvdt-{k}'}}}
  valve: {{channel: bench-kill-{os.getpid()}-{k}}}
  emulators: {{run_dir: {tmp}, autostart: true}}
""")
    return p


def _first_sample_ns(path: Path) -> int | None:
    """start_time_ns of the log once the first sample's clock is on disk, else None."""
    from rig.log.reader import scan

    if not path.exists() or path.stat().st_size < 1000:
        return None
    try:
        c = scan(path, topics=set())
    except Exception:  # noqa: BLE001 - a file being written
        return None
    trial = c.metadata_dict().get("trial", {})
    if trial.get("clock") == "first_sample":
        return int(trial["start_time_ns"])
    if "clock" not in trial and "start_time_ns" in trial:  # a log from before issue 21: its first block on disk
        from rig.log.schemas import RAW_TOPIC

        c = scan(path, topics={RAW_TOPIC})
        if any(c.topic_of(m) == RAW_TOPIC for m in c.messages):
            return int(trial["start_time_ns"])
    return None


def _last_sample_ns(path: Path) -> int | None:
    """Wall-clock ns of the last sample a recovery of ``path`` keeps (raw blocks and /log25)."""
    from rig.log.recover import recover
    from rig.log.reader import scan
    from rig.log.schemas import LOG25_TOPIC, RAW_TOPIC, decode_raw

    fixed = path.with_suffix(".recovered.mcap")
    recover(path, fixed)
    c = scan(fixed)
    last = None
    for m in c.messages:
        topic = c.topic_of(m)
        if topic == LOG25_TOPIC:
            ns = m.log_time
        elif topic == RAW_TOPIC:
            t = decode_raw(c.channels[m.channel_id].message_encoding, m.data)["t_s"]
            ns = m.log_time + int(round((float(t[-1]) - float(t[0])) * 1e9))  # log_time: the block's first
        else:
            continue
        last = ns if last is None else max(last, ns)
    return last


def one_kill(backend: str, tmp: Path, k: int, rnd: random.Random, repo: Path = REPO) -> dict:
    out = tmp / f"kill-{k}.mcap"
    args = [sys.executable, "-m", "rig.cli", "run", str(repo / SMOKE.relative_to(REPO)), "--out", str(out), "-q"]
    args += ["--hardware", str(_profile(tmp, k, repo))] if backend == "hardware" else ["--sim", "--pace", "1"]
    proc = subprocess.Popen(args, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        t_end = time.monotonic() + 120
        start = None
        while start is None:
            if proc.poll() is not None:
                raise RuntimeError(f"rig run exited ({proc.returncode}) before its first sample")
            if time.monotonic() > t_end:
                raise RuntimeError("no first sample within 120 s")
            time.sleep(0.1)
            start = _first_sample_ns(out)
        at_s = rnd.uniform(1.0, TRIAL_S - 1.0)
        delay = (start + int(at_s * 1e9) - time.time_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)
        t_kill = time.time_ns()
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.wait()
    last = _last_sample_ns(out)
    return {"kill_at_s": (t_kill - start) / 1e9, "loss_s": (t_kill - last) / 1e9 if last else None,
            "load": os.getloadavg()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", choices=("hardware", "sim"), default="hardware")
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--repo", type=Path, default=REPO, help="the checkout whose recipe and emulated profile to run "
                                                           "(with PYTHONPATH=that checkout: an older commit)")
    a = ap.parse_args()
    rnd = random.Random(a.seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-kill-") as d:
        for k in range(a.kills):
            r = one_kill(a.backend, Path(d), k, rnd, a.repo.resolve())
            rows.append(r)
            load = " ".join(f"{x:.2f}" for x in r["load"])
            print(f"kill {k + 1:2d}/{a.kills}: at {r['kill_at_s']:6.2f} s of trial, lost "
                  f"{r['loss_s']:.3f} s   (load average {load})", flush=True)
    losses = [r["loss_s"] for r in rows if r["loss_s"] is not None]
    print(f"{a.backend}: {len(losses)} kills, loss median {statistics.median(losses):.3f} s, "
          f"worst {max(losses):.3f} s (targets: median <= 0.5 s, worst <= 1 s)")
    if a.json:
        a.json.write_text(json.dumps({"backend": a.backend, "kills": rows}, indent=2))


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
