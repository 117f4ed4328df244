"""Fault injection through the real hardware path: `rig run RECIPE --hardware PROFILE` in a subprocess
against the emulated rig (one emulator process for the module, its own CAN channel), one test per fault.

Each test asserts the trip or the event (in the finished, readable MCAP), the safe valve state seen from
the valve emulator (disabled, spool 0) and, where a log can exist, that it reads back. Outcomes only,
no latencies (the machine is shared): the latencies are measured in docs/hardware.md.
"""

from __future__ import annotations

import contextlib
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

from drivers.config import hardware_of_profile
from drivers.emulators.valve_controller import send_foreign, send_malformed
from rig.config.profile import load_profile
from rig.config.recipe import compile_recipe, load_recipe
from rig.hardware.emulated import start_emulator_process
from rig.hardware.safety import latch_path
from rig.log import read_trial

pytestmark = pytest.mark.slow

def _emulated_env(tmp: Path, private_profile, short_recipe) -> SimpleNamespace:
    """A private profile, the fault recipe and an emulated rig in its own process (stop ``.emu``).

    The recipe (about 5 s): a hold, a 30 µm run-in stub each way at 20 µm/s (motion for the checks), a hold."""
    prof = private_profile(tmp, autostart=False)
    profile = load_profile(prof)
    recipe = tmp / "faults.yaml"
    recipe.write_text(short_recipe("faults"))
    plan = compile_recipe(load_recipe(recipe), profile)
    emu = start_emulator_process(hardware_of_profile(profile), profile, lubricant="boundary", seed=5,
                                 private=False)
    return SimpleNamespace(tmp=tmp, prof=prof, recipe=recipe, emu=emu, x0=float(plan.x_ref_um[0]),
                           channel=emu.hw.valve.channel, node=emu.hw.valve.node_id)


@pytest.fixture(scope="module")
def env(tmp_path_factory, private_profile, short_recipe):
    e = _emulated_env(tmp_path_factory.mktemp("faults"), private_profile, short_recipe)
    yield e
    e.emu.stop()


FAULTS = (("valve", "fault"), ("valve", "silent"), ("valve", "ignore_setpoints"), ("valve", "stuck"),
          ("loadcells", "slow_s"), ("loadcells", "nan_friction"), ("loadcells", "inf_normal_1"),
          ("lvdt", "drop_every"), ("lvdt", "garbage_every"), ("lvdt", "corrupt_every"))
SAFETY_FAULTS = (("safety", "estop"), ("safety", "pressure_lost"))


def _start(env, out: Path, preexec_fn=None) -> subprocess.Popen:
    for dev, fault in FAULTS + SAFETY_FAULTS:
        env.emu.inject(dev, fault, None)
    latch_path(env.emu.hw.safety).unlink(missing_ok=True)  # a failed test's latch must not refuse the next
    env.emu.reset_plant(env.x0)
    return subprocess.Popen([sys.executable, "-m", "rig.cli", "run", str(env.recipe), "--hardware", str(env.prof),
                             "--out", str(out), "-q"], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, preexec_fn=preexec_fn)


def _wait_running(env, p, ticks: int = 700, timeout_s: float = 60.0) -> int:
    """Until the loop has sent ``ticks`` set-points of this run to the valve (it is following); returns
    the valve's set-point count at the start (the run's tick k is about ``n_setpoints - n0``)."""
    n0 = env.emu.stats()["n_setpoints"]
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if p.poll() is not None:
            raise AssertionError(f"rig exited early ({p.returncode}):\n{p.stdout.read()}")
        if env.emu.stats()["n_setpoints"] - n0 >= ticks:
            return n0
        time.sleep(0.02)
    raise AssertionError("the loop did not start")


def _finish(p, timeout_s: float = 60.0) -> str:
    try:
        return p.communicate(timeout=timeout_s)[0]
    except subprocess.TimeoutExpired:
        p.kill()
        raise AssertionError("rig run hung") from None


