"""The one friction-model module, shared by the simulated rig and the analysis.

Rate-and-state friction of one interface of the double-shear fixture
(Dupont & Dunlap 1995, section 2.1), written with the friction coefficient:

    mu = mu0 + A ln(v/V0) + theta                                   (eq. 5)
    dtheta/ddelta = -(theta + B ln(v/V0)) / L     (Ruina slip law, eq. 6)
    mu_ss(v) = mu0 + (A - B) ln(v/V0)                                (eq. 7)

with ``v`` in µm/s, slip ``delta`` in µm, ``L`` in µm, ``V0 = 1 µm/s``. The
total friction force of the fixture is ``F = mu * (N1 + N2)`` (two interfaces,
``2 mu N`` at the nominal per-rider normal force ``N``).

Sticking and ``v -> 0`` are handled by the regularised (arcsinh) form

    mu = A asinh( v / (2 V0) * exp((mu0 + theta) / A) )

which equals eq. (5) to within exp(-2 (mu0+theta)/A) (1e-70 here) while
sliding, is odd in ``v`` and finite at ``v = 0``, so stick-slip can be
simulated with a solver implicit in ``v``. With ``A = 0`` (paraffin oil in
Table 2) a smooth sign function of width ``v_reg_um_s`` takes its place.

The composable extensions of ``../shared/specs/diagnosis.md`` that act on the
friction law itself (second state variable, aging law, slip wear drift,
position-periodic friction; a delayed velocity for Hess & Soom) live in the
numba kernel :func:`mu_step`; the sensor- and fixture-side ones
(``sensor_lag``, ``force_offset_drift``, ``normal_force_variation``,
``finite_stiffness``) are applied by whoever turns ``mu`` into a measured
force, with the helpers here (:func:`lowpass_uneven`).

:class:`FrictionModel` is the serialisable description (baseline, extensions,
params with the catalogue's names and units) that ``rig diagnose --model-out``
writes and ``rig run --friction-model`` reads; :meth:`FrictionModel.to_array`
packs it for the kernels.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from numba import njit
from pydantic import BaseModel, ConfigDict, Field, field_validator

V0_UM_S = 1.0  # reference velocity V0 (µm/s), diagnosis.md and Table 2

# ---------------------------------------------------------------------------
# Table 2 of the paper: mean ± standard deviation of the mean, velocity jumps
# 1-10 µm/s, 100 N normal force. A_mu, B_mu dimensionless; L in µm; k_cr kN/m.
# ---------------------------------------------------------------------------
TABLE2 = {
    "dry": {"A_mu": (2.8e-3, 0.5e-3), "B_mu": (9.4e-3, 1.1e-3), "L_um": (64.7, 14.3), "k_cr_kN_per_m": (10.2, 2.9)},
    "paraffin": {"A_mu": (0.0, 0.0), "B_mu": (11.1e-3, 2.5e-3), "L_um": (22.4, 4.3), "k_cr_kN_per_m": (49.4, 14.5)},
    "boundary": {"A_mu": (1.1e-3, 0.1e-3), "B_mu": (4.0e-3, 0.4e-3), "L_um": (19.2, 1.4), "k_cr_kN_per_m": (14.8, 2.3)},
}
LUBRICANT_NAMES = tuple(TABLE2)

# ---------------------------------------------------------------------------
# Packed parameter vector for the numba kernels
# ---------------------------------------------------------------------------
P_MU0 = 0        # mu0 (1)
P_A = 1          # A_mu (1): direct effect; for steady_state baseline, the slope c
P_B = 2          # B_mu (1); 0 for the steady_state baseline
P_L = 3          # L_um (µm)
P_V0 = 4         # V0 (µm/s)
P_B2 = 5         # B2_mu (1), second state variable (0 = absent)
P_L2 = 6         # L2_um (µm)
P_AGING = 7      # 1.0: Dieterich aging law in place of the Ruina slip law
P_AMP = 8        # amplitude_mu (1), position-periodic friction
P_WAVE = 9       # wavelength_um (µm)
P_PHASE = 10     # phase_rad (rad)
P_WEAR = 11      # rate_mu_per_mm (1/mm), slip wear drift
P_VREG = 12      # v_reg_um_s (µm/s), regularisation width when A = 0
P_STATE_ON = 13  # 1.0: a state variable exists (rate_state); 0.0: steady_state (mu = mu0 + c ln v/V0)
N_PARAMS = 14

# state vector: theta, theta2, accumulated slip (µm, always >= 0)
S_THETA = 0
S_THETA2 = 1
S_SLIP = 2
N_STATE = 3


@njit(cache=True)
def mu_regularized(v_um_s, theta_total, mu0, a, v0, v_reg):
    """Friction coefficient for velocity ``v`` and total state, arcsinh form of eq. (5).

    Odd in ``v``; equals ``mu0 + theta + a ln(v/v0)`` while sliding.
    """
    base = mu0 + theta_total
    av = abs(v_um_s)
    sgn = 1.0 if v_um_s >= 0.0 else -1.0
    if a > 0.0:
        if av == 0.0:
            return 0.0
        lnz = math.log(av / (2.0 * v0)) + base / a
        if lnz > 30.0:
            return sgn * (base + a * math.log(av / v0))
        return sgn * a * math.asinh(math.exp(lnz))
    # A = 0: friction independent of speed; smooth sign over v_reg
    return base * v_um_s / math.sqrt(v_um_s * v_um_s + v_reg * v_reg)


@njit(cache=True)
def dmu_dv(v_um_s, theta_total, mu0, a, v0, v_reg):
    """d mu / d v (s/µm) of :func:`mu_regularized`, for implicit solvers."""
    base = mu0 + theta_total
    av = abs(v_um_s)
    if a > 0.0:
        lnz = math.log(max(av, 1e-300) / (2.0 * v0)) + base / a
        if lnz > 30.0:
            return a / max(av, 1e-300)
        z = math.exp(lnz)
        # d/dv a asinh(k v) = a k / sqrt(1 + k^2 v^2), k = z / v
        k = math.exp(base / a) / (2.0 * v0)
        return a * k / math.sqrt(1.0 + z * z)
    return base * v_reg * v_reg / (v_um_s * v_um_s + v_reg * v_reg) ** 1.5


@njit(cache=True)
def _slip_law_update(theta, v_abs, dslip, b, l_um, v0):
    """Exact Ruina slip-law update of a state over slip ``dslip`` at constant speed (eq. 6)."""
    if b == 0.0 or dslip <= 0.0:
        return theta
    vv = max(v_abs, 1e-12)
    th_ss = -b * math.log(vv / v0)
    return th_ss + (theta - th_ss) * math.exp(-dslip / l_um)


@njit(cache=True)
def _aging_law_update(theta, v_abs, dt_s, b, l_um, v0):
    """Exact Dieterich aging-law update over ``dt`` at constant speed.

    dtheta/dt = B (V0/L) exp(-theta/B) - B v / L  (diagnosis.md, aging_law).
    With phi = exp(theta/B): dphi/dt = V0/L - v phi / L, linear in phi.
    """
    if b == 0.0 or dt_s <= 0.0:
        return theta
    phi = math.exp(theta / b)
    if v_abs * dt_s / l_um < 1e-9:
        phi = phi + v0 / l_um * dt_s
    else:
        phi_ss = v0 / v_abs
        phi = phi_ss + (phi - phi_ss) * math.exp(-v_abs * dt_s / l_um)
    return b * math.log(phi)


@njit(cache=True)
def theta_steady(p, v_um_s):
    """Steady-state theta (first state) at speed v: -B ln(v/V0)."""
    return -p[P_B] * math.log(max(abs(v_um_s), 1e-12) / p[P_V0])


@njit(cache=True)
def init_state(p, s, v_um_s):
    """Put the state at steady state for sliding at ``v`` (slip accumulator untouched)."""
    vv = max(abs(v_um_s), 1e-12)
    s[S_THETA] = -p[P_B] * math.log(vv / p[P_V0]) if p[P_STATE_ON] > 0.5 else 0.0
    s[S_THETA2] = -p[P_B2] * math.log(vv / p[P_V0])


@njit(cache=True)
def advance_state(p, s, v_um_s, dt_s):
    """Advance the state over ``dt`` at constant velocity ``v`` (exact for constant v)."""
    v_abs = abs(v_um_s)
    dslip = v_abs * dt_s
    if p[P_STATE_ON] > 0.5:
        if p[P_AGING] > 0.5:
            s[S_THETA] = _aging_law_update(s[S_THETA], v_abs, dt_s, p[P_B], p[P_L], p[P_V0])
        else:
            s[S_THETA] = _slip_law_update(s[S_THETA], v_abs, dslip, p[P_B], p[P_L], p[P_V0])
    if p[P_B2] != 0.0:
        s[S_THETA2] = _slip_law_update(s[S_THETA2], v_abs, dslip, p[P_B2], p[P_L2], p[P_V0])
    s[S_SLIP] += dslip


@njit(cache=True)
def mu_of(p, s, v_um_s, x_um):
    """Friction coefficient for the current state, velocity and position."""
    theta_total = s[S_THETA2]
    if p[P_STATE_ON] > 0.5:
        theta_total += s[S_THETA]
    if p[P_STATE_ON] < 0.5 and p[P_A] < 0.0:
        # steady_state baseline with a negative slope c (P_A): mu = mu0 + c ln(v/V0) (+ theta2),
        # the log argument held at v_reg near v = 0 and a smooth sign as in the A = 0 case
        av = max(abs(v_um_s), p[P_VREG])
        base = p[P_MU0] + theta_total + p[P_A] * math.log(av / p[P_V0])
        mu = base * v_um_s / math.sqrt(v_um_s * v_um_s + p[P_VREG] * p[P_VREG])
    else:
        mu = mu_regularized(v_um_s, theta_total, p[P_MU0], p[P_A], p[P_V0], p[P_VREG])
    extra = 0.0
    if p[P_AMP] != 0.0:
        extra += p[P_AMP] * math.sin(2.0 * math.pi * x_um / p[P_WAVE] + p[P_PHASE])
    if p[P_WEAR] != 0.0:
        extra += p[P_WEAR] * s[S_SLIP] * 1e-3
    if v_um_s >= 0.0:
        return mu + extra
    return mu - extra


@njit(cache=True)
def mu_step(p, s, v_um_s, dt_s, x_um):
    """Advance the state by ``dt`` at ``v`` and return mu at the end of the step."""
    advance_state(p, s, v_um_s, dt_s)
    return mu_of(p, s, v_um_s, x_um)


@njit(cache=True)
def mu_series(p, t_s, v_um_s, x_um, v_init_um_s):
    """Friction coefficient along a whole record of kinematics (analysis forward model).

    The state starts at steady state for ``v_init`` and is integrated in slip
    between samples with the velocity of the interval's midpoint (exact
    per interval for piecewise-constant velocity, so uneven sampling and gaps
    are handled). Returns mu at every sample.
    """
    n = t_s.shape[0]
    out = np.empty(n)
    s = np.zeros(N_STATE)
    init_state(p, s, v_init_um_s)
    out[0] = mu_of(p, s, v_um_s[0], x_um[0])
    for i in range(1, n):
        dt = t_s[i] - t_s[i - 1]
        vm = 0.5 * (v_um_s[i] + v_um_s[i - 1])
        advance_state(p, s, vm, dt)
        out[i] = mu_of(p, s, v_um_s[i], x_um[i])
    return out


def lowpass_uneven(t_s: np.ndarray, y: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass ``tau dy_f/dt = y - y_f`` on unevenly sampled data (exact for a
    piecewise-linear input). Used for ``sensor_lag`` and for the simulated load cells."""
    return _lowpass_uneven(np.ascontiguousarray(t_s, dtype=float), np.ascontiguousarray(y, dtype=float),
                           float(tau_s))


