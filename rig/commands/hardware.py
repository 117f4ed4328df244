"""Hardware commands: ``rig devices check``, ``rig emulate``, ``rig reset``, ``rig pause`` / ``rig resume``,
``rig loop-bench``.

``rig devices check --hardware PROFILE [--start-emulators]`` connects to every
device of the profile's ``hardware`` section, reads each once and says what
answered (and where), the safety chain's inputs, outputs and latch included.
``rig reset --hardware PROFILE`` clears the safety chain's latch once its inputs
read healthy. ``rig pause`` / ``rig resume`` talk to the running ``rig run`` of this
user through its socket (:mod:`rig.session.pausing`). ``rig emulate --hardware PROFILE`` serves the emulated devices in
the foreground until Ctrl-C. ``rig loop-bench`` runs the 1 kHz loop against
the emulators holding position and prints a LinuxCNC-style latency report.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import typer
from rich.table import Table

from rig.commands.common import JSON_HELP, Lubricant, console, err_console, fail, json_to_stdout, write_json

DEFAULT_EMULATED = Path("config/rigs/emulated.yaml")


def _fail(msg: str, code: int = 2):
    fail(msg, code)


def _load(profile_path: Path):
    from drivers.config import HardwareConfigError, hardware_of_profile
    from rig.config.profile import ProfileError, load_profile

    try:
        profile = load_profile(profile_path)
    except ProfileError as exc:
        _fail(str(exc))
    try:
        hw = hardware_of_profile(profile, where=str(profile_path))
    except HardwareConfigError as exc:
        _fail(str(exc))
    return profile, hw


DEVICE_LABELS = {"loadcells": "load cells", "lvdt": "LVDT", "valve": "servovalve", "safety": "safety chain"}


def _reading(rig, name: str) -> str:
    if name == "loadcells":
        f, n1, n2 = rig.forces.forces_N
        return (f"friction {f:.3f} N, normal 1 {n1:.3f} N, normal 2 {n2:.3f} N, "
                f"counter {rig.forces.counter}, status 0x{rig.forces.status:04x}")
    if name == "lvdt":
        lv = rig.position
        return f"position {lv.position_um:.3f} µm, seq {lv.seq}, status 0x{lv.status:02x}"
    if name == "safety":
        from rig.hardware.safety import latched_message

        latched = latched_message(rig.safety.cfg)
        return rig.safety.describe() + (f"; LATCHED: {latched}" if latched else "; not latched")
    va = rig.valve.final_state()
    return f"status 0x{va['status_bits']:02x} (enabled {va['enabled']}), output {va['output']:+.4f}"


def check_devices(hw) -> list[dict]:
    """Connect to each device, wait for its first data, read it once; one row per device (never raises)."""
    from drivers.errors import DeviceError
    from rig.hardware.devices import build_devices, wait_for_data

    from drivers.safety_io import SafetyIO

    rig = build_devices(hw)
    rig.safety = SafetyIO(hw.safety) if hw.safety is not None else None  # read once, directly (no link)
    order = (rig.forces, rig.position, rig.valve) + ((rig.safety,) if rig.safety is not None else ())
    rows = []
    for dev in order:
        row = {"device": DEVICE_LABELS[dev.name], "address": dev.address}
        try:
            dev.connect()
            if dev is rig.safety:
                dev.poll(max(0.5, 4 * hw.valve.heartbeat_timeout_s))  # the inputs and the outputs read back
            else:
                wait_for_data([dev], max(0.5, 4 * hw.valve.heartbeat_timeout_s), time.monotonic)
            row.update(ok=True, reading=_reading(rig, dev.name))
        except DeviceError as exc:
            row.update(ok=False, reading=exc.message)
        finally:
            dev.close()
        rows.append(row)
    return rows


def devices_check(
    hardware: Path = typer.Option(..., "--hardware", metavar="PROFILE", help="Rig profile with a hardware section."),
    start_emulators: bool = typer.Option(False, "--start-emulators",
                                         help="Start the emulated devices first (rig.hardware.emulated)."),
    json_out: Optional[Path] = typer.Option(None, "--json", metavar="PATH", help=JSON_HELP),
):
    """Connect to every device, read each once, say what answered. Exit 1 if any did not."""
    profile, hw = _load(hardware)
    emu = None
    if start_emulators:
        from rig.hardware.emulated import EmulatorError, start_emulator_process

        try:
            emu = start_emulator_process(hw, profile)
        except EmulatorError as exc:
            _fail(str(exc), 1)
    try:
        rows = check_devices(emu.hw if emu is not None else hw)
    finally:
        if emu is not None:
            emu.stop()
    if json_out is not None:
        write_json(rows, json_out)
    if not json_to_stdout(json_out):
        tab = Table(title=f"devices of {hardware}")
        for col in ("device", "address", "answered", "reading"):
            tab.add_column(col, overflow="fold")
        for r in rows:
            tab.add_row(r["device"], r["address"], "[green]yes[/]" if r["ok"] else "[red]NO[/]", r["reading"])
        console.print(tab)
    if not all(r["ok"] for r in rows):
        raise typer.Exit(1)


def emulate(
    profile_path: Path = typer.Option(DEFAULT_EMULATED, "--hardware", metavar="PROFILE",
                                      help="Rig profile with a hardware section."),
    lubricant: Lubricant = typer.Option(Lubricant.boundary, "--lubricant", help="Friction of the simulated plant."),
    seconds: Optional[float] = typer.Option(None, "--seconds", min=0.0, help="Stop after this long (s; default: Ctrl-C)."),
):
    """Serve the emulated devices of PROFILE (Modbus, LVDT pty, CAN valve) until Ctrl-C."""
    import signal

    from rig.hardware.emulated import EmulatorError, EmulatorService, control_socket_path, start_emulator_process

    # Ctrl-C stops it whatever this process inherited: a parent that ignores SIGINT (a background job of a
    # script, a test runner whose libraries set it to SIG_IGN) makes Python leave it ignored, and the
    # emulators then served until --seconds ran out (the CI's test waited 60 s for a Ctrl-C, twice)
    signal.signal(signal.SIGINT, signal.default_int_handler)

    profile, hw = _load(profile_path)
    try:  # the profile's own channel and ports: `rig run` and `rig devices check` in other processes reach them
        emu = start_emulator_process(hw, profile, lubricant=lubricant.value, private=False)
    except EmulatorError as exc:
        _fail(str(exc), 1)
    try:
        service = EmulatorService(emu, control_socket_path(hw))
    except (EmulatorError, OSError) as exc:
        emu.stop()
        _fail(f"cannot serve the emulators' control socket: {exc}", 1)
    console.print(f"emulators up: {emu.hw.loadcells.address_text}; {emu.hw.lvdt.address_text}; "
                  f"{emu.hw.valve.address_text}; `rig run --hardware {profile_path}` and `rig devices check "
                  f"--hardware {profile_path}` in another terminal use them. Ctrl-C stops.", highlight=False)
    t0 = time.monotonic()
    try:
        while seconds is None or time.monotonic() - t0 < seconds:
            time.sleep(0.2)
            if not emu.proc.is_alive():
                _fail("the emulator process died", 1)
    except KeyboardInterrupt:
        pass
    finally:
        service.close()
        st = emu.stats() if emu.proc.is_alive() else {}
        emu.stop()
    console.print(f"stopped; plant steps {st.get('steps')}, Modbus requests {st.get('modbus_requests')}, "
                  f"LVDT frames {st.get('lvdt_sent')}", highlight=False)


def reset_command(
    hardware: Path = typer.Option(..., "--hardware", metavar="PROFILE", help="Rig profile with a hardware.safety "
                                                                           "section."),
):
    """Clear the safety chain's latch (after an e-stop or a pressure loss) once both inputs read healthy.
    Exit 1 (and the latch kept) while the e-stop is open or the pressure is lost."""
    from rig.hardware.safety import reset

    _profile, hw = _load(hardware)
    if hw.safety is None:
        _fail(f"{hardware}: the profile has no safety chain (hardware.safety); nothing to reset")
    ok, text = reset(hw.safety)
    if not ok:
        _fail(f"safety chain {hw.safety.address_text}: {text}", 1)
    console.print(f"safety chain {hw.safety.address_text}: {text}", highlight=False)


def _pause_cmd(command: str, pid: int | None) -> None:
    from rig.session.pausing import send

    if pid is not None and pid <= 0:
        _fail(f"--pid {pid}: a process id is a positive number")
    try:
        answer = send(command, pid)
    except (OSError, ValueError) as exc:
        _fail(f"rig {command}: {exc}", 1)
    if not answer.startswith("ok"):
        _fail(f"rig {command}: the run answered {answer!r}", 1)
    console.print(f"{command}: the run is {answer.split()[-1]}"
                  + (" (it holds at the plan's next safe point)" if command == "pause" else ""), highlight=False)


PID_OPTION = typer.Option(None, "--pid", help="The `rig run` to talk to (default: the only one of this user).")


def pause_command(pid: Optional[int] = PID_OPTION):
    """Pause the running trial: it holds the position at the plan's next safe point (as SIGUSR1 to `rig run`)."""
    _pause_cmd("pause", pid)


