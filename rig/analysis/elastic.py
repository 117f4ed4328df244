"""Elastic correction of a record: the slip at the interface (``rig export --elastic-correction``).

A load-point record (measured-data.md, ``position_source: load_point``: the position at the
actuator, as on rock and gouge machines) has the machine's compliance between the measured
position and the interface. With a stiffness ``k`` the interface slip is

    interface_slip_um = position_um - friction_N / k          (k in N/µm = kN/m x 1e-3)

the elastic correction of the friction lab (e.g. Marone 1998; xlook's ``ec`` command), the
``interface_slip_um`` column of measured-data.md. ``k`` is given, or ``fit``: the file's
``machine_stiffness_kN_per_m`` metadata when present (a calibration), else the whole-record
rate-and-state fit with a finite stiffness (:func:`rig.analysis.identify.fit_whole_record`,
the same fit as ``rig identify``'s).
"""

from __future__ import annotations

import math

import numpy as np

from rig.data import TrialData, positive_number

KN_PER_M_TO_N_PER_UM = 1e-3
UNDETERMINED_REL_SD = 0.5  # a fitted stiffness whose s.e. exceeds half its value is not a stiffness to correct with


def parse_correction(text: str) -> float | None:
    """``fit`` -> None; a positive stiffness in kN/m -> its value. ValueError otherwise."""
    if text.strip().lower() == "fit":
        return None
    v = positive_number(text)
    if v is None:
        raise ValueError(f"--elastic-correction {text!r}: expected a positive stiffness in kN/m or 'fit'")
    return v


def stiffness_kN_per_m(trial: TrialData, given: float | None) -> tuple[float, str, float | None]:
    """The stiffness to correct with (kN/m), where it came from, and its standard error (fit).
    ValueError when the metadata value is not a positive number or the fit fails."""
    if given is not None:
        return float(given), "given", None
    v = trial.positive_metadata("machine_stiffness_kN_per_m", "kN/m")
    if v is not None:
        return v, "machine_stiffness_kN_per_m metadata", None
    from rig.analysis.identify import fit_whole_record

    # the report's 6-figure stiffness, not WholeRecordFit.params: the file states the k it was corrected
    # with (elastic_correction_kN_per_m, 6 figures), and its column must follow from that k exactly
    fit = fit_whole_record(trial, stiffness=True).report()
    k = (fit.get("params") or {}).get("stiffness_kN_per_m")
    if not fit.get("ok") or k is None or not math.isfinite(k) or k <= 0:
        raise ValueError(f"{trial.source or 'trial'}: the whole-record fit with a machine stiffness did not "
                         f"converge ({fit.get('reason', 'no finite positive stiffness')}); give the stiffness "
                         "in kN/m instead of 'fit'")
    from rig.model.checks import at_bound

    err = (fit.get("err_corr") or {}).get("stiffness_kN_per_m")
    side = at_bound("stiffness_kN_per_m", float(k))
    vague = err is not None and math.isfinite(err) and err > UNDETERMINED_REL_SD * k
    if side is not None or vague:  # the record does not determine a stiffness (none to correct)
        how = f"on its {side} bound" if side else f"at {k:.3g} ± {err:.3g} kN/m"
        raise ValueError(f"{trial.source or 'trial'}: the whole-record fit put the machine stiffness {how}: "
                         "this record does not determine one (a position measured at the interface has no "
                         "compliance to correct); give the stiffness in kN/m instead of 'fit'")
    return float(k), "whole-record fit (rig identify's, with stiffness)", err


def interface_slip_um(position_um, friction_N, k_kN_per_m: float) -> np.ndarray:
    """Position minus friction over the stiffness (µm)."""
    return np.asarray(position_um, float) - np.asarray(friction_N, float) / (k_kN_per_m * KN_PER_M_TO_N_PER_UM)


def correct(trial: TrialData, given: float | None) -> dict:
    """Add ``interface_slip_um`` to ``trial`` (its extra columns) and the stiffness used to its
    metadata; returns ``{k_kN_per_m, source, k_err_kN_per_m}``."""
    k, src, err = stiffness_kN_per_m(trial, given)
    trial.extra = {"interface_slip_um": interface_slip_um(trial.position_um, trial.friction_N, k), **trial.extra}
    trial.metadata["elastic_correction_kN_per_m"] = f"{k:.6g}"
    trial.metadata["elastic_correction_source"] = src
    return {"k_kN_per_m": k, "source": src, "k_err_kN_per_m": err}


__all__ = ["parse_correction", "stiffness_kN_per_m", "interface_slip_um", "correct"]
