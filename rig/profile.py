"""Rig profile: every physical and controller parameter of a rig, with units in the names.

A profile is a YAML file (``config/rigs/*.yaml``) validated by :class:`RigProfile`
(pydantic, unknown fields forbidden). :func:`load_profile` turns any problem into a
:class:`ProfileError` that names the file, the field and, where the YAML parser knows
it, the line.

Sections (see docs/TEAM-CONTRACTS.md and docs/sim.md):

* ``loop``: the control-loop rate (1 kHz in the paper, section 3).
* ``controller``: digital PID on position error (paper, section 3) in physical units:
  error in µm, output a force demand in N. The valve command is the force demand
  divided by ``actuator.full_scale_force_N``, saturated at ±1. Dither at 500 Hz,
  0.1 % of the PID output (section 3).
* ``servovalve``, ``actuator``, ``fixture``, ``normal``, ``sensors``, ``stroke``: the
  plant (simulated by :mod:`rig.plant`, documented in docs/sim.md).
* ``lubricants``: per-lubricant friction parameters, Table 2 means for A, B, L; the paper
  gives no ``mu0``, so the values here are assumptions.
* ``sim``: numerical settings of the simulated rig.
* ``hardware``: free-form, validated by the hardware code.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from rig.friction import FrictionModel


class ProfileError(ValueError):
    """A rig profile could not be loaded: names the file, the field and (if known) the line."""

    def __init__(self, path, field: str | None, msg: str, line: int | None = None):
        self.path = str(path)
        self.field = field
        self.line = line
        self.msg = msg
        where = self.path + (f", line {line}" if line else "")
        what = f"field '{field}': " if field else ""
        super().__init__(f"{where}: {what}{msg}")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class LoopConfig(_Strict):
    rate_hz: float = Field(1000.0, gt=0, description="control-loop rate (paper: 1 kHz)")

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_hz


class ControllerConfig(_Strict):
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


class ServovalveConfig(_Strict):
    time_constant_s: float = Field(0.001, gt=0, description="first-order spool time constant")
    stiction_band_cmd: float = Field(0.0, ge=0, description="spool stiction/deadband, in valve-command units (0-1)")


class ActuatorConfig(_Strict):
    full_scale_force_N: float = Field(10000.0, gt=0, description="static force at valve command 1 (actuator blocked)")
    piston_area_mm2: float = Field(1000.0, gt=0)
    chamber_volume_cm3: float = Field(560.0, gt=0, description="total oil volume of both chambers")
    bulk_modulus_MPa: float = Field(1400.0, gt=0, description="effective oil bulk modulus")
    leakage_time_constant_s: float = Field(0.002, gt=0, description="V_t/(4 beta C_L): pressure decay through leakage")
    moving_mass_kg: float = Field(10.0, gt=0, description="piston + grip + test piece")
    viscous_damping_N_s_per_um: float = Field(0.0, ge=0, description="piston seal viscous damping")

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


class FixtureConfig(_Strict):
    test_piece_stiffness_N_per_um: float = Field(1.0, gt=0, description="paper: at least 1 MN/m")
    fixture_stiffness_N_per_um: float = Field(10.0, gt=0, description="paper: at least 10 MN/m (incl. load cell)")


class NormalConfig(_Strict):
    """Normal force on each rider, from soft springs (paper, section 3 and 4)."""

    nominal_force_N: float = Field(100.0, gt=0, description="per rider (paper: 100 N)")
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


class LvdtConfig(_Strict):
    cutoff_hz: float = Field(100.0, gt=0, description="analog low-pass before digitisation (first order)")
    noise_sigma_um: float = Field(0.125, ge=0, description="Gaussian; the paper's ±0.25 µm read as 2 sigma")
    quantization_um: float = Field(0.076, ge=0, description="ADC step (0 = none)")
    min_um: float = Field(0.0, description="lower end of the measuring range")
    max_um: float = Field(5000.0, description="upper end (paper: 5 mm)")


class LoadCellConfig(_Strict):
    cutoff_hz: float = Field(100.0, gt=0, description="first-order low-pass")
    noise_sigma_N: float = Field(0.125, ge=0, description="Gaussian sigma (the paper's ± read as 2 sigma)")


class SensorsConfig(_Strict):
    lvdt: LvdtConfig = Field(default_factory=LvdtConfig)
    friction_load_cell: LoadCellConfig = Field(default_factory=LoadCellConfig)
    normal_load_cells: LoadCellConfig = Field(
        default_factory=lambda: LoadCellConfig(cutoff_hz=10.0, noise_sigma_N=0.3))


class StrokeConfig(_Strict):
    min_um: float = 0.0
    max_um: float = 5000.0
    home_um: float = 500.0

    @model_validator(mode="after")
    def _order(self):
        if not (self.min_um <= self.home_um <= self.max_um) or self.min_um >= self.max_um:
            raise ValueError("need min_um <= home_um <= max_um and min_um < max_um")
        return self


class LubricantParams(_Strict):
    mu0: float = Field(gt=0, description="friction coefficient at V0 = 1 µm/s (assumed: paper gives none)")
    A_mu: float = Field(ge=0)
    B_mu: float = Field(ge=0)
    L_um: float = Field(gt=0)


def _default_lubricants() -> dict[str, LubricantParams]:
    return {
        "dry": LubricantParams(mu0=0.15, A_mu=2.8e-3, B_mu=9.4e-3, L_um=64.7),
        # Table 2: A = 0.0* (below the load-cell noise); 2e-4 keeps a direct effect (docs/sim.md)
        "paraffin": LubricantParams(mu0=0.12, A_mu=2e-4, B_mu=11.1e-3, L_um=22.4),
        "boundary": LubricantParams(mu0=0.10, A_mu=1.1e-3, B_mu=4.0e-3, L_um=19.2),
    }


class SimConfig(_Strict):
    substeps: int = Field(2, ge=1, le=1000, description="plant integration substeps per loop tick")
    initial_creep_um_s: float = Field(0.01, gt=0,
                                      description="state at steady state for this speed when starting at rest")
    interface_mass_kg: float = Field(
        0.2, gt=0, description="mass at the interface, used only for memoryless (steady_state) friction models "
                               "with a delay or a negative slope, which are ill-posed on a massless interface")


class RigProfile(_Strict):
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
    sim: SimConfig = Field(default_factory=SimConfig)
    hardware: dict[str, Any] | None = None

    @property
    def dt_s(self) -> float:
        return 1.0 / self.loop.rate_hz

    @property
    def output_max_N(self) -> float:
        c = self.controller.output_max_N
        return self.actuator.full_scale_force_N if c is None else c

    def friction_model(self, lubricant: str) -> FrictionModel:
        """The rate-and-state :class:`FrictionModel` (eqs. 5-6) for a lubricant of this profile."""
        if lubricant not in self.lubricants:
            raise ValueError(f"unknown lubricant {lubricant!r}; this profile has: {', '.join(self.lubricants)}")
        lp = self.lubricants[lubricant]
        return FrictionModel(params={"mu0": lp.mu0, "A_mu": lp.A_mu, "B_mu": lp.B_mu, "L_um": lp.L_um})

    def k_cr_N_per_um(self, lubricant: str, total: bool = True) -> float:
        """Quasi-static critical stiffness (eq. 13) for a lubricant, in N/µm.

        ``total=True`` uses the force on the sliding test piece, 2 N (both interfaces of the
        double-shear fixture); ``total=False`` uses N per rider, as the paper's Table 2 does.
        """
        lp = self.lubricants[lubricant]
        n = self.normal.nominal_force_N * (2.0 if total else 1.0)
        return (lp.B_mu - lp.A_mu) * n / lp.L_um


# ---------------------------------------------------------------------------
# loading with file/field/line errors
# ---------------------------------------------------------------------------
def _node_line(node, loc: tuple) -> int | None:
    """Line (1-based) of the YAML node at ``loc`` (or of its deepest existing parent)."""
    line = node.start_mark.line + 1 if node is not None else None
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            nxt = None
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    nxt = v
                    line = k.start_mark.line + 1
                    break
            if nxt is None:
                return line
            node = nxt
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def load_profile(path: str | Path) -> RigProfile:
    """Load and validate a rig profile YAML. Raises :class:`ProfileError` (file, field, line)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProfileError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    try:
        root = yaml.compose(text)
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise ProfileError(path, None, f"invalid YAML: {getattr(exc, 'problem', None) or exc}", line) from None
    if doc is None:
        raise ProfileError(path, None, "empty file", 1)
    if not isinstance(doc, dict):
        raise ProfileError(path, None, "top level must be a mapping of sections", 1)
    if "rig_profile" in doc and len(doc) == 1:  # optional wrapper
        doc = doc["rig_profile"]
        loc_prefix: tuple = ("rig_profile",)
    else:
        loc_prefix = ()
    try:
        prof = RigProfile.model_validate(doc)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = tuple(err.get("loc", ()))
        field = ".".join(str(x) for x in loc) or None
        msg = err.get("msg", "invalid value")
        if err.get("type") == "extra_forbidden":
            msg = "unknown field (not allowed; check the spelling and units in the name)"
        if "input" in err and err.get("type") not in ("extra_forbidden", "missing"):
            inp = err["input"]
            if not isinstance(inp, dict):
                msg += f" (got {inp!r})"
        n_more = len(exc.errors()) - 1
        if n_more:
            msg += f" [and {n_more} more problem(s)]"
        raise ProfileError(path, field, msg, _node_line(root, loc_prefix + loc)) from None
    _check_physics(prof, path, root, loc_prefix)
    return prof


def _check_physics(prof: RigProfile, path, root, prefix) -> None:
    for name, lp in prof.lubricants.items():
        for fname in ("mu0", "A_mu", "B_mu", "L_um"):
            if not math.isfinite(getattr(lp, fname)):
                loc = prefix + ("lubricants", name, fname)
                raise ProfileError(path, ".".join(loc), "must be finite", _node_line(root, loc))
    if prof.sensors.lvdt.min_um >= prof.sensors.lvdt.max_um:
        loc = prefix + ("sensors", "lvdt", "max_um")
        raise ProfileError(path, ".".join(loc), "must exceed sensors.lvdt.min_um", _node_line(root, loc))


def default_profile_path() -> Path:
    """config/rigs/sim.yaml of this repository."""
    return Path(__file__).resolve().parents[1] / "config" / "rigs" / "sim.yaml"