def resume_command(pid: Optional[int] = PID_OPTION):
    """Resume the paused trial: a run-up of 5 L at the segment's velocity, then the plan goes on."""
    _pause_cmd("resume", pid)


def loop_bench(seconds: float = 60.0, profile_path: Path = DEFAULT_EMULATED, out_json: Path | None = None) -> dict:
    """Run the loop holding position against the (emulated) devices; return the final statistics.

    The trial session runs on the hardware backend and logs to memory (events and statistics only).
    Raises :class:`LoopBenchFailed` (its message for the operator) if the emulators did not start or
    the loop stopped early (a trip, a lost device).
    """
    import numpy as np

    from drivers.config import hardware_of_profile
    from rig.config.profile import load_profile
    from rig.session import MemoryLog, run_trial
    from rig.session.hardware import HardwareBackend

    profile = load_profile(profile_path)
    hw = hardware_of_profile(profile)
    rate = float(profile.loop.rate_hz)
    x = np.full(int(round(seconds * rate)), float(profile.stroke.home_um))
    plan = SimpleNamespace(x_ref_um=x, loop_rate_hz=rate, duration_s=(x.size - 1) / rate, n_ticks=x.size,
                           events=[])
    emu = None
    if hw.emulators.autostart:
        from rig.hardware.emulated import EmulatorError, start_emulator_process

        try:
            emu = start_emulator_process(hw, profile, lubricant="boundary")
        except EmulatorError as exc:
            raise LoopBenchFailed(f"the emulated devices of {profile_path} did not start: {exc}") from None
    from rig.hardware.timing import StallProbe, attribute_skips

    load_before = os.getloadavg()
    t0 = time.time()
    log = MemoryLog(keep_blocks=False, rate_hz=rate)
    # a bare sleeper beside the loop: a skipped cycle while it stalled too is the VM's, else the loop's
    probe = StallProbe(1.0 / rate, 2.0 / rate, hw.realtime.priority if hw.realtime.sched_fifo else 0,
                       hw.realtime.cpu).start()
    try:
        result = run_trial(plan, HardwareBackend(hw, profile, emulator=emu), log)
        emu_stats = emu.stats() if emu is not None else {}
    finally:
        gaps = probe.stop()
        if emu is not None:
            emu.stop()
    if result.status != "completed":
        raise LoopBenchFailed(f"the loop stopped: {result.reason}")
    summary = result.summary
    res = dict(summary["timing"])
    res["skipped_attribution"] = {**attribute_skips(summary.get("skips", []), gaps, 1.0 / rate),
                                  "probe_stalls": len(gaps)}
    res["emulator"] = {k: emu_stats.get(k) for k in ("steps", "lock_steps", "free_steps", "max_gap_s",
                                                     "gaps_over_5ms", "modbus_requests")}
    res.update(seconds=seconds, loadavg_before=load_before, loadavg_after=os.getloadavg(),
               started_utc=time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t0)),
               realtime=summary.get("realtime"), cpus=os.cpu_count(), emulated=hw.emulators.autostart,
               devices=summary.get("devices"), read_max_us_by_device=summary.get("read_max_us_by_device"),
               stalls=[(e["wake_monotonic_s"], e["gap_s"], e["skipped"]) for e in log.events
                       if e["kind"] == "stall" and "wake_monotonic_s" in e])  # CLOCK_MONOTONIC: across processes
    if out_json:
        Path(out_json).write_text(json.dumps(res, indent=2, default=str))
    return res


