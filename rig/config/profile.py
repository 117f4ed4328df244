"""Rig profile: every physical and controller parameter of a rig, with units in the names.

A profile is a YAML file (``config/rigs/*.yaml``) validated by :class:`RigProfile`
(pydantic, strict, unknown fields forbidden) through the one loader
(:mod:`rig.config.loader`): :func:`load_profile` turns any problem into a
:class:`ProfileError` that names the file, the field and the line. A profile may
start with ``extends: other.yaml`` and give only what differs (``emulated.yaml``
extends ``sim.yaml``).

Sections (docs/sim.md, docs/hardware.md):

* ``loop``: the control-loop rate (1 kHz in the paper, section 3).
* ``controller``: digital PID on position error (paper, section 3) in physical units:
  error in µm, output a force demand in N. The valve command is the force demand
  divided by ``actuator.full_scale_force_N``, saturated at ±1. Dither at 500 Hz,
  0.1 % of the PID output (section 3).
* ``servovalve``, ``actuator``, ``fixture``, ``normal``, ``sensors``, ``stroke``: the
  plant (simulated by :mod:`rig.sim.plant`, documented in docs/sim.md).
* ``lubricants``: per-lubricant friction parameters. ``A_mu``, ``B_mu``, ``L_um`` left out of a
  lubricant named as in Table 2 are Table 2's means, read by name from
  :data:`rig.model.paper.TABLE2` (the one place Table 2 is written); the paper gives no
  ``mu0``, so each profile states its own (an assumption). ``lubricant_map``: a lab's own
  lubricant names (a recipe's free ``lubricant``) mapped to one of ``lubricants``.
* ``required_metadata``: keys every trial must record (e.g. ``[specimen, operator]``):
  ``rig run`` refuses, exit 2, before anything moves when one is missing.
* ``sim``: numerical settings of the simulated rig.
* ``hardware``: the devices, typed by :class:`drivers.config.HardwareConfig`
  (``null``: a simulated rig only).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from drivers.config import HardwareConfig
from rig.config.loader import ConfigError, StrictModel, expect_kind, field_error, read_yaml, validate
from rig.model.paper import TABLE2, k_cr_eq13_N_per_um
from rig.model.spec import FrictionModel
from trajectories import DEFAULT_MAX_SPEED_UM_S, RigLimits


class ProfileError(ConfigError):
    """A rig profile cannot be used: names the file, the field and the line."""


# Upper bound of a normal force (N): ten times the paper's 100 N per rider; the soft normal
# springs and the +-0.6 N normal load cells are sized for about that (section 3).
MAX_NORMAL_FORCE_N = 1000.0


class LoopConfig(StrictModel):
    rate_hz: float = Field(1000.0, gt=0, le=100_000.0, description="control-loop rate (paper: 1 kHz)")

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_hz


class ControllerConfig(StrictModel):
    """PID on position error (µm) -> force demand (N); section 3 of the paper."""

    kp_N_per_um: float = Field(0.5, ge=0, description="proportional gain = controller stiffness (N/µm = MN/m)")
    ki_N_per_um_s: float = Field(5.0, ge=0, description="integral gain (N per µm·s)")
    kd_N_s_per_um: float = Field(0.003, ge=0, description="derivative gain (N·s/µm), backward difference")
    bias_N: float = Field(0.0, description="constant force added to the PID output (LinuxCNC 'bias')")
    integral_max_N: float = Field(500.0, gt=0, description="clamp on |integral term| (N)")
    output_max_N: float | None = Field(None, gt=0, description="clamp on |PID output| (N); default full scale")
    error_max_um: float = Field(5000.0, gt=0, description="clamp on |position error| (µm)")
    dither_frequency_hz: float = Field(500.0, ge=0, description="dither frequency (paper: 500 Hz)")
    dither_amplitude_fraction: float = Field(0.001, ge=0, description="dither amplitude / reference (paper: 0.1 %)")
    dither_reference: Literal["pid_output", "full_scale"] = Field(
        "pid_output", description="pid_output: fraction of the low-passed |PID output|; full_scale: of full_scale_force_N")
    dither_smoothing_s: float = Field(0.05, gt=0, description="time constant of the |PID output| low-pass for the dither")
    ff1_N_s_per_um: float = Field(0.0, ge=0, description="velocity feed-forward (LinuxCNC FF1): force per unit reference "
                                                         "velocity, N s/µm; 0 = off")


class ServovalveConfig(StrictModel):
    time_constant_s: float = Field(0.001, gt=0, description="first-order spool time constant")
    stiction_band_cmd: float = Field(0.0, ge=0, description="spool stiction/deadband, in valve-command units (0-1)")


class ActuatorConfig(StrictModel):
    full_scale_force_N: float = Field(10000.0, gt=0, description="static force at valve command 1 (actuator blocked)")
    piston_area_mm2: float = Field(1000.0, gt=0)
    chamber_volume_cm3: float = Field(560.0, gt=0, description="total oil volume of both chambers")
    bulk_modulus_MPa: float = Field(1400.0, gt=0, description="effective oil bulk modulus")
    leakage_time_constant_s: float = Field(0.002, gt=0, description="V_t/(4 beta C_L): pressure decay through leakage")
    moving_mass_kg: float = Field(10.0, gt=0, le=10_000.0, description="piston + grip + test piece")
    viscous_damping_N_s_per_um: float = Field(0.0, ge=0, description="piston seal viscous damping")
    max_speed_um_s: float | None = Field(None, gt=0, le=1e6, description="fastest reference the planner allows "
                                                                       "(None: the planner's default, 1 mm/s)")
    max_accel_um_s2: float | None = Field(None, gt=0, description="largest reference acceleration (None: no limit)")

    @property
    def hydraulic_stiffness_N_per_um(self) -> float:
        """4 beta A^2 / V_t, in N/µm (= MN/m)."""
        beta = self.bulk_modulus_MPa * 1e6
        area = self.piston_area_mm2 * 1e-6
        vol = self.chamber_volume_cm3 * 1e-6
        return 4.0 * beta * area * area / vol * 1e-6

    @property
    def hydraulic_damping_N_s_per_um(self) -> float:
        """Velocity-force slope of the leaky actuator, k_h tau_L (N·s/µm): acts as eq. (8)'s k_v."""
        return self.hydraulic_stiffness_N_per_um * self.leakage_time_constant_s