def _recovered_s(out: Path, rec: Path) -> float:
    """`rig recover OUT --out REC` (exit 0), then the trial seconds of raw data it kept."""
    r = subprocess.run([sys.executable, "-m", "rig.cli", "recover", str(out), "--out", str(rec)], cwd=REPO,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    return float(read_trial(rec, channel="raw").time_s[-1])


def _safe_valve(env, timeout_s: float = 3.0) -> dict:
    t_end = time.monotonic() + timeout_s
    while True:
        st = env.emu.stats()
        if not st["valve_enabled"] and st["valve_output"] == 0.0:
            return st
        if time.monotonic() > t_end:
            raise AssertionError(f"valve not safe (disabled, spool 0): {st}")
        time.sleep(0.02)


def _trip(out: Path, names: set[str]) -> tuple[dict, object]:
    tr = read_trial(out, channel="raw")  # finished: readable without recovery
    trips = [e for e in tr.events if e["kind"] == "interlock"]
    assert trips, [e["kind"] for e in tr.events]
    assert trips[0]["name"] in names, trips[0]
    assert tr.valve_cmd[-1] == 0.0  # the last logged tick is nulled
    assert any(e["kind"] == "trial_failed" for e in tr.events)
    return trips[0], tr


def _run_fault(env, name: str, inject, names: set[str]) -> tuple[dict, object, str]:
    out = env.tmp / f"{name}.mcap"
    p = _start(env, out)
    n0 = _wait_running(env, p)
    k_inject = env.emu.stats()["n_setpoints"] - n0
    inject()
    text = _finish(p)
    assert p.returncode == 1, text
    assert "INTERLOCK" in text, text
    _safe_valve(env)
    trip, tr = _trip(out, names)
    # for docs/hardware.md (pytest -s): ticks from the injection to the trip (± the few set-points of start())
    print(f"\nFAULT {name}: trip {trip['name']} {round(trip['t_s'] * 1000) - k_inject} ticks after the injection")
    return trip, tr, text


@pytest.mark.parametrize("device,fault,value,names", [
    ("loadcells", "nan_friction", True, {"non_finite"}),
    ("loadcells", "inf_normal_1", True, {"non_finite"}),
    ("valve", "ignore_setpoints", True, {"valve_dither"}),
    ("valve", "stuck", True, {"valve_dither"}),
    ("loadcells", "slow_s", 0.0015, {"frame_loss"}),
    ("lvdt", "drop_every", 2, {"frame_loss"}),
    ("lvdt", "garbage_every", 2, {"stream_garbage"}),
    ("lvdt", "corrupt_every", 2, {"serial_checksum_errors"}),
])
def test_device_fault(env, device, fault, value, names):
    trip, tr, _ = _run_fault(env, f"{device}-{fault}", lambda: env.emu.inject(device, fault, value), names)
    if trip["name"] == "non_finite":
        assert trip["values"]["channel"] == ("friction_N" if fault == "nan_friction" else "normal_1_N")
        assert "load-cell conditioner" in trip["message"]


@pytest.mark.parametrize("kind", ["rpdo", "status", "malformed"])
def test_foreign_and_malformed_can_frames(env, kind):
    def inject():
        if kind == "malformed":
            send_malformed(env.channel, env.node)
        else:
            send_foreign(env.channel, kind, env.node)
    trip, _, _ = _run_fault(env, f"can-{kind}", inject, {"can_foreign_frames", "can_malformed_frames",
                                                          "valve_rejected_frames", "valve_fault",
                                                          "valve_counter"})
    assert "canopen-rig_unix:" in trip["message"]


def _rig(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig.cli", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=90)


@pytest.mark.parametrize("fault,name", [("estop", "estop"), ("pressure_lost", "hydraulic_pressure")])
def test_the_safety_chain_trips_latches_and_resets(env, fault, name):
    """An e-stop (or a loss of hydraulic pressure) mid-trial: the valve nulled and disabled from the trip's
    tick, the amplifier's enable off, a readable log, exit 1; the next `rig run` refuses, naming the chain,
    and `rig reset` clears the latch only once the input is healthy again."""
    trip, tr, text = _run_fault(env, f"safety-{fault}", lambda: env.emu.inject("safety", fault, True), {name})
    k = round(trip["t_s"] * 1000)
    assert np.all(tr.valve_cmd[k:] == 0.0)  # nulled from the trip's own tick on
    assert not env.emu.stats()["safety"]["amplifier_enabled"]
    events = [e for e in tr.events if e["kind"] == "stop_state" and e.get("state") == "safe"]
    assert events and "enable output off True" in events[0]["detail"], tr.events[-4:]
    # latched: the next run refuses, naming the chain (once: the latch is the chain's, whatever tripped it);
    # a reset with the input still unhealthy refuses too
    if fault == "estop":
        r = _rig("run", env.recipe, "--hardware", env.prof, "--out", env.tmp / f"refused-{fault}.mcap", "-q")
        assert r.returncode == 1 and "safety chain" in r.stdout + r.stderr and "latched" in r.stdout + r.stderr, \
            r.stdout + r.stderr
    else:
        assert "hydraulic_pressure" in latch_path(env.emu.hw.safety).read_text()
    r = _rig("reset", "--hardware", env.prof)
    assert r.returncode == 1 and "not reset" in r.stderr, r.stdout + r.stderr
    env.emu.inject("safety", fault, None)
    r = _rig("reset", "--hardware", env.prof)
    assert r.returncode == 0 and "latch cleared" in r.stdout, r.stdout + r.stderr
    assert not latch_path(env.emu.hw.safety).exists()


def test_sigstop_of_the_loop(env, find_child):
    """A short stall is an event and the reference resumes where it was; a long one trips."""
    out = env.tmp / "sigstop.mcap"
    p = _start(env, out)
    _wait_running(env, p)
    loop = find_child(p.pid, "rig-rt-loop")
    t0 = time.monotonic()
    os.kill(loop, signal.SIGSTOP)
    time.sleep(0.1)  # below stall_trip_s (0.25 s in the emulated profile): an event
    os.kill(loop, signal.SIGCONT)
    short_s = time.monotonic() - t0  # the test itself may be descheduled: what it really was
    time.sleep(0.5)
    with contextlib.suppress(ProcessLookupError):  # (gone if the short stall was a long one)
        os.kill(loop, signal.SIGSTOP)
        time.sleep(0.6)  # above it: a trip
        os.kill(loop, signal.SIGCONT)
    text = _finish(p)
    assert p.returncode == 1, text
    _safe_valve(env)
    trip, tr = _trip(out, {"loop_stall", "valve_watchdog", "valve_heartbeat", "valve_fault"})
    # the valve's confirmed safe state after the stall is in the log (its heartbeat: it left OPERATIONAL
    # during the stall, so its last status PDO, from before, is not its state)
    safe = [e for e in tr.events if e["kind"] == "stop_state" and e.get("state") == "safe"]
    assert safe and "enabled False" in safe[0]["detail"] and "confirmed True" in safe[0]["detail"], tr.events[-5:]
    stalls = [e for e in tr.events if e["kind"] == "stall" and e["gap_s"] > 0.08]
    assert stalls and stalls[-1]["gap_s"] >= 0.25, (trip, stalls)
    if short_s < 0.2:
        assert len(stalls) >= 2 and stalls[0]["gap_s"] < 0.25 and stalls[0]["t_s"] < trip["t_s"], stalls
    # the reference never jumps: time is held across the stalls (no gaps in t_s, steps <= v dt)
    t, ref = tr.time_s, tr.position_ref_um
    assert np.allclose(np.diff(t), 1e-3, atol=1e-9)
    assert np.max(np.abs(np.diff(ref))) < 0.05  # 20 µm/s x 1 ms = 0.02 µm


@contextlib.contextmanager
def _small_disk(tmp: Path, size_kb: int):
    """A tmpfs of ``size_kb`` (root may mount one); else None (the caller limits the file size)."""
    mnt = tmp / f"disk{size_kb}"
    mnt.mkdir()
    ok = shutil.which("mount") and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs",
                                                   str(mnt)], capture_output=True).returncode == 0
    try:
        yield mnt if ok else None
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_disk_full_ends_the_trial_safely(env):
    # the compact log (rig.columns.v2) writes ~12 kB per second of trial after ~30 kB of header,
    # recipe and profile: 64 kB fills a few seconds into the smoke trial
    with _small_disk(env.tmp, 64) as mnt:
        if mnt is not None:
            out, limit = mnt / "full.mcap", None
        else:  # no mount allowed: the kernel refuses writes beyond RLIMIT_FSIZE (EFBIG) instead of ENOSPC
            out, limit = env.tmp / "full.mcap", 64 * 1024
        pre = (lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))) if limit else None
        p = _start(env, out, preexec_fn=pre)
        t0 = time.monotonic()
        text = _finish(p, timeout_s=60)
        assert p.returncode == 1, text
        assert time.monotonic() - t0 < 45
        assert "No space left on device" in text or "File too large" in text, text
        st = _safe_valve(env)
        assert st["valve"]["nmt"] in ("PRE-OPERATIONAL", "OPERATIONAL")
        assert not st["valve_watchdog"]  # nulled by the loop (told by the session), not by the valve's watchdog
        # what reached the disk before it filled reads back after `rig recover`
        assert _recovered_s(out, env.tmp / "full-recovered.mcap") > 0.5