class LoopBenchFailed(RuntimeError):
    """The loop stopped before the end of the bench (the message says why)."""


def loop_bench_command(
    seconds: float = typer.Option(60.0, "--seconds", min=0.01, max=86400.0, help="How long to run the loop (s)."),
    hardware: Path = typer.Option(DEFAULT_EMULATED, "--hardware", metavar="PROFILE",
                                  help="Rig profile (default: the emulated rig; its emulators are started)."),
    out_json: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (the figures)"),
):
    """Run the 1 kHz loop holding position against the devices; print jitter, lateness, misses."""
    from rig.hardware.timing import format_stats

    _load(hardware)
    try:
        res = loop_bench(seconds, hardware)
    except LoopBenchFailed as exc:
        _fail(str(exc), 1)
    if out_json is not None:
        write_json(res, out_json)
    out = err_console if json_to_stdout(out_json) else console
    out.print(format_stats(res, f"loop-bench {seconds:g} s"), highlight=False)
    rt = res.get("realtime") or {}
    out.print(f"  scheduling {rt.get('sched')} (priority {rt.get('priority')}) {rt.get('note') or ''}; "
                  f"load average before {res['loadavg_before'][0]:.2f}, after {res['loadavg_after'][0]:.2f} "
                  f"on {res['cpus']} CPUs", highlight=False)
    targets = {"execution p50 < 150 µs": res.get("exec_p50_us", 1e9) < 150,
               "execution p99 < 500 µs": res.get("exec_p99_us", 1e9) < 500,
               "lateness p99 < 100 µs": res.get("late_p99_us", 1e9) < 100,
               "0 skipped cycles of the loop's own": (res.get("skipped_attribution") or {}).get("loop_cycles", 1) == 0}
    em = res.get("emulator") or {}
    if em.get("steps"):
        out.print(f"  emulator: {em['steps']} plant steps ({em['lock_steps']} on setpoints), longest gap "
                      f"{1e3 * (em['max_gap_s'] or 0):.1f} ms, {em['gaps_over_5ms']} gaps over 5 ms", highlight=False)
    at = res.get("skipped_attribution") or {}
    if at:
        out.print(f"  skipped cycles: {at['vm_cycles']} the VM's (the probe stalled too, {at['vm_episodes']} "
                  f"episodes), {at['loop_cycles']} the loop's ({at['loop_episodes']} episodes); the probe "
                  f"stalled {at['probe_stalls']} times over 2 ms", highlight=False)
    out.print("  targets: " + "; ".join(f"{k} {'[green]met[/]' if ok else '[yellow]not met[/]'}"
                                        for k, ok in targets.items()))
    sys.stdout.flush()


def register(app: typer.Typer) -> None:
    devices_app = typer.Typer(help="The rig's devices (load cells, LVDT, servovalve).", no_args_is_help=True)
    devices_app.command("check")(devices_check)
    app.add_typer(devices_app, name="devices")
    app.command("emulate")(emulate)
    app.command("reset")(reset_command)
    app.command("pause")(pause_command)
    app.command("resume")(resume_command)
    app.command("loop-bench")(loop_bench_command)