class FixtureConfig(StrictModel):
    test_piece_stiffness_N_per_um: float = Field(1.0, gt=0, description="paper: at least 1 MN/m")
    fixture_stiffness_N_per_um: float = Field(10.0, gt=0, description="paper: at least 10 MN/m (incl. load cell)")


class NormalConfig(StrictModel):
    """Normal force on each rider, from soft springs (paper, section 3 and 4)."""

    nominal_force_N: float = Field(100.0, gt=0, le=MAX_NORMAL_FORCE_N, description="per rider (paper: 100 N)")
    rider_offset_fraction: tuple[float, float] = Field((0.005, -0.005), description="static mismatch of riders 1, 2")
    rider_spring_stiffness_N_per_um: float = Field(0.05, ge=0, description="soft normal springs")
    face_taper_um_per_mm: tuple[float, float] = Field((3.0, -2.0), description="test-piece face slope under rider 1, 2")
    face_waviness_amplitude_um: tuple[float, float] = Field((4.0, 3.0))
    face_waviness_wavelength_um: tuple[float, float] = Field((1500.0, 2300.0))
    face_waviness_phase_rad: tuple[float, float] = Field((0.0, 1.0))

    @model_validator(mode="after")
    def _wavelength(self):
        if min(self.face_waviness_wavelength_um) <= 0:
            raise ValueError("face_waviness_wavelength_um must be positive")
        return self


class LvdtSignal(StrictModel):
    """What the LVDT chain does to the position signal (modelled by the simulated rig).

    The device itself (serial port, calibration) is :class:`drivers.config.LvdtConfig`
    in the ``hardware`` section.
    """

    cutoff_hz: float = Field(100.0, gt=0, description="analog low-pass before digitisation (first order)")
    noise_sigma_um: float = Field(0.125, ge=0, description="Gaussian; the paper's ±0.25 µm read as 2 sigma")
    quantization_um: float = Field(0.076, ge=0, description="ADC step (0 = none)")
    min_um: float = Field(0.0, description="lower end of the measuring range")
    max_um: float = Field(5000.0, description="upper end (paper: 5 mm)")


class LoadCellSignal(StrictModel):
    """What a load-cell chain does to the force signal (modelled by the simulated rig).

    The conditioner (Modbus registers, calibration) is :class:`drivers.config.LoadCellConfig`
    in the ``hardware`` section.
    """

    cutoff_hz: float = Field(100.0, gt=0, description="first-order low-pass")
    noise_sigma_N: float = Field(0.125, ge=0, description="Gaussian sigma (the paper's ± read as 2 sigma)")


class SensorsConfig(StrictModel):
    lvdt: LvdtSignal = Field(default_factory=LvdtSignal)
    friction_load_cell: LoadCellSignal = Field(default_factory=LoadCellSignal)
    normal_load_cells: LoadCellSignal = Field(
        default_factory=lambda: LoadCellSignal(cutoff_hz=10.0, noise_sigma_N=0.3))


