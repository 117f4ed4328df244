"""Device configuration models: the ``hardware`` section of a rig profile (pydantic).

:class:`rig.config.profile.RigProfile` types its ``hardware`` field as
:class:`HardwareConfig`, so the profile loader (:mod:`rig.config.loader`) reports
a bad hardware field with its file and line like any other. This module imports
nothing from ``rig`` (drivers are the lower layer); it also holds
:class:`StrictModel`, the one strict base class of every configuration model of
the project (recipes, rig profiles and these device configs).

:func:`parse_hardware` validates a plain dict (a profile's hardware section sent to
another process as a dict). The section describes the three devices of the rig of
Dupont & Dunlap (1995, section 3) and how the real-time loop guards them:

* ``loadcells``: the conditioner of the friction load cell (top of the fixture,
  +-0.25 N) and the two normal-force load cells in series with the riders
  (+-0.6 N), read over Modbus TCP or RTU in one request;
* ``lvdt``: the LVDT conditioner (5 mm stroke, 0.076 µm quantization step)
  streaming frames over a serial line (format in :mod:`drivers.lvdt`);
* ``valve``: the servovalve controller on CANopen (NMT, heartbeats, SYNC + set-point
  RPDO every tick, status TPDO with the actual spool, EMCY; :mod:`drivers.valve`);
* ``interlocks``: limits and staleness thresholds checked every tick;
* ``realtime``: scheduling of the loop process;
* ``emulators``: whether ``rig run --hardware`` starts the emulators itself.
"""

from __future__ import annotations

import datetime as _dt
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class StrictModel(BaseModel):
    """The one strict base of configuration models: unknown fields are errors, every float
    must be finite, assignments are validated. Files are validated in pydantic's strict
    mode besides (``trials: true`` is no integer), by :mod:`rig.config.loader`."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)


class CalibrationRecord(StrictModel):
    """A sensor's calibration, as its certificate states it (ASTM E4 / ISO 7500-1 practice for load cells).

    Forces in N (an LVDT's record in µm: ``capacity_um``, ``verified_range_um``, ``uncertainty_um``,
    ``shunt_reference_um``). ``verified_range_*``: the range the calibration verified; ``class``: the
    ISO 7500-1 class (0.5, 1, 2, 3: the relative error allowed, in %); ``shunt_reference_*``: the
    conditioner's shunt-calibration reading recorded at calibration, to which each shunt check compares
    (``shunt_tolerance_fraction`` of it, default 0.1 %); ``uncertainty_*``: the expanded uncertainty
    (k = 2) of a reading.
    """

    serial: str = Field(min_length=1, max_length=100)
    capacity_N: float | None = Field(None, gt=0)
    capacity_um: float | None = Field(None, gt=0)
    verified_range_N: tuple[float, float] | None = None
    verified_range_um: tuple[float, float] | None = None
    class_: str | None = Field(None, alias="class", description="ISO 7500-1 class: 0.5, 1, 2 or 3")
    certificate: str | None = None
    calibrated_on: _dt.date | None = None
    due_on: _dt.date | None = None
    shunt_reference_N: float | None = None
    shunt_reference_um: float | None = None
    shunt_tolerance_fraction: float = Field(0.001, gt=0, le=0.1)
    uncertainty_N: float | None = Field(None, ge=0)
    uncertainty_um: float | None = Field(None, ge=0)

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True,
                              populate_by_name=True)

    @field_validator("class_", mode="before")
    @classmethod
    def _class_text(cls, v):
        """``class: 1`` or ``class: 0.5`` as a lab writes it: the class's name."""
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return f"{v:g}"
        return v

    @model_validator(mode="after")
    def _ranges(self):
        for name in ("verified_range_N", "verified_range_um"):
            r = getattr(self, name)
            if r is not None and not r[0] < r[1]:
                raise ValueError(f"{name}: [lo, hi] with lo < hi")
        if self.calibrated_on and self.due_on and self.due_on < self.calibrated_on:
            raise ValueError("due_on is before calibrated_on")
        if self.class_ is not None and self.class_ not in CALIBRATION_CLASSES:
            raise ValueError(f"class {self.class_!r}: one of {', '.join(CALIBRATION_CLASSES)} (ISO 7500-1)")
        return self

    @property
    def class_error_fraction(self) -> float | None:
        """The relative error the class allows (ISO 7500-1: class 1 -> 1 %), None without a class."""
        return CALIBRATION_CLASSES.get(self.class_) if self.class_ is not None else None