def test_kill9_of_the_logger(env):
    """The loop's parent (the logger) dies: the loop nulls and disables the valve by itself."""
    out = env.tmp / "kill-logger.mcap"
    p = _start(env, out)
    _wait_running(env, p, ticks=1500)
    t_kill = time.monotonic()
    os.kill(p.pid, signal.SIGKILL)
    st = _safe_valve(env)
    print(f"\nFAULT kill -9 logger: valve disabled {(st['t_valve_disabled'] - t_kill) * 1e3:.1f} ms after the kill")
    p.wait(10)
    assert not st["valve_watchdog"]  # nulled by the loop's safe stop, not by the valve's watchdog
    assert _recovered_s(out, env.tmp / "kill-logger-recovered.mcap") > 0.3


def test_kill9_of_the_loop(env, find_child):
    """The loop dies: the valve nulls on its own (set-point watchdog, host heartbeat); the log is finished."""
    out = env.tmp / "kill-loop.mcap"
    p = _start(env, out)
    _wait_running(env, p)
    os.kill(find_child(p.pid, "rig-rt-loop"), signal.SIGKILL)
    text = _finish(p)
    assert p.returncode == 1 and "loop process died" in text, text
    st = _safe_valve(env)
    assert st["valve_watchdog"] or st["valve"]["latched"]
    tr = read_trial(out, channel="raw")
    assert any(e["kind"] == "loop_died" for e in tr.events)



