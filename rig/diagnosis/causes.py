"""The catalogue of causes (diagnosis.md), one object per cause in one registry.

In the way rsfmodel's state relations are small classes that the model loops
over, each :class:`Cause` holds what is particular to one physical effect:

- ``name`` and ``params`` (the parameters a finding reports, names and units
  of the catalogue);
- ``starts(p, grid, screen)``: starting points of its joint fit from the
  current model's parameters ``p`` (and the screening figures);
- ``plausible(p, grid)``: its own physical checks of a fit (the checks every
  fit passes -- bounds, plausible ranges, |A|, |B| < 0.05 -- are in
  :func:`rig.diagnosis.core._plausible`);
- ``evidence(p, grid, info)``: one sentence a person can check on the plot;
- ``scaling``: how the duration of its transient scales with the new speed
  (``"slip"``: ~1/v, ``"time"``: fixed, ``None``: no claim) and whether it is
  a transient cause at all (``transient``: checked on the swapped step split).

The statistics that decide (hold-out gain, BIC, z, re-splits, stability,
alternatives, uncertainties) are written once, in :mod:`rig.diagnosis.core`,
for all of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from rig.model.forward import cumulative_slip_um
from rig.model.spec import EXT_PARAMS

from .prep import Grid

EFFECT_MIN_NOISE = 0.5      # second state: its steady-state effect 2 N |B2| ln(v_hi/v_lo) >= this x noise
STIFF_MIN_SLIP_FRAC = 0.05  # finite stiffness: the slip the spring takes up in a transient >= this x L
# finite stiffness: a spring far softer than the record's own force-displacement secant after a step
# (stiffness_floor_kN_per_m) cannot make the force rise as fast as it does; "far": this factor below
STIFF_FLOOR_FACTOR = 3.0
STIFF_SECANT_MIN_UM = 3.0   # the secant over at least this much load-point travel (position noise ~0.2 um)
STIFF_SECANT_PRE_S = 1.0    # measured from this long before the step (its detected time may be late)
# two slip-law states of opposite sign must differ in length by at least this factor
MIN_OPPOSITE_STATE_RATIO = 3.0


def slip_of(grid: Grid) -> np.ndarray:
    """Accumulated slip (µm) at every bin."""
    return cumulative_slip_um(grid.t, grid.v)


def speeds(grid: Grid) -> tuple[float, float]:
    """The 5th and 95th percentiles of the sliding speed (µm/s)."""
    v = grid.v[grid.v > 0.05]
    if v.size == 0:
        return 0.0, 0.0
    return float(np.percentile(v, 5)), float(np.percentile(v, 95))


def rate_starts(p_ss: dict) -> list[dict]:
    """Rate-and-state starting points from a steady-state fit: L over 3-300 µm, two A's."""
    c = p_ss["c_mu"]
    out = []
    for L in (3.0, 10.0, 30.0, 100.0, 300.0):
        for A in (1e-3, 4e-3):
            out.append({"mu0": p_ss["mu0"], "A_mu": A, "B_mu": A - c, "L_um": L})
    return out


def _force_scale(grid: Grid) -> float:
    """N of friction per unit of a mu coefficient across the record's speeds, 2 N ln(v_hi / v_lo)."""
    vlo, vhi = speeds(grid)
    lnr = math.log(max(vhi, 1e-9) / max(vlo, 1e-9)) if vlo > 0 else 0.0
    return 2.0 * grid.N_nom * lnr


def _always(p: dict, grid: Grid) -> bool:
    return True


@dataclass(frozen=True)
class Cause:
    name: str
    params: tuple[str, ...]
    starts: Callable[[dict, Grid, dict], list[dict]]
    evidence: Callable[[dict, Grid, dict], str]
    plausible: Callable[[dict, Grid], bool] = _always
    scaling: str | None = None
    transient: bool = False
    keep: int = 2  # ranked starts fitted in full