#: ISO 7500-1 classes and their allowed relative error of indication
CALIBRATION_CLASSES = {"0.5": 0.005, "1": 0.01, "2": 0.02, "3": 0.03}


class ChannelCal(StrictModel):
    """One load-cell channel: ``force_N = raw * scale + offset - tare_N``.

    ``address`` is the first register of the value (absolute Modbus address).
    ``raw`` is the float32 or the scaled integer read from the conditioner.
    ``calibration``: the load cell's calibration record (:class:`CalibrationRecord`).
    """

    address: int = Field(ge=0, le=65535)
    scale: float = 1.0
    offset: float = 0.0
    tare_N: float = 0.0
    calibration: CalibrationRecord | None = None
    shunt_address: int | None = Field(None, ge=0, le=65535,
                                      description="input register (same encoding) of the channel's shunt-"
                                                  "calibration reading; None: the conditioner has none")


class LoadCellConfig(StrictModel):
    """Modbus conditioner of the three load cells; one request reads every channel."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(default=502, ge=1, le=65535)
    serial_port: str | None = None
    baudrate: int = 115200
    device_id: int = Field(default=1, ge=0, le=247)
    register_type: Literal["input", "holding"] = "input"
    encoding: Literal["float32", "int16", "int32"] = "float32"
    word_order: Literal["big", "little"] = "big"
    timeout_s: float = Field(default=0.005, gt=0)
    counter_address: int | None = Field(default=0, ge=0, le=65535,
                                        description="uint16 sample counter (staleness); None: none")
    status_address: int | None = Field(default=1, ge=0, le=65535,
                                       description="uint16 status word (bit0 overload)")
    friction: ChannelCal = ChannelCal(address=2)
    normal_1: ChannelCal = ChannelCal(address=4)
    normal_2: ChannelCal = ChannelCal(address=6)

    @model_validator(mode="after")
    def _check(self):
        if self.transport == "rtu" and not self.serial_port:
            raise ValueError("transport 'rtu' needs serial_port")
        return self

    @property
    def words_per_value(self) -> int:
        return 1 if self.encoding == "int16" else 2

    @property
    def address_text(self) -> str:
        if self.transport == "tcp":
            return f"modbus-tcp://{self.host}:{self.port} unit {self.device_id}"
        return f"modbus-rtu:{self.serial_port}@{self.baudrate} unit {self.device_id}"

    def span(self) -> tuple[int, int]:
        """(first address, count) of the single request covering every register used."""
        addrs = [self.friction.address, self.normal_1.address, self.normal_2.address]
        ends = [a + self.words_per_value for a in addrs]
        for a in (self.counter_address, self.status_address):
            if a is not None:
                addrs.append(a)
                ends.append(a + 1)
        first = min(addrs)
        return first, max(ends) - first


class LvdtConfig(StrictModel):
    """Serial LVDT conditioner streaming position frames (:mod:`drivers.lvdt`)."""

    port: str = "/dev/ttyUSB0"
    baudrate: int = 921600
    um_per_count: float = Field(default=0.076, gt=0,
                                description="quantization step (paper: 0.076 µm); in a rig profile it "
                                            "defaults to sensors.lvdt.quantization_um and must equal it")
    offset_um: float = 0.0
    invert: bool = False
    calibration: CalibrationRecord | None = None

    @property
    def address_text(self) -> str:
        return f"serial:{self.port}@{self.baudrate}"


class CanopenValveConfig(StrictModel):
    """The servovalve controller on CANopen (CiA 301 + a CiA 408 subset; :mod:`drivers.valve`).

    ``interface``: ``rig_unix`` (the machine-local bus of :mod:`drivers.canopen_bus`,
    the emulated rig), ``socketcan`` (the real rig), ``virtual`` (one process). The
    heartbeat, set-point watchdog and follow figures are written to the valve by SDO
    at connect. Following is checked twice on the valve's reported spool position:

    * level: it must stay within ``follow_max`` (fraction of full scale) of the
      commanded one, or the host trips after ``follow_time_s`` (a spool stuck away
      from its command; as loose as the valve's lag and hysteresis need);
    * dither: over the last ``dither_window_ticks`` status PDOs, the spool's 500 Hz
      (Nyquist) content must be at least ``dither_min_gain`` of the command's, judged
      whenever the command's is at least ``dither_min_command`` (fraction of full scale).
      The controller's dither is a test signal a live spool must follow: a valve that
      ignores its set-points, or a stuck spool, loses it within about one window, at any
      command level. ``dither_min_gain`` 0.1 accepts a first-order spool down to 32 Hz
      bandwidth (time constant 5 ms: gain tau -> (1-e^(-T/tau))/(1+e^(-T/tau)) at 1 kHz).
    """

    interface: Literal["rig_unix", "virtual", "socketcan"] = "rig_unix"
    channel: str = Field(default="rig", pattern=r"^[A-Za-z0-9._-]{1,64}$",
                         description="rig_unix: one name per rig (two rigs on one host use two names)")
    node_id: int = Field(default=1, ge=1, le=126)
    host_node_id: int = Field(default=127, ge=1, le=127, description="the host's heartbeat 0x700+id")
    heartbeat_period_s: float = Field(default=0.01, gt=0, description="both sides' heartbeat period")
    heartbeat_timeout_s: float = Field(default=0.05, gt=0, description="a heartbeat older than this is lost")
    watchdog_s: float = Field(default=0.02, gt=0, description="valve nulls without a set-point this long")
    tpdo_timeout_s: float = Field(default=0.05, gt=0, description="host: no TPDO this long is unhealthy")
    follow_max: float = Field(default=0.1, gt=0, description="|spool command - actual|, full scale")
    follow_time_s: float = Field(default=0.05, gt=0, description="... for longer than this is unhealthy")
    dither_window_ticks: int = Field(default=32, ge=8, le=1000,
                                     description="status PDOs over which the spool's dither is compared")
    dither_min_gain: float = Field(default=0.1, gt=0, lt=1,
                                   description="spool's 500 Hz amplitude / the command's: less trips")
    dither_min_command: float = Field(default=2.0e-4, gt=0, le=0.1,
                                      description="command's 500 Hz amplitude (full scale) needed to judge")
    connect_timeout_s: float = Field(default=2.0, gt=0)
    start_timeout_s: float = Field(default=1.0, gt=0, description="NMT start + reset + enable, verified")

    @property
    def address_text(self) -> str:
        return f"canopen-{self.interface}:{self.channel} node {self.node_id}"


class InterlockConfig(StrictModel):
    """Trip thresholds, checked every tick (:mod:`rig.hardware.interlocks`).

    Stroke limits default to the profile's stroke when not given (the paper's
    LVDT and actuator allow 5 mm). Every limit is written so that a value not
    provably inside it (NaN included) trips.

    Following error (always on), as LinuxCNC's ``FERROR`` / ``MIN_FERROR``:
    ``limit = max(min_following_error_um, following_error_um * |v_ref| / max_velocity_um_s)``
    with ``v_ref`` the reference velocity of the tick.

    Timing health: a stall (no tick for longer than ``stall_event_s``) is a
    ``stall`` event, longer than ``stall_trip_s`` a trip; skipped cycles above
    ``max_skipped_fraction`` of the last second trip; per device, lost frames or
    missed answers (``max_lost_frames``), bad checksums (``max_checksum_errors``)
    and stream garbage (``max_garbage_bytes``) within one second trip.
    """

    stroke_min_um: float | None = None
    stroke_max_um: float | None = None
    friction_max_N: float = Field(default=200.0, gt=0)
    normal_min_N: float = 5.0
    normal_max_N: float = 500.0
    stale_s: float = Field(default=0.005, gt=0, description="sensor data older than this trips")
    max_checksum_errors: int = Field(default=50, ge=0, description="frames with a bad checksum within 1 s")
    max_lost_frames: int = Field(default=50, ge=0,
                                 description="lost frames (sequence gaps) or missed answers within 1 s")
    max_garbage_bytes: int = Field(default=1000, ge=0, description="bytes skipped on a stream within 1 s")
    max_modbus_errors: int = Field(default=3, ge=1, description="consecutive exceptions/timeouts")
    max_can_errors: int = Field(default=3, ge=1, description="consecutive CAN send errors")
    max_consecutive_late: int = Field(default=10, ge=1,
                                      description="run of cycles more than late_threshold_s late")
    late_threshold_s: float = Field(default=0.001, gt=0)
    stall_event_s: float = Field(default=0.005, gt=0, description="a gap between ticks longer than this: event")
    stall_trip_s: float = Field(default=0.05, gt=0, description="... longer than this: trip")
    max_skipped_fraction: float = Field(default=0.02, ge=0, le=1,
                                        description="skipped cycles within the last second, fraction")
    following_error_um: float = Field(default=200.0, gt=0,
                                      description="FERROR: |x_ref - x| limit at max_velocity_um_s")
    min_following_error_um: float = Field(default=50.0, gt=0, description="MIN_FERROR: the limit at rest")
    max_velocity_um_s: float = Field(default=1000.0, gt=0, description="velocity at which FERROR applies")
    logger_timeout_s: float = Field(default=1.0, gt=0,
                                    description="the logger has not taken a block for this long: trip")
    logger_heartbeat_s: float = Field(default=0.02, gt=0,
                                      description="no heartbeat from the logger for this long and the logger "
                                                  "process exiting: trip (a killed logger's teardown delays "
                                                  "PDEATHSIG by ~80 ms)")
    stop_hold_s: float = Field(default=0.2, ge=0, description="time logged in the safe state")
    max_pause_s: float = Field(default=600.0, gt=0, description="an operator's pause held longer than this "
                                                                "trips to the safe state")


class RealtimeConfig(StrictModel):
    sched_fifo: bool = True
    priority: int = Field(default=80, ge=1, le=99)
    spin_s: float = Field(default=50e-6, ge=0, description="spin before deadline (not under FIFO)")
    cpu: int | None = Field(default=None, description="pin the loop process to this CPU")
    block_ticks: int = Field(default=100, ge=1)


class EmulatorConfig(StrictModel):
    """Emulators (drivers.emulators) started by ``rig run --hardware`` when ``autostart``."""

    autostart: bool = False
    seed: int = Field(default=1, ge=0, le=2**32 - 1)
    lubricant: str | None = Field(default=None, description="None: the trial's lubricant")
    normal_force_N: float | None = None
    sched_fifo: bool = True
    priority: int = Field(default=70, ge=1, le=99)
    cpu: int | None = Field(default=None, ge=0, description="pin the emulator processes to this CPU "
                                                           "(with realtime.cpu: keep them off the loop's)")
    run_dir: str = "/tmp/rig-emulated"
    faults: dict[Literal["loadcells", "lvdt", "valve"], dict[str, float]] = Field(
        default_factory=dict, description="faults set when the emulators start (CI): e.g. {loadcells: "
                                          "{drift: 0.01}} (drivers.emulators.modbus_conditioner.FAULT_KEYS)")


class SafetyConfig(StrictModel):
    """The lab's safety chain on a digital I/O module (Modbus TCP; :mod:`drivers.safety_io`).

    Inputs are Modbus discrete inputs, outputs coils, by address. The e-stop input is
    normally closed: 1 = circuit closed (healthy); 0 = pressed, or a broken wire. The
    pressure-OK input is 1 while the hydraulic power unit holds pressure. The loop drives the
    valve amplifier's enable output (on only while it controls) and toggles the watchdog output
    every tick (the module's relay drops the enable when it stops toggling). A trip on either input
    latches (``latch_dir``) until ``rig reset --hardware PROFILE`` sees both inputs healthy."""

    host: str = "127.0.0.1"
    port: int = Field(default=502, ge=1, le=65535)
    device_id: int = Field(default=1, ge=0, le=247)
    timeout_s: float = Field(default=0.005, gt=0, description="an answer later than this is missed")
    estop_input: int = Field(default=0, ge=0, le=65535, description="discrete input, normally closed")
    pressure_ok_input: int = Field(default=1, ge=0, le=65535, description="discrete input, 1 = pressure OK")
    enable_output: int = Field(default=0, ge=0, le=65535, description="coil: the valve amplifier's enable")
    watchdog_output: int = Field(default=1, ge=0, le=65535, description="coil toggled every tick")
    watchdog_s: float = Field(default=0.05, gt=0, description="the module drops the enable output when the "
                                                               "watchdog output has not toggled for this long")
    latch_dir: str = Field(default="~/.local/state/rig", description="where a safety trip's latch is kept "
                                                                     "(one file per module address)")

    @model_validator(mode="after")
    def _check(self):
        if self.estop_input == self.pressure_ok_input:
            raise ValueError("estop_input and pressure_ok_input must be different inputs")
        if self.enable_output == self.watchdog_output:
            raise ValueError("enable_output and watchdog_output must be different coils")
        return self

    @property
    def address_text(self) -> str:
        return f"modbus-tcp://{self.host}:{self.port} unit {self.device_id}"


class HardwareConfig(StrictModel):
    loadcells: LoadCellConfig
    lvdt: LvdtConfig
    valve: CanopenValveConfig
    safety: SafetyConfig | None = None
    interlocks: InterlockConfig = InterlockConfig()
    realtime: RealtimeConfig = RealtimeConfig()
    emulators: EmulatorConfig = EmulatorConfig()


def calibration_records(hw: "HardwareConfig") -> dict[str, CalibrationRecord | None]:
    """Every force channel's and the LVDT's calibration record, by channel name."""
    lc = hw.loadcells
    return {"friction": lc.friction.calibration, "normal_1": lc.normal_1.calibration,
            "normal_2": lc.normal_2.calibration, "lvdt": hw.lvdt.calibration}


def calibration_problems(hw: "HardwareConfig", today: _dt.date) -> list[dict]:
    """The channels whose calibration is past its ``due_on`` on ``today``: one dict each
    (``channel``, ``serial``, ``due_on``, ``message`` naming the channel and the date)."""
    out = []
    for ch, cal in calibration_records(hw).items():
        if cal is not None and cal.due_on is not None and cal.due_on < today:
            out.append({"channel": ch, "serial": cal.serial, "due_on": cal.due_on.isoformat(),
                        "message": f"hardware.{'lvdt' if ch == 'lvdt' else 'loadcells.' + ch}: calibration of "
                                   f"{cal.serial} was due on {cal.due_on.isoformat()}"})
    return out


class HardwareConfigError(ValueError):
    """The hardware section is missing or wrong; the message names where."""


def parse_hardware(section: dict | None, where: str = "hardware") -> HardwareConfig:
    """Validate a hardware section given as a plain dict (sent to another process, or built in
    code); one clear error naming the field. Profiles are typed when loaded (rig.config)."""
    if section is None:
        raise HardwareConfigError(f"{where}: the profile has no 'hardware' section")
    if isinstance(section, HardwareConfig):
        return section
    try:
        return HardwareConfig.model_validate(section)
    except ValidationError as exc:
        msgs = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"])
            msgs.append(f"{where}.{loc}: {err['msg']}")
        raise HardwareConfigError("; ".join(msgs)) from None


def hardware_of_profile(profile, where: str | None = None) -> HardwareConfig:
    """The :class:`HardwareConfig` of a RigProfile (or of a plain dict holding ``hardware``);
    :class:`HardwareConfigError` when the profile has none (``hardware: null``)."""
    section = profile.get("hardware") if isinstance(profile, dict) else getattr(profile, "hardware", None)
    name = where or str(getattr(profile, "source_path", None) or "profile")
    return parse_hardware(section, where=f"{name}: hardware")