@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_or_sighup_of_rig_run_stops_safely(env, sig):
    """`kill` (SIGTERM) or the operator's terminal going away (SIGHUP, an SSH session dropped): an
    operator's stop, as Ctrl-C: the valve nulled and disabled, the log finished and readable, exit
    130. SIGHUP used to kill `rig run` outright: no footer on the MCAP, the loop stopped only by
    its logger-died check."""
    out = env.tmp / f"{sig.name}.mcap"
    p = _start(env, out)
    _wait_running(env, p)
    os.kill(p.pid, sig)
    text = _finish(p)
    assert p.returncode == 130, text
    assert f"operator abort ({sig.name})" in text, text
    _safe_valve(env)
    tr = read_trial(out, channel="raw")  # finished: readable without recovery
    assert tr.metadata["status"] == "interrupted"
    assert tr.valve_cmd[-1] == 0.0


def test_terminal_hangup_stops_safely(env):
    """`rig run` on a real terminal (a pty) that goes away (its master closed: the kernel sends SIGHUP
    and every later write to it fails with EIO): the stop completes, valve safe, log finished, exit
    130. It exited 1 with an MCAP cut mid-record: the stop's own messages failed with EIO."""
    import pty
    import select

    for dev, fault in FAULTS:
        env.emu.inject(dev, fault, None)
    env.emu.reset_plant(env.x0)
    out = env.tmp / "hangup.mcap"
    n0 = env.emu.stats()["n_setpoints"]
    pid, fd = pty.fork()
    if pid == 0:  # the child: rig run with the pty as its controlling terminal
        try:
            os.chdir(REPO)
            os.execv(sys.executable, [sys.executable, "-m", "rig.cli", "run", str(env.recipe), "--hardware",
                                      str(env.prof), "--out", str(out)])
        finally:
            os._exit(127)
    try:
        t_end = time.monotonic() + 60
        while env.emu.stats()["n_setpoints"] - n0 < 700 and time.monotonic() < t_end:
            if select.select([fd], [], [], 0.02)[0]:
                try:
                    os.read(fd, 65536)  # what the operator would have seen
                except OSError:
                    break
        assert env.emu.stats()["n_setpoints"] - n0 >= 700, "the loop did not start"
    finally:
        os.close(fd)  # the terminal goes away
    t_end = time.monotonic() + 60
    while (w := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > t_end:
            os.kill(pid, signal.SIGKILL)
            raise AssertionError("rig run hung after the hangup")
        time.sleep(0.05)
    assert os.waitstatus_to_exitcode(w[1]) == 130
    _safe_valve(env)
    tr = read_trial(out, channel="raw")  # finished: readable without recovery
    assert tr.metadata["status"] == "interrupted" and tr.valve_cmd[-1] == 0.0


def test_kill9_of_the_load_cell_conditioner(tmp_path, private_profile, short_recipe):
    """The conditioner's process dies (its Modbus TCP connection closed by the kernel): a fault no
    injection models. The loop trips at once on the lost device, nulls and disables the valve, and
    never goes on with the last forces as if they were new (it did: the trial completed, exit 0,
    on frozen forces). Its own emulator: the module's one keeps its Modbus server."""
    env2 = _emulated_env(tmp_path, private_profile, short_recipe)
    emu = env2.emu
    try:
        out = tmp_path / "kill-conditioner.mcap"
        p = _start(env2, out)
        _wait_running(env2, p)
        kids = [int(k) for k in subprocess.run(["pgrep", "-P", str(emu.proc.pid)], capture_output=True,
                                               text=True).stdout.split()]
        kids = [k for k in kids if Path(f"/proc/{k}/comm").read_text().strip() != "rig-emulator-io"]
        assert len(kids) == 1, kids  # the Modbus server's process (the emulator's other child: the I/O module)
        os.kill(kids[0], signal.SIGKILL)
        text = _finish(p)
        assert p.returncode == 1, text
        assert "device_lost" in text and "load-cell conditioner" in text, text
        _safe_valve(env2)
        trip, tr = _trip(out, {"device_lost"})
        assert "load-cell conditioner" in trip["message"]
        assert tr.time_s[-1] < 3.0  # the 5 s trial ended at the trip
    finally:
        emu.stop()
