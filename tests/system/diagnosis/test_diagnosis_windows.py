"""The same causes from any window and any rate (issue 10, Deliver 4 / Must show).

A step cut two different ways, or logged at 25 Hz and at 1 kHz, gives the same causes: crops of
the shared real records and of a synthetic record.

What made crops disagree before (docs/diagnosis.md, "Hold-out design", and docs/validation.md):
- the 20 equal time blocks were placed from the record's first sample, so a crop decided whether
  a single step's peak fell in a fitted or a held-out block (the basalt record: held out, the
  rigid fit never saw the direct effect and ran to A ~ 0, L at its bound); they are now phased so
  that the step's transient starts a fit block;
- on Leeman from 1.3 s, a sensor lag (tau 0.29 s, 1.6 % gain) was added on top of the machine
  spring, moving k from 712 to 1130 kN/m: a lag and a spring both round the same step, so a
  further cause that moves an earlier finding's parameter by more than 30 % is not separable
  from it and is not named (core.MAX_FINDING_SHIFT).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import rig
from rig.data import TrialData
from rig.diagnosis import diagnose
from rig.log import load_trial
from rig.sim.synth import SynthSpec, make_record


TRANSIENT = {"second_state_variable", "aging_law", "sensor_lag", "finite_stiffness", "time_delay",
             "frictional_memory"}


def crop(tr: TrialData, t0: float, t1: float = np.inf, every: int = 1) -> TrialData:
    """Samples with t0 <= t <= t1 (every ``every``-th: a slower logging rate), time from 0."""
    t = np.asarray(tr.time_s)
    idx = np.flatnonzero((t >= t0) & (t <= t1))[::every]

    def f(a):
        return None if a is None else np.asarray(a)[idx]

    return TrialData(time_s=t[idx] - t[idx][0], position_um=f(tr.position_um), friction_N=f(tr.friction_N),
                     normal_1_N=f(tr.normal_1_N), normal_2_N=f(tr.normal_2_N),
                     position_ref_um=f(tr.position_ref_um), metadata=dict(tr.metadata), events=[],
                     source=f"{tr.source}[{t0}:{t1}:{every}]")


def causes(tr: TrialData) -> tuple[set[str], dict]:
    rep = diagnose(tr).report()
    return {f["cause"] for f in rep["findings"]}, rep


def test_leeman_same_cause_from_every_crop(real_data_dir):
    """12 -> 1.2 um/s at 4.35 s: the whole record, from 1.3 s (the crop that added a sensor lag),
    and the first 17 s (only ~15 um of the 25 um decay): finite_stiffness, nothing else."""
    tr = load_trial(real_data_dir / "leeman-p4309-step2.csv")
    ks = []
    for t0, t1 in ((0.0, np.inf), (1.3, np.inf), (0.0, 17.0)):
        got, rep = causes(crop(tr, t0, t1))
        assert got == {"finite_stiffness"}, (t0, t1, rep["findings"])
        ks.append(rep["findings"][0]["params"]["stiffness_kN_per_m"])
    # the same spring, whichever window (published fit: 560 kN/m)
    assert max(ks) / min(ks) < 1.5, ks


def test_basalt_no_transient_cause_from_any_crop(real_data_dir):
    """3 -> 10 um/s at 68.7 s: with the step fitted, one state explains the transient in every
    window (A, B ~ 0.008, L ~ 10 um); no transient cause is named in any. (A slow drift at about
    5 % hold-out gain passes in some windows and not in others: docs/validation.md.) The machine's
    coupling of this load-point record is fitted from the start in every window (issue 20), and
    named first unless it significantly worsens that window's held-out data (then not at all)."""
    tr = load_trial(real_data_dir / "giacomel-basalt-brava.csv")
    base = []
    for t0, t1 in ((0.0, np.inf), (10.0, np.inf), (30.0, np.inf), (0.0, 110.0)):
        got, rep = causes(crop(tr, t0, t1))
        named = [f["cause"] for f in rep["findings"]]
        rest = named[1:] if named[:1] == ["finite_stiffness"] else named
        assert not set(rest) & TRANSIENT, (t0, t1, rep["findings"])
        base.append(rep["baseline"]["params"])
    for k, tol in (("A_mu", 0.15), ("B_mu", 0.15), ("L_um", 0.35)):
        v = [p[k] for p in base]
        assert max(v) / min(v) < 1 + tol, (k, v)