# --- frictional memory (steady_state baseline only) --------------------------------------------
def _memory_starts(p, grid, screen):
    out = []
    for s in rate_starts({"mu0": p["mu0"], "c_mu": p.get("c_mu", 0.0)}):
        q = dict(p)
        q.pop("c_mu", None)
        q.update(s)
        out.append(q)
    return out


def _memory_evidence(p, grid, info):
    vlo, vhi = speeds(grid)
    L = p["L_um"]
    return (f"after each velocity change the friction approaches its new steady value over a slip of "
            f"L = {L:.3g} um (time L/v from {L / max(vhi, 1e-9):.3g} s to {L / max(vlo, 1e-9):.3g} s), "
            f"with a direct jump A = {p['A_mu']:.3g}: memory over a slip distance")


def _resolved_time(name: str):
    """A time constant ``name`` (s) the kinematics resolve and shorter than a fifth of the record
    (a 72 s "sensor lag" on a 2.8 h record is no sensor's)."""
    def check(p, grid):
        return grid.time_resolution_s <= p[name] <= 0.2 * float(grid.t[-1] - grid.t[0])
    return check


# --- time delay (steady_state baseline only) ---------------------------------------------------


def _delay_evidence(p, grid, info):
    vlo, vhi = speeds(grid)
    return (f"friction follows the steady-state curve of the velocity {p['delay_s']:.3g} s earlier, the same "
            f"delay at {vlo:.3g} and {vhi:.3g} um/s and no direct jump: a fixed time delay (Hess & Soom)")


# --- second state variable -----------------------------------------------------------------------
def _second_starts(p, grid, screen):
    L = p.get("L_um", 20.0)
    B = p.get("B_mu", 0.003)
    out = []
    for f in (0.05, 0.2, 5.0, 15.0, 50.0):
        for b2 in (0.5 * abs(B) + 5e-4, -0.5 * abs(B) - 5e-4):
            out.append(dict(p, B2_mu=b2, L2_um=max(L * f, 0.5)))
    # the baseline's state may be the slow one: a new fast state beside it
    for f in (0.05, 0.2):
        for b1 in (abs(B) + 1e-3, 3e-3):
            out.append(dict(p, B_mu=b1, L_um=max(L * f, 0.2), B2_mu=B, L2_um=L))
    return out


def _second_plausible(p, grid):
    if _force_scale(grid) * abs(p["B2_mu"]) < EFFECT_MIN_NOISE * grid.noise_N:
        return False  # significant perhaps, but below the noise floor: not a finding
    # two states of opposite sign and similar length nearly cancel: their small difference is one hump
    # that a single state, a spring or a lag shapes as well; two states are two only if their lengths
    # differ (docs/diagnosis.md, "Rules learned from records")
    L1, L2 = p.get("L_um", 0.0), p["L2_um"]
    if p.get("B_mu", 0.0) * p["B2_mu"] < 0 and max(L1, L2) < MIN_OPPOSITE_STATE_RATIO * min(L1, L2):
        return False
    # a state longer than half the record's slip cannot be told from a drift
    if p["L2_um"] > 0.5 * float(slip_of(grid)[-1]):
        return False
    # nor can one whose transient is shorter than the kinematics resolve, even at the fastest sliding
    # (as sensor_lag and time_delay): it stands in for the loading/sensors
    return p["L2_um"] / max(speeds(grid)[1], 1e-9) >= grid.time_resolution_s


def _second_evidence(p, grid, info):
    return (f"a second, {'slower' if p['L2_um'] > p.get('L_um', 0) else 'faster'} transient over a slip of "
            f"L2 = {p['L2_um']:.3g} um (B2 = {p['B2_mu']:.3g}) remains after the first state's "
            f"L = {p.get('L_um', float('nan')):.3g} um")


# --- aging law -------------------------------------------------------------------------------------
def _aging_starts(p, grid, screen):
    L = p.get("L_um", 20.0)
    return [dict(p), dict(p, L_um=L * 0.5), dict(p, L_um=L * 2.0)]


def _aging_evidence(p, grid, info):
    return ("the transients are asymmetric between up- and down-steps in the way the Dieterich aging law "
            f"predicts (state evolves with contact time), L = {p['L_um']:.3g} um")


