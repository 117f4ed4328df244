"""Harmless transformations of a record (diagnosis.md, "The answer depends on the physics only").

Each takes a :class:`rig.data.TrialData` and returns a new one that carries the
same physics: the diagnosis must name the same causes, with every parameter
within its uncertainty. The invariance test (tests/unit/diagnosis/test_diagnosis_invariance.py)
and the sweep (benchmarks/bench_invariance.py) use these, one definition each.
"""

from __future__ import annotations

import numpy as np

from rig.data import TrialData


def _copy(trial: TrialData, **changes) -> TrialData:
    t = trial.select(np.ones(len(trial), bool))
    for k, v in changes.items():
        setattr(t, k, v)
    return t


def shift(trial: TrialData, dt_s: float = 1000.0, dx_um: float = 5000.0) -> TrialData:
    """Time and position shifted by constants (a clock that starts at 1000 s, a position from 5 mm)."""
    ref = None if trial.position_ref_um is None else trial.position_ref_um + dx_um
    return _copy(trial, time_s=trial.time_s + dt_s, position_um=trial.position_um + dx_um, position_ref_um=ref)


def decimate(trial: TrialData, factor: int = 2) -> TrialData:
    """Every ``factor``-th row."""
    m = np.zeros(len(trial), bool)
    m[::factor] = True
    return trial.select(m)


def switch_rate(trial: TrialData, slow_hz: float = 10.0, fast_hz: float = 100.0, at_frac: float = 0.5) -> TrialData:
    """Logged slowly (at most ``slow_hz``) before ``at_frac`` of the record's time, fast (at most
    ``fast_hz``) after: the acquisition of many rock-mechanics machines around a step."""
    t = np.asarray(trial.time_s, dtype=float)
    t_sw = t[0] + at_frac * (t[-1] - t[0])
    keep = np.zeros(t.size, bool)
    last = -np.inf
    for i, ti in enumerate(t):  # the next row at least one period after the last kept one
        period = 1.0 / (slow_hz if ti < t_sw else fast_hz)
        if ti - last >= period * (1.0 - 1e-6):
            keep[i] = True
            last = ti
    return trial.select(keep)


def trim(trial: TrialData, frac: float = 0.05) -> TrialData:
    """``frac`` of the record's time cut off at each end."""
    t = np.asarray(trial.time_s, dtype=float)
    T = t[-1] - t[0]
    return trial.select((t >= t[0] + frac * T) & (t <= t[-1] - frac * T))


def scale_forces(trial: TrialData, factor: float = 3.0) -> TrialData:
    """Friction and both normal forces (and the nominal normal force) times ``factor``: the friction
    coefficient is unchanged; a stiffness in kN/m scales with the forces."""
    meta = dict(trial.metadata)
    if "normal_force_N" in meta:
        meta["normal_force_N"] = f"{float(meta['normal_force_N']) * factor:.12g}"
    if "machine_stiffness_kN_per_m" in meta:
        meta["machine_stiffness_kN_per_m"] = f"{float(meta['machine_stiffness_kN_per_m']) * factor:.12g}"
    n1 = None if trial.normal_1_N is None else trial.normal_1_N * factor
    n2 = None if trial.normal_2_N is None else trial.normal_2_N * factor
    return _copy(trial, friction_N=trial.friction_N * factor, normal_1_N=n1, normal_2_N=n2, metadata=meta)


# name -> transformation with the spec's parameters; "scale" multiplies forces by SCALE_FACTOR
SCALE_FACTOR = 3.0
TRANSFORMS = {
    "shift": shift,
    "decimate2": decimate,
    "rate10to100": switch_rate,
    "trim5": trim,
    "scale": scale_forces,
}

# how each reported parameter transforms under "scale" (a stiffness scales with the forces, a force
# drift too; everything in mu or um or s is unchanged)
FORCE_SCALED = ("stiffness_kN_per_m", "rate_N_per_s")


def expected(name: str, value: float, transform: str) -> float:
    """The value a parameter should take on the transformed record, given its value on the original."""
    if transform == "scale" and name in FORCE_SCALED:
        return value * SCALE_FACTOR
    return value


__all__ = ["shift", "decimate", "switch_rate", "trim", "scale_forces", "TRANSFORMS", "expected", "SCALE_FACTOR"]
