"""``rig calibrate tare|shunt|verify --hardware PROFILE``: the force channels' calibration checks (issue 21).

* ``tare`` zeroes the unloaded channels (the mean of their readings becomes each channel's
  ``tare_N``; the values are printed and recorded in ``cal/tare-<date>.json`` to copy into the profile).
* ``shunt`` reads each bridge's shunt-calibration register and compares it with the
  ``shunt_reference_N`` of the channel's calibration record (ASTM E4 / ISO 7500-1 practice);
  ``cal/shunt-<date>.json``; exit 1 when one drifted beyond its tolerance.
* ``verify`` steps through reference loads the operator applies (dead weights, a reference cell;
  on the emulated rig its reference-load input), reads the channel at each, and writes
  ``cal/<serial>-<date>.json``: the error at each point and pass/fail for the record's class.

The checks themselves are :mod:`drivers.calibration`; the records are the profile's
``hardware.loadcells.<channel>.calibration`` (:class:`drivers.config.CalibrationRecord`).
Exit status: 0 passed; 1 a check failed or a device did not answer; 2 bad input.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from rig.commands.common import EXIT_FAILED, console, fail, warn

calibrate_app = typer.Typer(help="Calibration of the force channels: tare, shunt check, verification against "
                                 "reference loads (records in the profile's hardware section).",
                            no_args_is_help=True)

CHANNELS = ("friction", "normal_1", "normal_2")
_HW = typer.Option(..., "--hardware", metavar="PROFILE", help="Rig profile with a hardware section.")
_EMU = typer.Option(None, "--start-emulators/--no-start-emulators",
                    help="Start the emulated devices first (default: the profile's emulators.autostart).")
_CAL_DIR = typer.Option(Path("cal"), "--cal-dir", metavar="DIR", help="Where the records are written.")


class _Devices:
    """The load-cell conditioner of a profile (and the emulators when asked), connected; closes both."""

    def __init__(self, profile_path: Path, start_emulators: Optional[bool]):
        from drivers.config import HardwareConfigError, hardware_of_profile
        from rig.config.profile import ProfileError, load_profile

        try:
            self.profile = load_profile(profile_path)
            self.hw = hardware_of_profile(self.profile, where=str(profile_path))
        except (ProfileError, HardwareConfigError) as exc:
            fail(str(exc))
        self.emu = None
        self.reader = None
        if start_emulators if start_emulators is not None else self.hw.emulators.autostart:
            from rig.hardware.emulated import EmulatorError, start_emulator_process

            try:
                self.emu = start_emulator_process(self.hw, self.profile)
            except EmulatorError as exc:
                fail(str(exc), EXIT_FAILED)

    def __enter__(self):
        from drivers.errors import DeviceError
        from drivers.loadcells import LoadCellReader

        hw = self.emu.hw if self.emu is not None else self.hw
        self.reader = LoadCellReader(hw.loadcells)
        try:
            self.reader.connect()
        except DeviceError as exc:
            self.__exit__()
            fail(str(exc), EXIT_FAILED)
        return self

    def __exit__(self, *exc) -> None:
        if self.reader is not None:
            self.reader.close()
        if self.emu is not None:
            self.emu.stop()

    def records(self) -> dict:
        from drivers.config import calibration_records

        return calibration_records(self.hw)


def shunt_rows(hw, records=None) -> list[dict]:
    """Connect to ``hw``'s conditioner, read every shunt register, compare (:func:`drivers.calibration.shunt_check`).
    Raises DeviceError when the conditioner does not answer."""
    from drivers.calibration import shunt_check
    from drivers.config import calibration_records
    from drivers.loadcells import LoadCellReader

    reader = LoadCellReader(hw.loadcells)
    reader.connect()
    try:
        readings = reader.read_shunt()
    finally:
        reader.close()
    return shunt_check(readings, records if records is not None else calibration_records(hw))


def shunt_configured(hw) -> bool:
    """Does any channel have a shunt register and a reference to compare it with?"""
    lc = hw.loadcells
    return any(getattr(lc, ch).shunt_address is not None and getattr(lc, ch).calibration is not None
               and getattr(lc, ch).calibration.shunt_reference_N for ch in CHANNELS)


def _record_path(cal_dir: Path, stem: str) -> Path:
    """``cal/<stem>-<date>.json``; a second record the same day gets the time too (records are never replaced)."""
    now = datetime.datetime.now(datetime.timezone.utc)
    p = cal_dir / f"{stem}-{now.date().isoformat()}.json"
    return p if not p.exists() else cal_dir / f"{stem}-{now.strftime('%Y-%m-%dT%H%M%SZ')}.json"


def _write_record(path: Path, doc: dict) -> None:
    from rig.data import atomic_write_text

    try:
        atomic_write_text(path, json.dumps(doc, indent=2, allow_nan=False, default=str) + "\n", overwrite=False)
    except OSError as exc:
        fail(f"cannot write {path}: {exc.strerror or exc}", EXIT_FAILED)
    console.print(f"wrote {path}", markup=False)


def _mean_reading(reader, channel: int, n: int) -> float:
    import time

    total = 0.0
    for _ in range(n):
        total += reader.read()[channel]
        time.sleep(0.002)
    return total / n


@calibrate_app.command("tare")
def tare_cmd(hardware: Path = _HW, start_emulators: Optional[bool] = _EMU, cal_dir: Path = _CAL_DIR,
             samples: int = typer.Option(50, "--samples", min=1, max=100000, help="Readings averaged per channel.")):
    """Zero the unloaded channels: their mean reading becomes each channel's tare_N (unload them first)."""
    from drivers.errors import DeviceError

    with _Devices(hardware, start_emulators) as dev:
        try:
            tares = dev.reader.tare(samples)
        except DeviceError as exc:
            fail(str(exc), EXIT_FAILED)
    tab = Table(title="tare (N): copy into the profile's hardware.loadcells.<channel>.tare_N")
    for c in ("channel", "tare_N"):
        tab.add_column(c)
    for ch, v in tares.items():
        tab.add_row(ch, f"{v:.4f}")
    console.print(tab)
    _write_record(_record_path(cal_dir, "tare"), {"kind": "tare", "profile": str(hardware), "samples": samples,
                                                  "utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                                                  "tare_N": tares})


@calibrate_app.command("shunt")
def shunt_cmd(hardware: Path = _HW, start_emulators: Optional[bool] = _EMU, cal_dir: Path = _CAL_DIR):
    """Read each bridge's shunt-calibration value and compare it with its reference (exit 1 when one drifted)."""
    from drivers.calibration import shunt_check
    from drivers.errors import DeviceError

    with _Devices(hardware, start_emulators) as dev:
        if not shunt_configured(dev.hw):
            fail(f"{hardware}: no channel has a shunt_address and a calibration.shunt_reference_N to compare with")
        try:
            rows = shunt_check(dev.reader.read_shunt(), dev.records())
        except DeviceError as exc:
            fail(str(exc), EXIT_FAILED)
    tab = Table(title="shunt calibration check (ASTM E4 / ISO 7500-1)")
    for c in ("channel", "serial", "reading (N)", "reference (N)", "deviation", "tolerance", "result"):
        tab.add_column(c)
    for r in rows:
        dev_txt = "-" if r["deviation_fraction"] is None else f"{r['deviation_fraction'] * 100:+.3f} %"
        tol = "-" if r["tolerance_fraction"] is None else f"±{r['tolerance_fraction'] * 100:.3f} %"
        res = {True: "ok", False: "[red]DRIFTED[/]", None: "no reference"}[r["ok"]]
        tab.add_row(r["channel"], str(r["serial"] or "-"), f"{r['reading_N']:.4f}",
                    "-" if r["reference_N"] is None else f"{r['reference_N']:.4f}", dev_txt, tol, res)
    console.print(tab)
    _write_record(_record_path(cal_dir, "shunt"), {"kind": "shunt", "profile": str(hardware),
                                                   "utc": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                                                   "channels": rows})
    bad = [r for r in rows if r["ok"] is False]
    if bad:
        fail("shunt check: " + "; ".join(f"{r['channel']} ({r['serial']}) drifted "
                                          f"{(r['deviation_fraction'] or float('nan')) * 100:+.3f} %" for r in bad),
             EXIT_FAILED)


@calibrate_app.command("verify")
def verify_cmd(hardware: Path = _HW, start_emulators: Optional[bool] = _EMU, cal_dir: Path = _CAL_DIR,
               channel: str = typer.Option("friction", "--channel", help="friction, normal_1 or normal_2."),
               points: str = typer.Option(..., "--points", metavar="N,N,...",
                                          help="Reference loads (N) to step through, e.g. 10,50,100."),
               samples: int = typer.Option(50, "--samples", min=1, max=100000, help="Readings averaged per point.")):
    """Step through reference loads; write cal/<serial>-<date>.json with the error at each point and pass/fail.

    On the emulated rig each load is applied through the conditioner's reference-load input; on a
    real rig rig asks the operator to apply it (dead weights, a reference cell) and press Enter."""
    from drivers.calibration import verify_points
    from drivers.errors import DeviceError

    if channel not in CHANNELS:
        fail(f"--channel {channel!r}: one of {', '.join(CHANNELS)}")
    try:
        loads = [float(x) for x in points.split(",") if x.strip()]
    except ValueError:
        fail(f"--points {points!r}: expected numbers of newtons separated by commas, e.g. 10,50,100")
    if not loads or any(not (v == v and abs(v) < 1e9) for v in loads):
        fail(f"--points {points!r}: expected finite numbers of newtons")
    k = CHANNELS.index(channel)
    measured = []
    with _Devices(hardware, start_emulators) as dev:
        cal = dev.records()[channel]
        if cal is None:
            warn(f"{hardware}: hardware.loadcells.{channel} has no calibration record: errors without a class verdict")
        try:
            for ref in loads:
                if dev.emu is not None:
                    dev.emu.inject("loadcells", "reference_channel", k + 1)
                    dev.emu.inject("loadcells", "reference_load_N", ref)
                    import time

                    time.sleep(0.05)  # the next conversions carry it
                else:
                    typer.prompt(f"apply {ref:g} N to the {channel} load cell, then press Enter", default="",
                                 show_default=False)
                measured.append((ref, _mean_reading(dev.reader, k, samples)))
        except DeviceError as exc:
            fail(str(exc), EXIT_FAILED)
        finally:
            if dev.emu is not None:
                dev.emu.inject("loadcells", "reference_channel", None)
    res = verify_points(measured, cal)
    tab = Table(title=f"verification of {channel} ({cal.serial if cal else 'no record'}, class "
                      f"{res['class'] or '-'})")
    for c in ("reference (N)", "indicated (N)", "error (N)", "relative", "in range", "result"):
        tab.add_column(c)
    for r in res["points"]:
        q = "-" if r["relative_error"] is None else f"{r['relative_error'] * 100:+.3f} %"
        tab.add_row(f"{r['reference_N']:g}", f"{r['indicated_N']:.4f}", f"{r['error_N']:+.4f}", q,
                    "yes" if r["in_verified_range"] else "no", {True: "ok", False: "[red]FAIL[/]", None: "-"}[r["ok"]])
    console.print(tab)
    today = datetime.date.today().isoformat()
    doc = {"kind": "verify", "channel": channel, "serial": cal.serial if cal else None, "date": today,
           "profile": str(hardware), "samples_per_point": samples,
           "calibration": cal.model_dump(mode="json", by_alias=True) if cal else None, **res}
    _write_record(_record_path(cal_dir, cal.serial if cal else channel), doc)
    if res["passed"] is False:
        fail(f"verification of {channel}: outside class {res['class']} at "
             + ", ".join(f"{r['reference_N']:g} N" for r in res["points"] if r["ok"] is False), EXIT_FAILED)


def register(app: typer.Typer) -> None:
    app.add_typer(calibrate_app, name="calibrate")