# --- sensor lag ------------------------------------------------------------------------------------


def _lag_evidence(p, grid, info):
    vlo, vhi = speeds(grid)
    tau = p["tau_s"]
    return (f"the friction's response to every velocity change is rounded over a fixed time tau = {tau:.3g} s "
            f"(a slip of {tau * vlo:.3g} to {tau * vhi:.3g} um depending on speed): a time constant of the "
            "force channel, not a slip distance")


# --- finite stiffness ------------------------------------------------------------------------------
def _stiff_plausible(p, grid):
    dF = _force_scale(grid) * (abs(p.get("A_mu", 0.0)) + abs(p.get("B_mu", p.get("c_mu", 0.0))))
    # the spring must take up a slip the data can tell from rigid
    return dF / (p["stiffness_kN_per_m"] * 1e-3) >= STIFF_MIN_SLIP_FRAC * p.get("L_um", 20.0)


def stiffness_floor_kN_per_m(grid: Grid) -> float:
    """The lowest stiffness between the measured position and the interface that the record's own
    force rise after its steps allows, over STIFF_FLOOR_FACTOR (kN/m; 0 where no step bounds it).

    With ``F = k (x - delta)`` (eq. 1's spring; x the measured position, delta the interface's slip)
    and an interface that slides forward (``d delta >= 0``), every change of force obeys
    ``dF <= k dx``: the secant ``(F - F_0) / (x - x_0)`` from the steady force before a step is a lower
    bound on k, largest early in an up-step's rise (the load point runs ahead of an interface still at
    the old speed). Measured from STIFF_SECANT_PRE_S before the step (a late step time would
    steepen it), over at least STIFF_SECANT_MIN_UM of travel, with the force change reduced by three
    standard errors; the largest over the steps and their first minute. Sepiolite velstep1: 564 kN/m
    (its coupled fits: 341 kN/m; the trimmed copy's 0.7 kN/m made the 2 N rise take 3 mm of slip).
    A force proportional to the normal force scales with it, as the stiffness does."""
    st = grid.step_times_s
    if st is None or st.size == 0:
        return 0.0
    t, x, F, c = grid.t, grid.x, grid.F_mean, np.maximum(grid.count, 1e-9)
    sd = np.maximum(np.sqrt(np.maximum(grid.ss_within, 0.0) / c), grid.noise_N) / np.sqrt(c)
    best = 0.0
    for ts in st:
        pre = (t < ts) & (t > ts - 30.0) & (grid.v > 0.0)  # sliding forward (not a fitted bin: a start)
        post = (t > ts) & (t < ts + 60.0)
        if pre.sum() < 3 or not post.any():
            continue
        F0 = float(np.average(F[pre], weights=c[pre]))
        sd0 = float(np.sqrt(np.average((F[pre] - F0) ** 2, weights=c[pre]) / pre.sum()))
        x0 = float(np.interp(ts - STIFF_SECANT_PRE_S, t, x))
        dx = x[post] - x0
        dF = F[post] - F0 - 3.0 * np.hypot(sd[post], sd0)
        ok = dx >= STIFF_SECANT_MIN_UM
        if ok.any():
            best = max(best, float(np.max(dF[ok] / dx[ok])))
    return best * 1e3 / STIFF_FLOOR_FACTOR  # N/um -> kN/m


def _stiff_evidence(p, grid, info):
    k = p["stiffness_kN_per_m"]
    return (f"the interface lags the measured position (LVDT or load point) by F/k: the rise after a "
            f"velocity change spans a slip set by k = {k:.4g} kN/m (the measured point moves "
            f"{1.0 / (k * 1e-3):.3g} um per N of friction change before the interface does)")


# --- normal force, drifts, periodic --------------------------------------------------------------
def _nfv_evidence(p, grid, info):
    return (f"the residual follows mu x (N1 + N2 - 2 N_nom) with slope {info.get('normal_slope', float('nan')):.2f} "
            f"(z = {info.get('normal_z', float('nan')):.1f}): friction scales with the measured normal force")