class StrokeConfig(StrictModel):
    min_um: float = 0.0
    max_um: float = 5000.0
    home_um: float = 500.0

    @model_validator(mode="after")
    def _order(self):
        if not (self.min_um <= self.home_um <= self.max_um) or self.min_um >= self.max_um:
            raise ValueError("need min_um <= home_um <= max_um and min_um < max_um")
        return self


class LubricantParams(StrictModel):
    mu0: float = Field(gt=0, le=10.0, description="friction coefficient at V0 = 1 µm/s (assumed: paper gives none)")
    A_mu: float = Field(ge=0, le=1.0)
    B_mu: float = Field(ge=0, le=1.0)
    L_um: float = Field(gt=0, le=1e5, description="characteristic slip length (Table 2: 19-65 µm)")


# mu0 at V0 = 1 µm/s of each Table 2 lubricant: assumed (the paper gives none)
_DEFAULT_MU0 = {"dry": 0.15, "paraffin": 0.12, "boundary": 0.10}
# paraffin's A: Table 2 has 0.0* ("less than the noise level of the load cell"); 2e-4 gives a
# jump 2 N A ln 10 = 0.09 N, under the ±0.25 N noise, while A = 0 exactly leaves the interface
# without a direct effect and the loop's noise then drives jerky micro-slip (docs/sim.md)
_DEFAULT_OVERRIDES = {"paraffin": {"A_mu": 2e-4}}


def table2_lubricant(name: str, entry: dict) -> dict:
    """A profile's lubricant entry with the Table 2 means (``A_mu``, ``B_mu``, ``L_um``) it leaves
    out filled in by name from :data:`rig.model.paper.TABLE2`; an entry of another name, or
    not a mapping, is returned as it is (validation then names what is missing)."""
    if name not in TABLE2 or not isinstance(entry, dict):
        return entry
    return {k: mean for k, (mean, _sd) in TABLE2[name].items() if k != "k_cr_kN_per_m"} | entry


def _default_lubricants() -> dict[str, LubricantParams]:
    return {name: LubricantParams(**table2_lubricant(name, {"mu0": mu0} | _DEFAULT_OVERRIDES.get(name, {})))
            for name, mu0 in _DEFAULT_MU0.items()}


class SimConfig(StrictModel):
    substeps: int = Field(2, ge=1, le=1000, description="plant integration substeps per loop tick")
    initial_creep_um_s: float = Field(0.01, gt=0,
                                      description="state at steady state for this speed when starting at rest")
    interface_mass_kg: float = Field(
        0.2, gt=0, description="mass at the interface, used only for memoryless (steady_state) friction models "
                               "with a delay or a negative slope, which are ill-posed on a massless interface")