def test_synthetic_same_causes_at_25_hz_and_1_khz_and_two_crops():
    """A second state variable (B2 0.0025 over 200 um) in a 1 kHz record of the paper's steps:
    the whole record at 1 kHz, every 40th sample (25 Hz), and two crops at 25 Hz that cut the
    record at different steps all name second_state_variable and nothing else."""
    eff = {"second_state_variable": {"B2_mu": 0.0025, "L2_um": 200.0}}
    trial, _ = make_record(SynthSpec(rate_hz=1000.0, effects=eff, seed=41, duration_s=600.0, protocol="paper",
                                     with_ref=False))
    for t0, t1, every in ((0.0, np.inf, 1), (0.0, np.inf, 40), (0.0, 430.0, 40), (130.0, np.inf, 40)):
        got, rep = causes(crop(trial, t0, t1, every))
        assert got == {"second_state_variable"}, (t0, t1, every, rep["findings"])
        assert abs(rep["model"]["params"]["L2_um"] - 200.0) < 0.35 * 200.0


def test_basalt_velstep7_same_answer_from_every_crop():
    """A second public BRAVA basalt record (tests/data/giacomel-basalt-velstep7.csv, MIT; 100 -> 300
    um/s at 1 kHz, Giacomel et al. 2021 Fig. 1e): the whole record, from 0.5 s and up to 4 s give
    the same answer -- one state (A ~ 0.0095, B ~ 0.0112, L ~ 13 um; identify's whole-record fit
    with stiffness: 0.0105 +- 0.0007, 0.0116 +- 0.0007, 11.3 +- 0.9 um) and no finding but the
    machine's coupling of a load-point record (issue 20: fitted from the start, always reported)."""
    from pathlib import Path

    tr = load_trial(Path(rig.__file__).resolve().parents[1] / "tests" / "data" / "giacomel-basalt-velstep7.csv")
    for t0, t1 in ((0.0, np.inf), (0.5, np.inf), (0.0, 4.0)):
        got, rep = causes(crop(tr, t0, t1))
        assert got == {"finite_stiffness"}, (t0, t1, rep["findings"])
        p = rep["baseline"]["params"]
        assert abs(p["A_mu"] - 0.0105) < 0.2 * 0.0105 and abs(p["B_mu"] - 0.0116) < 0.2 * 0.0116, p


def test_sepiolite_no_second_state_from_any_crop(real_data_dir):
    """The three TR2 sepiolite records are overlapping slices of one run (exp013: velstep1 0.2 -> 2
    um/s, velstep2 2 -> 0.2, velstep3 = the shared giacomel-sepiolite-tr2 0.2 -> 2). A second, slower
    state with B2 > 0 that made velstep1's friction fall by ~0.08 after its up-step would make it
    recover by about as much after velstep2's down-step; it keeps falling instead (docs/validation.md):
    the slow evolution is a slip weakening, not a memory. No crop names second_state_variable. (What
    the crops do name is not yet window-stable: docs/validation.md, "Window stability".)"""
    from pathlib import Path

    data = Path(rig.__file__).resolve().parents[1] / "tests" / "data"
    # fewer crops than before issue 20: these load-point records now carry the machine's spring in
    # every fit (several times the cost); the full sweep is benchmarks/bench_invariance.py
    cases = ((real_data_dir / "giacomel-sepiolite-tr2.csv", ((0.0, np.inf), (800.0, np.inf))),
             (data / "giacomel-sepiolite-velstep1.csv", ((1000.0, np.inf),)),
             (data / "giacomel-sepiolite-velstep2.csv", ((0.0, 3000.0),)))
    for path, crops in cases:
        tr = load_trial(path)
        for t0, t1 in crops:
            got, rep = causes(crop(tr, t0, t1))
            assert "second_state_variable" not in got, (path.name, t0, t1, rep["findings"])