def _wear_evidence(p, grid, info):
    return (f"friction drifts by {p['rate_mu_per_mm']:.3g} per mm of accumulated slip; a drift in slip fits "
            "the hold-out blocks better than a drift in time")


def _offset_evidence(p, grid, info):
    return (f"the force zero drifts by {p['rate_N_per_s'] * 3600:.3g} N per hour, following time rather than "
            "slip (it keeps drifting at the same rate whatever the speed)")


def _periodic_starts(p, grid, screen):
    lam = screen.get("lam0", 100.0)
    return [dict(p, amplitude_mu=screen.get("amp0", 1e-3), wavelength_um=lam * lf, phase_rad=ph)
            for lf in (1.0, 0.97, 1.03) for ph in (0.0, 1.6, 3.1, -1.6)]


# a period in position is told from a drift by several cycles in the record: the screen's periodogram
# searches wavelengths up to 1/PERIODIC_SEARCH_CYCLES of the position span, and a fit (which starts
# there and may move) is plausible up to 1/PERIODIC_MIN_CYCLES of it. The same bound for both rejected
# a true 202 um period on a record trimmed by 5 % at each end: 4.7 cycles (docs/diagnosis.md)
PERIODIC_SEARCH_CYCLES = 5.0
PERIODIC_MIN_CYCLES = 4.0


def _periodic_plausible(p, grid):
    return p["wavelength_um"] <= float(grid.x.max() - grid.x.min()) / PERIODIC_MIN_CYCLES


def _periodic_evidence(p, grid, info):
    return (f"the residual is periodic in position with wavelength {p['wavelength_um']:.4g} um and amplitude "
            f"{p['amplitude_mu']:.3g} in mu, the same at every speed (so not periodic in time)")


CAUSES: dict[str, Cause] = {c.name: c for c in (
    Cause("frictional_memory", EXT_PARAMS["frictional_memory"], _memory_starts, _memory_evidence,
          scaling="slip", transient=True),
    Cause("time_delay", EXT_PARAMS["time_delay"],
          lambda p, g, s: [dict(p, delay_s=float(d)) for d in np.exp(np.linspace(np.log(0.02), np.log(10.0), 240))],
          _delay_evidence, _resolved_time("delay_s"), scaling="time", transient=True),
    Cause("second_state_variable", EXT_PARAMS["second_state_variable"], _second_starts, _second_evidence,
          _second_plausible, scaling="slip", transient=True, keep=4),
    Cause("aging_law", EXT_PARAMS["aging_law"], _aging_starts, _aging_evidence, transient=True),
    Cause("sensor_lag", EXT_PARAMS["sensor_lag"],
          lambda p, g, s: [dict(p, tau_s=float(t)) for t in np.exp(np.linspace(np.log(0.01), np.log(10.0), 22))],
          _lag_evidence, _resolved_time("tau_s"), scaling="time", transient=True),
    Cause("finite_stiffness", EXT_PARAMS["finite_stiffness"],
          lambda p, g, s: [dict(p, stiffness_kN_per_m=k) for k in (10.0, 40.0, 150.0, 600.0, 3000.0)],
          _stiff_evidence, _stiff_plausible, scaling="slip", transient=True),
    Cause("normal_force_variation", EXT_PARAMS["normal_force_variation"], lambda p, g, s: [dict(p)], _nfv_evidence),
    Cause("slip_wear_drift", EXT_PARAMS["slip_wear_drift"],
          lambda p, g, s: [dict(p, rate_mu_per_mm=s.get("wear0", 0.0))], _wear_evidence),
    Cause("force_offset_drift", EXT_PARAMS["force_offset_drift"],
          lambda p, g, s: [dict(p, rate_N_per_s=s.get("drift0", 0.0))], _offset_evidence),
    Cause("position_periodic", ("amplitude_mu", "wavelength_um"), _periodic_starts, _periodic_evidence,
          _periodic_plausible),
)}

__all__ = ["CAUSES", "Cause", "rate_starts", "slip_of", "speeds"]