class RigProfile(StrictModel):
    """All parameters of one rig (simulated or real). Units are in every name."""

    name: str = "rig"
    description: str = ""
    loop: LoopConfig = Field(default_factory=LoopConfig)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    servovalve: ServovalveConfig = Field(default_factory=ServovalveConfig)
    actuator: ActuatorConfig = Field(default_factory=ActuatorConfig)
    fixture: FixtureConfig = Field(default_factory=FixtureConfig)
    normal: NormalConfig = Field(default_factory=NormalConfig)
    sensors: SensorsConfig = Field(default_factory=SensorsConfig)
    stroke: StrokeConfig = Field(default_factory=StrokeConfig)
    lubricants: dict[str, LubricantParams] = Field(default_factory=_default_lubricants)
    lubricant_map: dict[str, str] = Field(default_factory=dict, description="a lab's lubricant name -> the key of "
                                                                          "its friction model in lubricants")
    required_metadata: list[str] = Field(default_factory=list, description="trial metadata keys rig run requires "
                                                                         "(e.g. specimen, operator)")
    sim: SimConfig = Field(default_factory=SimConfig)
    hardware: HardwareConfig | None = None

    @field_validator("lubricants", mode="before")
    @classmethod
    def _table2_by_name(cls, value):
        if not isinstance(value, dict):
            return value
        return {name: table2_lubricant(name, entry) for name, entry in value.items()}

    @model_validator(mode="after")
    def _cross_checks(self):
        for name, key in self.lubricant_map.items():
            if key not in self.lubricants:
                raise field_error(f"lubricant_map.{name}", f"{key!r} is not in lubricants (it has: "
                                                           f"{', '.join(self.lubricants)})")
        lv = self.sensors.lvdt
        if lv.min_um >= lv.max_um:
            raise field_error("sensors.lvdt.max_um", f"must exceed sensors.lvdt.min_um ({lv.min_um:g})")
        if self.hardware is not None:
            # the LVDT has one quantization step: the device's counts are the sensor chain's steps
            dev = self.hardware.lvdt
            if "um_per_count" not in dev.model_fields_set:
                dev.um_per_count = lv.quantization_um
            elif lv.quantization_um > 0 and abs(dev.um_per_count - lv.quantization_um) > 1e-9 * lv.quantization_um:
                raise field_error("hardware.lvdt.um_per_count",
                                  f"{dev.um_per_count:g} µm differs from sensors.lvdt.quantization_um "
                                  f"({lv.quantization_um:g} µm): the LVDT has one quantization step; "
                                  f"leave um_per_count out to take the sensor's")
        return self

    @property
    def dt_s(self) -> float:
        return 1.0 / self.loop.rate_hz

    @property
    def output_max_N(self) -> float:
        c = self.controller.output_max_N
        return self.actuator.full_scale_force_N if c is None else c

    def plan_limits(self, source: str | None = None) -> RigLimits:
        """What the planner needs: loop rate, stroke (narrowed by the hardware interlocks'
        stroke limits when given), the actuator's speed and acceleration, the home position."""
        lo, hi = self.stroke.min_um, self.stroke.max_um
        if self.hardware is not None:
            il = self.hardware.interlocks
            if il.stroke_min_um is not None:
                lo = max(lo, il.stroke_min_um)
            if il.stroke_max_um is not None:
                hi = min(hi, il.stroke_max_um)
        a = self.actuator
        note = "" if a.max_speed_um_s is not None else \
            "; the planner's default: the profile sets no actuator.max_speed_um_s"
        return RigLimits(loop_rate_hz=self.loop.rate_hz, stroke_min_um=lo, stroke_max_um=hi,
                         max_speed_um_s=a.max_speed_um_s if a.max_speed_um_s is not None else DEFAULT_MAX_SPEED_UM_S,
                         max_accel_um_s2=a.max_accel_um_s2 if a.max_accel_um_s2 is not None else math.inf,
                         initial_position_um=self.stroke.home_um, source=source or self.name,
                         max_speed_note=note)

    def lubricant_key(self, lubricant: str) -> str | None:
        """The key in ``lubricants`` of a lubricant name (itself, or through ``lubricant_map``); None:
        this profile has no friction model for it."""
        if lubricant in self.lubricants:
            return lubricant
        return self.lubricant_map.get(lubricant)

    def lubricant_names(self) -> list[str]:
        """Every lubricant name this profile maps to a friction model."""
        return list(self.lubricants) + [k for k in self.lubricant_map if k not in self.lubricants]

    def lubricant_params(self, lubricant: str) -> LubricantParams:
        key = self.lubricant_key(lubricant)
        if key is None:
            raise ValueError(f"unknown lubricant {lubricant!r}; this profile has: {', '.join(self.lubricant_names())}")
        return self.lubricants[key]

    def friction_model(self, lubricant: str) -> FrictionModel:
        """The rate-and-state :class:`FrictionModel` (eqs. 5-6) for a lubricant of this profile."""
        lp = self.lubricant_params(lubricant)
        return FrictionModel(params={"mu0": lp.mu0, "A_mu": lp.A_mu, "B_mu": lp.B_mu, "L_um": lp.L_um})

    def k_cr_N_per_um(self, lubricant: str, total: bool = True) -> float:
        """Quasi-static critical stiffness (eq. 13) for a lubricant, in N/µm.

        ``total=True`` uses the force on the sliding test piece, 2 N (both interfaces of the
        double-shear fixture); ``total=False`` uses N per rider, as the paper's Table 2 does.
        """
        lp = self.lubricant_params(lubricant)
        n = self.normal.nominal_force_N * (2.0 if total else 1.0)
        return k_cr_eq13_N_per_um(lp.A_mu, lp.B_mu, lp.L_um, n)


def load_profile(path: str | os.PathLike) -> RigProfile:
    """Load and validate a rig profile YAML (``extends`` resolved).

    Raises :class:`ProfileError` naming the file, the field and the line on any fault."""
    doc = read_yaml(path, error=ProfileError, what="a rig profile (a mapping of sections)", allow_extends=True)
    expect_kind(doc, RigProfile, "a rig profile", ProfileError)
    return validate(RigProfile, doc, error=ProfileError)


def default_profile_path() -> Path:
    """config/rigs/sim.yaml of this repository."""
    return Path(__file__).resolve().parents[2] / "config" / "rigs" / "sim.yaml"
