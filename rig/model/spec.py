"""The model description: baseline, extensions and named parameters with units (the model YAML).

:class:`FrictionModel` is what ``rig diagnose --model-out`` writes and ``rig run
--friction-model`` reads. It describes the forward model (:mod:`rig.model.forward`)
completely: the friction law (:mod:`rig.model.friction`), the loading system
(``finite_stiffness``: the stiffness between the measured position and the interface,
:mod:`rig.model.loading`, which *replaces* a rig's own fixture compliance) and the sensor
chain extensions (``sensor_lag``, ``time_delay``, ``force_offset_drift``,
``normal_force_variation``, :mod:`rig.model.sensors`).

:data:`CATALOGUE` is the one list of extensions (../shared/specs/diagnosis.md);
:data:`PARAMS` declares every parameter once: unit, bounds, log scaling and scale
(what :mod:`rig.fitting` fits with).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from rig.model import friction as fr
from rig.model.paper import TABLE2

V0_UM_S = fr.V0_UM_S

CATALOGUE = (
    "frictional_memory", "time_delay", "second_state_variable", "aging_law", "sensor_lag",
    "normal_force_variation", "slip_wear_drift", "force_offset_drift", "position_periodic",
    "finite_stiffness",
)

# the parameters each extension adds (catalogue names/units); frictional_memory replaces c_mu
EXT_PARAMS = {
    "frictional_memory": ("A_mu", "B_mu", "L_um"),
    "time_delay": ("delay_s",),
    "second_state_variable": ("B2_mu", "L2_um"),
    "aging_law": ("L_um",),
    "sensor_lag": ("tau_s",),
    "normal_force_variation": (),
    "slip_wear_drift": ("rate_mu_per_mm",),
    "force_offset_drift": ("rate_N_per_s",),
    "position_periodic": ("amplitude_mu", "wavelength_um"),
    "finite_stiffness": ("stiffness_kN_per_m",),
}
BASE_PARAMS = {"rate_state": ("mu0", "A_mu", "B_mu", "L_um"), "steady_state": ("mu0", "c_mu")}


class ParamDecl(NamedTuple):
    """One parameter: unit, bounds (lo, hi), fitted in ln (log) or as value/scale."""
    unit: str
    lo: float
    hi: float
    log: bool
    scale: float
    doc: str


PARAMS: dict[str, ParamDecl] = {
    "mu0": ParamDecl("1", -10.0, 10.0, False, 0.01, "friction coefficient at V0 = 1 µm/s, steady state"),
    "A_mu": ParamDecl("1", 0.0, 0.2, False, 1e-3, "direct effect (eq. 5)"),
    "B_mu": ParamDecl("1", -0.2, 0.2, False, 1e-3, "state effect (eq. 6)"),
    "L_um": ParamDecl("µm", 0.05, 1e5, True, 1.0, "characteristic slip distance (eq. 6)"),
    "c_mu": ParamDecl("1", -0.2, 0.2, False, 1e-3, "slope of mu_ss in ln v (steady_state baseline)"),
    "B2_mu": ParamDecl("1", -0.2, 0.2, False, 1e-3, "second state variable's effect"),
    "L2_um": ParamDecl("µm", 0.05, 1e6, True, 1.0, "second state variable's slip distance"),
    "delay_s": ParamDecl("s", 1e-4, 300.0, True, 1.0, "time delay of mu_ss (Hess & Soom)"),
    "tau_s": ParamDecl("s", 1e-4, 300.0, True, 1.0, "first-order sensor lag"),
    "rate_mu_per_mm": ParamDecl("1/mm", -1.0, 1.0, False, 1e-4, "slip wear drift"),
    "rate_N_per_s": ParamDecl("N/s", -10.0, 10.0, False, 1e-4, "force offset drift"),
    "amplitude_mu": ParamDecl("1", 0.0, 0.5, False, 1e-3, "position-periodic amplitude"),
    "wavelength_um": ParamDecl("µm", 1.0, 1e6, True, 1.0, "position-periodic wavelength"),
    "phase_rad": ParamDecl("rad", -np.pi, np.pi, False, 1.0, "position-periodic phase"),
    "stiffness_kN_per_m": ParamDecl("kN/m", 0.5, 1e7, True, 1.0,
                                    "stiffness between the measured position and the interface"),
    # nuisance of a whole-record fit: the speed whose steady state the record starts in
    "v_init_um_s": ParamDecl("µm/s", 1e-5, 1e3, True, 1.0, "initial steady-state speed"),
}


class Plausible(NamedTuple):
    """The range a measured parameter takes on a real interface (beyond the fit bounds of
    :data:`PARAMS`, which only keep the solver inside the model's domain), and why."""
    lo: float
    hi: float
    why: str


#: physically plausible ranges (rig.model.checks warns outside them): rate-and-state
#: coefficients of lubricated metals and of rocks are O(1e-4 - 2e-2) (Table 2: A 1.1e-3 -
#: 4.4e-3, B 4.0e-3 - 5.3e-3; rock friction a, b ~ 0.002 - 0.02), L of 1 - 100 µm
#: (Table 2: 7.3 - 19.2 µm; gouge up to a few hundred µm)
PLAUSIBLE: dict[str, Plausible] = {
    "A_mu": Plausible(1e-4, 0.05, "the direct effect (eq. 5) is positive and O(1e-4 - 2e-2) on real interfaces; "
                                  "below 1e-4 it is not resolved, above 0.05 it is an extrapolation"),
    "B_mu": Plausible(0.0, 0.05, "B < 0 means friction grows with slip after a velocity increase, which one state "
                                 "variable (eq. 6) does not do: a second, slower transient or a drift is being fitted"),
    "L_um": Plausible(0.1, 5000.0, "L is a slip distance of 1 - 100 µm (Table 2: 7 - 19 µm); millimetres is a "
                                   "drift, not a memory length"),
    "tau_s": Plausible(0.0, 10.0, "a force-sensor lag of more than 10 s is no sensor's"),
    "delay_s": Plausible(0.0, 10.0, "a delay of more than 10 s is no sensor's"),
}


def model_params(baseline: str, extensions: list[str]) -> list[str]:
    """Every parameter name of a model (order: baseline, then extensions)."""
    names: list[str] = []
    if baseline == "steady_state" and "frictional_memory" in extensions:
        names += ["mu0", "A_mu", "B_mu", "L_um"]
    else:
        names += list(BASE_PARAMS[baseline])
    for e in extensions:
        for p in EXT_PARAMS[e]:
            if p not in names:
                names.append(p)
        if e == "position_periodic":
            names.append("phase_rad")
    return names


class FrictionModel(BaseModel):
    """A model: baseline + extensions + parameters (names and units of :data:`PARAMS`).

    params keys: ``mu0``; rate_state: ``A_mu``, ``B_mu``, ``L_um``; steady_state: ``c_mu``
    (slope of mu_ss in ln v); extensions add those of :data:`EXT_PARAMS`.
    ``frictional_memory`` on a steady_state baseline turns it into rate_state.
    """

    model_config = ConfigDict(extra="forbid")

    baseline: Literal["rate_state", "steady_state"] = "rate_state"
    extensions: list[str] = Field(default_factory=list)
    params: dict[str, float] = Field(default_factory=dict)
    V0_um_s: float = V0_UM_S
    v_reg_um_s: float = 0.01

    @field_validator("extensions")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        bad = [e for e in v if e not in CATALOGUE]
        if bad:
            raise ValueError(f"unknown extension(s) {bad}; known: {', '.join(CATALOGUE)}")
        return v

    @field_validator("params")
    @classmethod
    def _known_params(cls, v: dict[str, float]) -> dict[str, float]:
        bad = [k for k in v if k not in PARAMS]
        if bad:
            raise ValueError(f"unknown parameter(s) {bad}; known: {', '.join(PARAMS)}")
        return v

    @model_validator(mode="after")
    def _complete(self) -> "FrictionModel":
        if "finite_stiffness" in self.extensions and not self.get("stiffness_kN_per_m") > 0:
            raise ValueError("finite_stiffness needs stiffness_kN_per_m > 0")
        if "sensor_lag" in self.extensions and self.get("tau_s") < 0:
            raise ValueError("sensor_lag needs tau_s >= 0")
        return self

    @property
    def has_state(self) -> bool:
        return self.baseline == "rate_state" or "frictional_memory" in self.extensions

    def get(self, name: str, default: float = 0.0) -> float:
        return float(self.params.get(name, default))

    @property
    def stiffness_N_per_um(self) -> float | None:
        """The loading system's stiffness (N/µm) if ``finite_stiffness``, else None (rigid)."""
        if "finite_stiffness" not in self.extensions:
            return None
        return self.get("stiffness_kN_per_m") * 1e-3

    def to_array(self) -> np.ndarray:
        """Pack the friction law for the numba kernels (the ``P_*`` indices of rig.model.friction)."""
        p = np.zeros(fr.N_PARAMS)
        p[fr.P_MU0] = self.get("mu0", 0.1)
        p[fr.P_V0] = self.V0_um_s
        p[fr.P_VREG] = self.v_reg_um_s
        if self.has_state:
            p[fr.P_STATE_ON] = 1.0
            p[fr.P_A] = self.get("A_mu")
            p[fr.P_B] = self.get("B_mu")
            p[fr.P_L] = self.get("L_um", 20.0)
        else:
            p[fr.P_A] = self.get("c_mu")
            p[fr.P_L] = 1.0
        if "second_state_variable" in self.extensions:
            p[fr.P_B2] = self.get("B2_mu")
            p[fr.P_L2] = self.get("L2_um", 100.0)
        if "aging_law" in self.extensions:
            p[fr.P_AGING] = 1.0
        if "position_periodic" in self.extensions:
            p[fr.P_AMP] = self.get("amplitude_mu")
            p[fr.P_WAVE] = self.get("wavelength_um", 250.0)
            p[fr.P_PHASE] = self.get("phase_rad")
        if "slip_wear_drift" in self.extensions:
            p[fr.P_WEAR] = self.get("rate_mu_per_mm")
        if p[fr.P_L] <= 0 or (p[fr.P_B2] != 0 and p[fr.P_L2] <= 0) or (p[fr.P_AMP] != 0 and p[fr.P_WAVE] <= 0):
            raise ValueError("L_um, L2_um and wavelength_um must be positive")
        return p

    def mu_ss(self, v_um_s):
        """Steady-state friction coefficient (eq. 7, plus a second state's -B2 ln v)."""
        v = np.maximum(np.abs(np.asarray(v_um_s, dtype=float)), 1e-12)
        lv = np.log(v / self.V0_um_s)
        slope = self.get("A_mu") - self.get("B_mu") if self.has_state else self.get("c_mu")
        if "second_state_variable" in self.extensions:
            slope = slope - self.get("B2_mu")
        return self.get("mu0", 0.1) + slope * lv

    @classmethod
    def for_lubricant(cls, name: str, mu0: float) -> "FrictionModel":
        """Table 2 mean values for a lubricant, with a chosen mu0."""
        if name not in TABLE2:
            raise ValueError(f"unknown lubricant {name!r}; known: {', '.join(TABLE2)}")
        row = TABLE2[name]
        return cls(params={"mu0": mu0, "A_mu": row["A_mu"][0], "B_mu": row["B_mu"][0], "L_um": row["L_um"][0]})

    def to_yaml(self, path: str | Path) -> None:
        """Write ``{friction_model: ...}`` atomically (temporary file, then rename), readable as
        ``open()`` would make it (0666 less the umask; mkstemp alone makes 0600)."""
        path = Path(path)
        text = yaml.safe_dump({"friction_model": self.model_dump()}, sort_keys=False)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent if str(path.parent) else ".")
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def from_yaml(cls, path: str | Path) -> "FrictionModel":
        doc = yaml.safe_load(Path(path).read_text())
        if isinstance(doc, dict) and "friction_model" in doc:
            doc = doc["friction_model"]
        return cls.model_validate(doc)


