"""The answer depends on the physics only (diagnosis.md; issue 20): the same causes, every parameter
within its uncertainty (or 25 %), whatever the offset, sampling, crop or scale of a record.

A few short records keep this cheap; benchmarks/bench_invariance.py sweeps every record the
project has (table in docs/validation.md)."""

from __future__ import annotations

import numpy as np
import pytest

from rig.diagnosis import diagnose
from rig.diagnosis.transforms import TRANSFORMS, expected, shift, switch_rate
from rig.sim.synth import SynthSpec, make_record


TRUTH = {"mu0": 0.11, "A_mu": 0.0011, "B_mu": 0.0040, "L_um": 19.2}


STEP_S = 30.0


def _load_point_step(k_kN_per_m: float = 300.0, seed: int = 7, stated: bool = False, rate_hz: float = 100.0):
    """One 1 -> 10 um/s step (at STEP_S) through a spring of known stiffness, written at the load point."""
    trial, truth = make_record(SynthSpec(protocol=[(STEP_S, 1.0), (STEP_S, 10.0)], duration_s=2 * STEP_S,
                                         rate_hz=rate_hz,
                                         params=dict(TRUTH), effects={"finite_stiffness": {"stiffness_kN_per_m":
                                                                                          k_kN_per_m}},
                                         with_ref=False, seed=seed))
    trial.metadata["position_source"] = "load_point"
    if stated:
        trial.metadata["machine_stiffness_kN_per_m"] = f"{k_kN_per_m:g}"
    return trial, truth


def _params(rep: dict) -> dict:
    return {k: v for k, v in rep["model"]["params"].items() if k != "mu0"}


def _causes(rep: dict) -> list[str]:
    return [f["cause"] for f in rep["findings"]]


@pytest.mark.parametrize("stated", [False, True])
def test_load_point_step_with_rate_switch_and_offset_is_finite_stiffness(stated):
    """Must-show of issue 20: a synthetic step with a known stiffness, at the load point, logged at
    10 Hz then 100 Hz, with its clock from 1000 s: finite_stiffness, a, b and L within 10 %."""
    trial, truth = _load_point_step(stated=stated)
    t_step = STEP_S - 0.5  # the switch just before the step, as rock-mechanics machines log
    trial = shift(switch_rate(trial, 10.0, 100.0, at_frac=t_step / float(trial.time_s[-1] - trial.time_s[0])))
    rep = diagnose(trial).report()
    assert _causes(rep)[:1] == ["finite_stiffness"], rep["findings"]
    p = rep["model"]["params"]
    for k in ("A_mu", "B_mu", "L_um"):
        assert abs(p[k] - truth["params"][k]) < 0.10 * truth["params"][k], (k, p[k], truth["params"][k])
    if stated:
        assert p["stiffness_kN_per_m"] == pytest.approx(300.0)  # held at the file's value
    else:
        assert abs(p["stiffness_kN_per_m"] - 300.0) < 0.25 * 300.0
    # the coupling's uncertainty and the flat a-b-L valley are reported
    assert set(rep["model"]["params_sd"]) >= {"A_mu", "B_mu", "L_um"}
    assert rep["model"]["correlation"]["A_mu,B_mu"] > 0.0  # A and B trade along the valley


@pytest.fixture(scope="module")
def load_point_reports():
    trial, truth = _load_point_step(seed=11, rate_hz=25.0)
    out = {"orig": diagnose(trial).report()}
    for name, tf in TRANSFORMS.items():
        out[name] = diagnose(tf(trial)).report()
    return out, truth


@pytest.mark.parametrize("name", list(TRANSFORMS))
def test_same_causes_and_parameters_under_every_transformation(load_point_reports, name):
    reps, truth = load_point_reports
    ref, rep = reps["orig"], reps[name]
    assert _causes(rep) == _causes(ref), (name, rep["findings"], ref["findings"])
    sd, sd2 = ref["model"].get("params_sd", {}), rep["model"].get("params_sd", {})
    for k, v in _params(ref).items():
        want = expected(k, v, name)
        # within twice the two estimates' joint reported uncertainty, or 25 %
        joint = float(np.hypot(expected(k, sd.get(k) or 0.0, name), sd2.get(k) or 0.0))
        tol = max(2.0 * joint, 0.25 * abs(want))
        assert abs(_params(rep)[k] - want) <= tol, (name, k, _params(rep)[k], want, tol)


def test_trimmed_one_step_load_point_record_that_starts_mid_transient():
    """A load-point record whose one step (10 -> 1 um/s at 2 s of 40 s) the 5 % trim cuts off: the
    trimmed copy starts a second after the step, mid-transient, in a state no steady run set. The
    start's state is fitted (diagnosis.md, "The start of a record"), so the coupling is named on
    both, with the same parameters within their uncertainty (before, the trimmed copy named nothing:
    fitted from a steady start, the coupling lost on the held-out data)."""
    trial, _ = make_record(SynthSpec(protocol=[(2.0, 10.0), (38.0, 1.0)], duration_s=40.0, rate_hz=25.0,
                                     params=dict(TRUTH), effects={"finite_stiffness": {"stiffness_kN_per_m": 300.0}},
                                     with_ref=False, seed=5))
    trial.metadata["position_source"] = "load_point"
    ref, rep = diagnose(trial).report(), diagnose(TRANSFORMS["trim5"](trial)).report()
    assert _causes(ref) == _causes(rep) == ["finite_stiffness"], (ref["findings"], rep["findings"])
    sd, sd2 = ref["model"]["params_sd"], rep["model"]["params_sd"]
    for k, v in _params(ref).items():
        tol = max(2.0 * float(np.hypot(sd[k], sd2[k])), 0.25 * abs(v))
        assert abs(_params(rep)[k] - v) <= tol, (k, _params(rep)[k], v, tol)


def test_shift_is_exact_on_a_real_record(real_data_dir):
    """A clock from 1000 s and a position from 5 mm change nothing at all (the issue's table: they
    turned aging_law into none)."""
    from rig.log import load_trial

    trial = load_trial(real_data_dir / "leeman-p4309-step2.csv")
    a, b = diagnose(trial).report(), diagnose(shift(trial)).report()
    assert _causes(a) == _causes(b) == ["finite_stiffness"]
    assert a["model"]["params"] == b["model"]["params"]


def test_time_weights_count_time_not_rows():
    from rig.diagnosis.prep import time_weights

    t = np.concatenate([np.arange(0.0, 10.0, 0.1), 10.0 + np.arange(0.0, 10.0, 0.01)])
    u = time_weights(t)
    slow, fast = u[t < 9.0].sum(), u[t > 11.0].sum()
    assert slow == pytest.approx(fast, rel=0.05)  # 9 s each side weigh the same, whatever the rows
    assert np.all(time_weights(np.arange(0.0, 10.0, 0.04)) == 1.0)  # uniform: every row 1
