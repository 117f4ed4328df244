"""Harmless transformations of a record (diagnosis.md, "The answer depends on the physics only").

Each takes a :class:`rig.data.TrialData` and returns a new one that carries the
same physics: the diagnosis must name the same causes, with every parameter
within its uncertainty. The invariance test (tests/unit/diagnosis/test_diagnosis_invariance.py)
and the sweep (benchmarks/bench_invariance.py) use these, one definition each.
"""

from __future__ import annotations

import math

import numpy as np

from rig.data import TrialData
from rig.model.checks import check_params


def _copy(trial: TrialData, **changes) -> TrialData:
    t = trial.select(np.ones(len(trial), bool))
    for k, v in changes.items():
        setattr(t, k, v)
    return t


SHIFT_S, SHIFT_UM = 1000.0, 5000.0


def shift(trial: TrialData, dt_s: float = SHIFT_S, dx_um: float = SHIFT_UM) -> TrialData:
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


def crop(trial: TrialData, start_frac: float, end_frac: float) -> TrialData:
    """The record less ``start_frac`` of its time at the start and ``end_frac`` at the end (its clock
    kept: not re-zeroed)."""
    t = np.asarray(trial.time_s, dtype=float)
    T = t[-1] - t[0]
    return trial.select((t >= t[0] + start_frac * T) & (t <= t[-1] - end_frac * T))


def trim(trial: TrialData, frac: float = 0.05) -> TrialData:
    """``frac`` of the record's time cut off at each end."""
    return crop(trial, frac, frac)


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


def origin_moved_um(trial: TrialData, transformed: TrialData, name: str) -> float:
    """How far a transformation moved the record's first position, the origin of every position the
    diagnosis measures (``prep.canonical``), beside a "shift" (µm): a trim starts later on the slip."""
    return float(transformed.position_um[0] - trial.position_um[0]) - (SHIFT_UM if name == "shift" else 0.0)


def not_determined(rep: dict) -> set[str]:
    """The final model's parameters a diagnosis report flags as not determined: on a bound, an error
    at least as large as the value (whatever else is flagged: a B < 0 with an error of 3 B), or no
    errors at all (the refit on all the data ran to a bound or failed)."""
    m = rep["model"]
    sd = m.get("params_sd")
    if not sd:
        return set(m["params"])
    out = {w["param"] for w in check_params(m["params"], sd) if w["kind"] == "at_bound"}
    return out | {k for k, v in m["params"].items() if v is not None and sd.get(k) is not None
                  and math.isfinite(sd[k]) and sd[k] >= abs(v) and v != 0.0}


# "within its reported uncertainty": at two standard errors (the 95 % a consistency check is read at;
# two honest estimates of one value differ by more than one error of each about half the time)
K_SD = 2.0


def _region(rep: dict, k: str, scale: float = 1.0) -> tuple[float, float] | None:
    """The reported uncertainty of the final model's ``k`` at ``K_SD`` errors: its interval
    (``intervals``, one error each side, skewed as the likelihood is) where the report gives one,
    else the value's +- ``params_sd``, each side K_SD times as far from the value; None without
    either. Times ``scale`` (a transformation's own effect, :func:`expected`)."""
    m = rep["model"]
    v = m["params"].get(k)
    iv = (m.get("intervals") or {}).get(k)
    sd = (m.get("params_sd") or {}).get(k)
    if v is None:
        return None
    if iv is not None and None not in iv:
        lo, hi = v - K_SD * max(v - iv[0], 0.0), v + K_SD * max(iv[1] - v, 0.0)
    elif sd is not None and math.isfinite(sd):
        lo, hi = v - K_SD * sd, v + K_SD * sd
    else:
        return None
    return (lo * scale, hi * scale) if scale > 0 else (hi * scale, lo * scale)


def _within(x: float, region: tuple[float, float] | None) -> bool:
    return region is not None and region[0] <= x <= region[1]


def differences(ref: dict, got: dict, name: str, origin_um: float = 0.0) -> list[str]:
    """What differs between the diagnosis reports of a record (``ref``) and of its copy transformed by
    ``name`` (diagnosis.md, "The answer depends on the physics only"): the causes named, or a
    parameter of the final model that agrees neither within 25 % (a phase: 0.25 rad) nor within the
    reported uncertainty -- the original's value inside the copy's interval (``intervals``, else
    +- ``params_sd``; at ``K_SD`` errors), or the copy's inside the original's --, after the transformation's own effect
    (:func:`expected`; a position-periodic phase moves by 2 pi ``origin_um`` / wavelength,
    :func:`origin_moved_um`). A parameter both reports flag as not determined and give no uncertainty
    for agrees: neither says anything about it. Empty: the same answer."""
    causes = [[f["cause"] for f in r["findings"]] for r in (ref, got)]
    if causes[0] != causes[1]:
        return [f"causes differ: {causes[1]} vs {causes[0]}"]
    rp, gp = ref["model"]["params"], got["model"]["params"]
    rsd, gsd = ref["model"].get("params_sd") or {}, got["model"].get("params_sd") or {}
    loose = {k for k in not_determined(ref) & not_determined(got) if k not in rsd and k not in gsd}
    off = []
    for k, v in rp.items():
        if k in ("mu0", "v_init_um_s") or k in loose or v is None or gp.get(k) is None:
            continue
        want = expected(k, v, name)
        d = gp[k] - want
        if k == "phase_rad":
            d = math.remainder(d - 2.0 * math.pi * origin_um / float(rp.get("wavelength_um") or math.inf), 2 * math.pi)
            if abs(d) > max(K_SD * max(rsd.get(k) or 0.0, gsd.get(k) or 0.0), 0.25):
                off.append(f"{k} {gp[k]:.3g} vs {want:.3g}")
            continue
        scale = expected(k, 1.0, name)
        if abs(d) <= 0.25 * abs(want) or _within(want, _region(got, k)) or _within(gp[k], _region(ref, k, scale)):
            continue
        off.append(f"{k} {gp[k]:.3g} vs {want:.3g}")
    return ["params differ: " + ", ".join(off)] if off else []


__all__ = ["shift", "decimate", "switch_rate", "trim", "scale_forces", "TRANSFORMS", "expected", "SCALE_FACTOR",
           "differences", "not_determined", "origin_moved_um"]
