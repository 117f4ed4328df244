"""`rig run --sim` paused by SIGUSR1 and by `rig pause` / `rig resume` through its socket: the pause holds
at the plan's next safe point, both are logged as events, the plan's later events move with the pause,
and the log reads back (the physics of a pause: benchmarks/bench_pause.py, docs/hardware.md)."""

from __future__ import annotations

from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import pytest

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

from rig.log import read_trial



def _rig(*args, env=None):
    return subprocess.run([sys.executable, "-m", "rig.cli", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=60, env=env)


def test_a_paced_simulated_run_pauses_on_sigusr1_and_resumes_on_rig_resume(tmp_path, monkeypatch, short_recipe):
    import os

    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "run"), "PYTHONUNBUFFERED": "1"}
    (tmp_path / "run").mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    recipe = tmp_path / "pause.yaml"
    recipe.write_text(short_recipe("pause", settle_s=1.0, stub_um=10, rest_s=1.0))
    out = tmp_path / "pause.mcap"
    p = subprocess.Popen([sys.executable, "-m", "rig.cli", "run", str(recipe), "--sim", "--pace", "1", "-q",
                          "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         env=env)
    sock = tmp_path / "run" / "rig" / f"run-{p.pid}.sock"
    t_end = time.monotonic() + 30
    while not sock.exists():
        assert p.poll() is None and time.monotonic() < t_end, p.stdout.read() if p.poll() is not None else "no socket"
        time.sleep(0.05)
    assert sock.stat().st_mode & 0o777 == 0o600
    time.sleep(0.3)  # in the settling hold: the pause takes effect at the next safe point (the stub's start)
    p.send_signal(signal.SIGUSR1)  # toggles: pause
    # wait for the pause to take effect (its echo), then hold 1.2 s: the hold does not depend on how long
    # the run took from binding its socket to tick 0 (a loaded machine)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(p.stdout), daemon=True)
    reader.start()
    t_end = time.monotonic() + 30
    while not any(line.startswith("paused at") for line in lines):
        assert p.poll() is None and time.monotonic() < t_end, "".join(lines) or "no pause"
        time.sleep(0.05)
    time.sleep(1.2)
    from rig.session.pausing import send

    assert send("status") == "ok paused"  # the socket sees the same state
    r = _rig("resume", "--pid", p.pid, env=env)  # the CLI, through the socket
    assert r.returncode == 0 and "running" in r.stdout, r.stdout + r.stderr
    assert p.wait(timeout=60) is not None
    reader.join(timeout=10)
    text = "".join(lines)
    assert p.returncode == 0, text
    assert not sock.exists()
    tr = read_trial(out, channel="raw")
    ev = {e["kind"]: e for e in tr.events if e["kind"] in ("pause", "resume", "runup_done")}
    assert set(ev) == {"pause", "resume", "runup_done"}, [e["kind"] for e in tr.events]
    assert ev["pause"]["t_s"] == pytest.approx(1.0, abs=0.01)  # the stub's start: the next safe point
    held = ev["resume"]["t_s"] - ev["pause"]["t_s"]
    assert held > 1.0
    stub = [e for e in tr.events if e["kind"] == "segment_start" and e.get("label") == "stub"]
    assert stub and stub[0]["t_s"] == pytest.approx(ev["runup_done"]["t_s"], abs=0.01)  # the plan moved on
    from rig.kinematics import pause_intervals

    assert pause_intervals(tr.events) == [(ev["pause"]["t_s"], ev["resume"]["t_s"])]
    assert tr.time_s[-1] == pytest.approx(held + 3.0 + 0.5, abs=1.0)
