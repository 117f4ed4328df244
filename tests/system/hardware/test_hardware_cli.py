"""`rig devices check` and `rig loop-bench` through the CLI."""

from __future__ import annotations

from pathlib import Path
import json
import subprocess
import sys
import time

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install


def _rig(*args, timeout=90):
    return subprocess.run([sys.executable, "-m", "rig.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def test_devices_check_with_and_without_emulators(tmp_path, private_profile):
    prof = private_profile(tmp_path)
    r = _rig("devices", "check", "--hardware", prof, "--start-emulators", "--json", "-")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = json.loads(r.stdout)
    assert [x["device"] for x in rows] == ["load cells", "LVDT", "servovalve", "safety chain"]
    assert all(x["ok"] for x in rows)
    assert "e-stop closed (healthy), pressure OK, enable output off; not latched" in rows[3]["reading"]
    assert "normal 1 " in rows[0]["reading"] and "position" in rows[1]["reading"]
    # nothing listening: each device named with its address, exit 1
    r = _rig("devices", "check", "--hardware", prof, "--json", "-")
    assert r.returncode == 1
    rows = json.loads(r.stdout)
    assert not any(x["ok"] for x in rows)
    assert "modbus-tcp://127.0.0.1:" in rows[0]["address"] and "refused" in rows[0]["reading"]
    assert str(tmp_path / "lvdt") in rows[1]["reading"]


def test_rig_emulate_serves_devices_check_and_run_in_other_processes(tmp_path, private_profile):
    """`rig emulate` in one terminal: `rig devices check` in another finds all three devices (the valve
    too: the profile's own CAN channel), and a `rig run` there homes the plant through its socket."""
    import signal

    from drivers.config import hardware_of_profile
    from rig.config.profile import load_profile
    from rig.hardware.emulated import RemoteEmulator

    prof = private_profile(tmp_path)
    # its output goes to a file, not a pipe: the test waits for `rig emulate` itself to exit, not for every
    # process that inherited its stdout (the emulator's own children) to close a pipe
    log = tmp_path / "emulate.log"
    with open(log, "w") as fh:
        # started with SIGINT ignored, as a background job or a test runner may leave it: Ctrl-C still stops it
        p = subprocess.Popen([sys.executable, "-m", "rig.cli", "emulate", "--hardware", str(prof), "--seconds",
                              "120"], cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, text=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        t_end = time.monotonic() + 60
        while "emulators up" not in log.read_text() and p.poll() is None and time.monotonic() < t_end:
            time.sleep(0.1)
        assert "emulators up" in log.read_text(), log.read_text()
        r = _rig("devices", "check", "--hardware", prof, "--json", "-")
        assert r.returncode == 0, r.stdout + r.stderr
        assert [x["ok"] for x in json.loads(r.stdout)] == [True, True, True, True]
        remote = RemoteEmulator.connect(hardware_of_profile(load_profile(prof)))
        assert remote is not None and remote.reset_plant(500.0)["ok"]
    finally:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            raise AssertionError("rig emulate did not stop within 60 s of Ctrl-C:\n" + log.read_text()) from None
    out = log.read_text()
    assert p.returncode == 0, out
    assert not (tmp_path / "emulate.sock").exists()


def test_devices_check_bad_profile(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text((REPO / "config/rigs/sim.yaml").read_text())  # hardware: null
    r = _rig("devices", "check", "--hardware", bad)
    assert r.returncode == 2
    assert "no 'hardware' section" in r.stderr


def test_loop_bench_short(tmp_path, private_profile):
    prof = private_profile(tmp_path)
    out = tmp_path / "bench.json"
    r = _rig("loop-bench", "--seconds", 1, "--hardware", prof, "--json", out)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "jitter" in r.stdout and "late > 100 µs" in r.stdout
    res = json.loads(out.read_text())
    assert res["n"] + res["skipped"] >= 995 and res["late_p50_us"] < 1000
    assert res["realtime"]["sched"] in ("SCHED_FIFO", "SCHED_OTHER")
    at = res["skipped_attribution"]
    assert at["vm_cycles"] + at["loop_cycles"] == res["skipped"] and "skipped cycles:" in r.stdout


def test_loop_bench_when_the_emulators_cannot_start(tmp_path, private_profile):
    """The emulated conditioner's port is taken: one clear error naming it, exit 1, no traceback."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        prof = private_profile(tmp_path, loadcells={"port": port})
        r = _rig("loop-bench", "--seconds", 1, "--hardware", prof)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr, r.stderr
    assert f"did not start: the Modbus server at modbus-tcp://127.0.0.1:{port}" in r.stderr, r.stderr
    assert r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) <= 2, r.stderr


def test_run_without_devices_names_the_device(tmp_path, private_profile):
    prof = private_profile(tmp_path, autostart=False)
    r = _rig("run", REPO / "config/recipes/smoke.yaml", "--hardware", prof, "--out", tmp_path / "x.mcap", "-q")
    assert r.returncode == 1
    assert "load-cell conditioner at modbus-tcp://127.0.0.1:" in r.stdout + r.stderr