#: the rock-mechanics community's names (xlook, RSFit3000, rsfmodel) of the spec's parameters:
#: a = A_mu, b = B_mu, Dc = L, and the stiffness normalised by the friction force per unit mu
RSF_NAMES = {"A_mu": "a", "B_mu": "b", "L_um": "Dc_um"}


def rsf_vocabulary(params: dict, friction_per_mu_N: float | None = None) -> dict:
    """Additive keys in the friction-lab vocabulary, the same values as the spec's names:
    ``a`` (= A_mu), ``b`` (= B_mu), ``Dc_um`` (= L_um), ``a_minus_b`` and, with a
    ``stiffness_kN_per_m``, ``k_per_um``: the stiffness over the normal force that carries the
    friction (``friction_per_mu_N``, 2 N for the double-shear fixture), in 1/µm, the normalised
    k of xlook and RSFit (k_per_um = stiffness_N_per_um / friction_per_mu_N).

    One helper for identify's and diagnose's JSON (both import rig.model). Keys whose source is
    absent or not a number are left out."""
    def num(v):
        try:
            v = float(v)
        except (TypeError, ValueError):
            return None
        return v if np.isfinite(v) else None

    out = {}
    for src, dst in RSF_NAMES.items():
        v = num(params.get(src))
        if v is not None:
            out[dst] = v
    a, b = num(params.get("A_mu")), num(params.get("B_mu"))
    if a is not None and b is not None:
        out["a_minus_b"] = a - b
    k = num(params.get("stiffness_kN_per_m"))
    if k is not None and friction_per_mu_N and friction_per_mu_N > 0:
        out["k_per_um"] = k * 1e-3 / float(friction_per_mu_N)
    return out