@njit(cache=True)
def _lowpass_uneven(t, y, tau):
    n = t.shape[0]
    out = np.empty(n)
    out[0] = y[0]
    if tau <= 0.0:
        for i in range(n):
            out[i] = y[i]
        return out
    for i in range(1, n):
        h = t[i] - t[i - 1]
        a = math.exp(-h / tau)
        # exact response to a linear ramp from y[i-1] to y[i] over h
        g = (1.0 - a) * tau / h if h > 0 else 1.0
        out[i] = a * out[i - 1] + (1.0 - g) * y[i] + (g - a) * y[i - 1]
    return out


# ---------------------------------------------------------------------------
# Serialisable model: what diagnosis writes and the simulated rig reads
# ---------------------------------------------------------------------------
EXTENSIONS = (
    "frictional_memory", "time_delay", "second_state_variable", "aging_law", "sensor_lag",
    "normal_force_variation", "slip_wear_drift", "force_offset_drift", "position_periodic",
    "finite_stiffness",
)


class FrictionModel(BaseModel):
    """A friction model: baseline + extensions + parameters (names and units of diagnosis.md).

    params keys: ``mu0``; rate_state: ``A_mu``, ``B_mu``, ``L_um``; steady_state: ``c_mu``
    (slope of mu_ss in ln v); extensions add ``B2_mu``, ``L2_um``, ``delay_s``, ``tau_s``,
    ``rate_mu_per_mm``, ``rate_N_per_s``, ``amplitude_mu``, ``wavelength_um``,
    ``phase_rad``, ``stiffness_kN_per_m``. ``frictional_memory`` on a steady_state
    baseline turns it into rate_state.
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
        bad = [e for e in v if e not in EXTENSIONS]
        if bad:
            raise ValueError(f"unknown extension(s) {bad}; known: {', '.join(EXTENSIONS)}")
        return v

    @property
    def has_state(self) -> bool:
        return self.baseline == "rate_state" or "frictional_memory" in self.extensions

    def get(self, name: str, default: float = 0.0) -> float:
        return float(self.params.get(name, default))

    def to_array(self) -> np.ndarray:
        """Pack for the numba kernels (see the ``P_*`` indices)."""
        p = np.zeros(N_PARAMS)
        p[P_MU0] = self.get("mu0", 0.1)
        p[P_V0] = self.V0_um_s
        p[P_VREG] = self.v_reg_um_s
        if self.has_state:
            p[P_STATE_ON] = 1.0
            p[P_A] = self.get("A_mu")
            p[P_B] = self.get("B_mu")
            p[P_L] = self.get("L_um", 20.0)
        else:
            p[P_A] = self.get("c_mu")
            p[P_L] = 1.0
        if "second_state_variable" in self.extensions:
            p[P_B2] = self.get("B2_mu")
            p[P_L2] = self.get("L2_um", 100.0)
        if "aging_law" in self.extensions:
            p[P_AGING] = 1.0
        if "position_periodic" in self.extensions:
            p[P_AMP] = self.get("amplitude_mu")
            p[P_WAVE] = self.get("wavelength_um", 250.0)
            p[P_PHASE] = self.get("phase_rad")
        if "slip_wear_drift" in self.extensions:
            p[P_WEAR] = self.get("rate_mu_per_mm")
        if p[P_L] <= 0 or (p[P_B2] != 0 and p[P_L2] <= 0) or (p[P_AMP] != 0 and p[P_WAVE] <= 0):
            raise ValueError("L_um, L2_um and wavelength_um must be positive")
        return p

    def mu_ss(self, v_um_s):
        """Steady-state friction coefficient (eq. 7, plus a second state's -B2 ln v)."""
        v = np.maximum(np.abs(np.asarray(v_um_s, dtype=float)), 1e-12)
        lv = np.log(v / self.V0_um_s)
        if self.has_state:
            slope = self.get("A_mu") - self.get("B_mu")
        else:
            slope = self.get("c_mu")
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
        from rig.data import atomic_write_text

        doc = {"friction_model": self.model_dump()}
        atomic_write_text(path, yaml.safe_dump(doc, sort_keys=False))

    @classmethod
    def from_yaml(cls, path: str | Path) -> "FrictionModel":
        doc = yaml.safe_load(Path(path).read_text())
        if isinstance(doc, dict) and "friction_model" in doc:
            doc = doc["friction_model"]
        return cls.model_validate(doc)


def k_cr_eq13_N_per_um(A_mu: float, B_mu: float, L_um: float, N_N: float) -> float:
    """Critical stiffness, quasi-static, k_v = 0 (eq. 13): (B_mu - A_mu) N / L, in N/µm (= MN/m).

    ``N`` is the nominal per-rider normal force, as in the paper's Table 2.
    Multiply by 1000 for kN/m.
    """
    return (B_mu - A_mu) * N_N / L_um


def k_cr_eq8(A_N: float, B_N: float, L_m: float, m_kg: float, k_v_N_s_per_m: float, V0_m_s: float) -> float:
    """Critical stiffness of the sliding system of Fig. 1 (eq. 8), SI units throughout.

    ``A_N``, ``B_N``: rate-and-state coefficients in force units (N), i.e.
    ``A_mu`` times the normal force acting on the sliding block (``2 N`` for the
    double-shear fixture's total friction force); ``L_m`` in m; returns N/m.
    """
    a_eff = A_N + k_v_N_s_per_m * V0_m_s
    return (B_N - a_eff) / L_m * (1.0 + m_kg * V0_m_s ** 2 / (a_eff * L_m))
