"""identify's whole-record fit on generated records with known truth: both state laws and the one
the record prefers, detrending, honest uncertainty (jacobian, bootstrap, mcmc), the field's
vocabulary, a known machine stiffness, and statistics that weigh time, not rows (issues 20, 24)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.analysis.identify import _time_weights, fit_whole_record, identify_trials
from rig.analysis.report import rounded
from rig.cli import app
from rig.data import write_csv
from rig.fitting.stats import effective_n, information_criterion
from rig.kinematics import detect_steps
from rig.model.spec import FrictionModel, rsf_vocabulary
from rig.sim import synth


TRUTH = {"mu0": 0.1, "A_mu": 0.0011, "B_mu": 0.004, "L_um": 19.2}
# a short paper protocol: 1 -> 5 -> 1 -> 10 -> 1 µm/s
SEGS = synth.paper_step_protocol(highs=(5.0, 10.0), pre_um=150.0, post_um=200.0, back_um=150.0)


def _record(extensions=(), seed=3, **extra):
    fm = FrictionModel(extensions=list(extensions), params={**TRUTH, **extra})
    return synth.generate(fm, SEGS, seed=seed).trial


@pytest.fixture(scope="module")
def both_laws():
    out = {}
    for law, ext in (("slip", ()), ("aging", ("aging_law",))):
        tr = _record(ext)
        out[law] = identify_trials([tr], law="both").report()
    return out


@pytest.mark.parametrize("law", ["slip", "aging"])
def test_each_law_recovered_within_10pct_and_preferred(both_laws, law):
    rep = both_laws[law]
    assert rep["preferred_law"] == law
    fit = rep["laws"][law]
    for k in ("A_mu", "B_mu", "L_um"):
        assert fit["params"][k] == pytest.approx(TRUTH[k], rel=0.10), (law, k)
    other = rep["laws"]["aging" if law == "slip" else "slip"]
    assert fit["rms_mu"] < other["rms_mu"]
    c = rep["laws"]["comparison"]
    assert c["bic"][law] < c["bic"]["aging" if law == "slip" else "slip"] - 6


def test_jacobian_errors_keys_and_asymmetric_L(both_laws):
    w = both_laws["slip"]["whole_record"]
    for k in ("A_mu", "B_mu", "L_um"):
        lo, hi = w["intervals"][k]
        assert lo < w["params"][k] < hi and w["params_sd"][k] > 0
    lo, hi = w["intervals"]["L_um"]
    L = w["params"]["L_um"]
    assert hi - L > L - lo  # ln-scaled: the interval reaches further up than down
    c = np.array(w["correlation"]["matrix"])
    assert w["correlation"]["names"][:4] == ["mu0", "A_mu", "B_mu", "L_um"]
    assert np.allclose(c, c.T) and np.allclose(np.diag(c), 1.0)
    assert c[1, 2] > 0.5  # A and B move together along the valley
    # the field's vocabulary: the same values under the other names
    assert w["params"]["a"] == w["params"]["A_mu"] and w["params"]["Dc_um"] == w["params"]["L_um"]
    assert w["params"]["a_minus_b"] == pytest.approx(w["params"]["A_mu"] - w["params"]["B_mu"], rel=1e-4)
    assert w["intervals"]["Dc_um"] == w["intervals"]["L_um"]
    m = both_laws["slip"]["mean"]
    assert m["b"] == m["B_mu"] and "a_minus_b" in m


def test_rsf_vocabulary_stiffness_normalised_by_friction_per_mu():
    v = rsf_vocabulary({"A_mu": 0.0077, "B_mu": 0.0071, "L_um": 25.0, "stiffness_kN_per_m": 560.0}, 200.0)
    assert v["k_per_um"] == pytest.approx(0.0028)  # Leeman: 560 kN/m at 100 N per rider
    assert v["a_minus_b"] == pytest.approx(0.0006)
    assert "k_per_um" not in rsf_vocabulary({"A_mu": 0.001}, 200.0)


def test_detrend_linear_and_auto_recover_a_slip_trend():
    rate = 0.002  # mu per mm of slip
    fm = FrictionModel(extensions=["slip_wear_drift"], params={**TRUTH, "rate_mu_per_mm": rate})
    tr = synth.generate(fm, synth.paper_step_protocol(highs=(5.0, 10.0), pre_um=300.0, post_um=300.0,
                                                      back_um=300.0), seed=5).trial
    steps = detect_steps(tr)
    fitted = fit_whole_record(tr, steps, detrend="linear", max_points=4000)
    lin = fitted.report()
    # the unrounded values the analyses start from (diagnose's prior), rounded once in the report
    assert rounded(fitted.params["B_mu"]) == lin["params"]["B_mu"] and fitted.curve is not None
    d = lin["detrend"]
    assert d["method"] == "linear"
    assert abs(d["rate_mu_per_mm"] - rate) < max(3 * d["rate_sd_mu_per_mm"], 0.1 * rate)
    auto = fit_whole_record(tr, steps, detrend="auto", max_points=4000, init={"L_um": 19.0}).report()
    assert auto["detrend"]["rate_mu_per_mm"] == pytest.approx(rate, rel=0.3)
    assert auto["detrend"]["windows_s"]
    none = fit_whole_record(tr, steps, detrend="none", max_points=4000).report()
    assert lin["rms_mu"] < none["rms_mu"]
    assert abs(lin["params"]["B_mu"] - TRUTH["B_mu"]) < abs(none["params"]["B_mu"] - TRUTH["B_mu"])


def test_bootstrap_and_mcmc_intervals():
    tr = _record(seed=7)
    steps = detect_steps(tr)
    bs = fit_whole_record(tr, steps, uncertainty="bootstrap:12", max_points=1500, seed=1).report()
    assert bs["uncertainty"]["method"] == "bootstrap" and bs["uncertainty"]["n_samples"] >= 10
    # the Jacobian's own errors (no floors: the jackknife and the velocity-rise floor see input errors
    # that no resampling of the residuals does)
    jac = fit_whole_record(tr, steps, max_points=1500, jackknife=False).report()
    for k in ("A_mu", "B_mu", "L_um"):
        assert bs["params_sd"][k] > 0
        # the two agree on the size of the error within a factor 3 (12 refits)
        assert jac["params_sd"][k] / 3 < bs["params_sd"][k] < 3 * jac["params_sd"][k]
    pytest.importorskip("emcee")
    mc = fit_whole_record(tr, steps, uncertainty="mcmc:40", max_points=1500, seed=1).report()
    assert mc["uncertainty"]["method"] == "mcmc" and 0 < mc["uncertainty"]["acceptance"] < 1
    for k in ("A_mu", "L_um"):
        lo, hi = mc["intervals"][k]
        assert lo < hi and mc["params_sd"][k] > 0


def test_known_machine_stiffness_is_held():
    """A load-point record whose file gives machine_stiffness_kN_per_m: the stiffness is taken as
    known (not fitted), and a, b, Dc come back within 10 %."""
    k = 300.0  # kN/m: 10 x k_cr, rounds the peak (k_per_um 0.0015, Leeman 0.0028)
    tr = _record(("finite_stiffness",), seed=9, stiffness_kN_per_m=k)
    tr.metadata.update({"position_source": "load_point", "machine_stiffness_kN_per_m": f"{k:g}"})
    w = identify_trials([tr]).report()["whole_record"]
    assert w["stiffness_source"] == "metadata"
    assert w["params"]["stiffness_kN_per_m"] == pytest.approx(k, rel=1e-6)
    assert w["params"]["k_per_um"] == pytest.approx(k * 1e-3 / 200.0, rel=1e-6)
    for name in ("A_mu", "B_mu", "L_um"):
        assert w["params"][name] == pytest.approx(TRUTH[name], rel=0.10), name


def test_time_weights_count_time_not_rows():
    t = np.concatenate([np.arange(0.0, 10.0, 0.1), 10.0 + np.arange(0.0, 10.0, 0.01)])
    w, typical = _time_weights(t)
    slow, fast = w[t < 10.0].sum(), w[t >= 10.0].sum()
    assert slow == pytest.approx(fast, rel=0.05)  # ten seconds each, whatever the rows
    assert typical == pytest.approx(0.01, rel=0.01) or typical == pytest.approx(0.1, rel=0.01)


def test_fast_logging_after_the_step_does_not_change_the_fit():
    """The same record logged at 2.5 Hz before the first step and 25 Hz after: the fit stays within
    its errors of the uniformly logged one."""
    tr = _record(seed=11)
    steps = detect_steps(tr)
    full = fit_whole_record(tr, steps, max_points=4000).report()
    t0 = steps[0].t_s
    keep = (tr.time_s >= t0 - 5.0) | (np.arange(len(tr)) % 10 == 0)
    thin = tr.__class__(time_s=tr.time_s[keep], position_um=tr.position_um[keep], friction_N=tr.friction_N[keep],
                        normal_1_N=tr.normal_1_N[keep], normal_2_N=tr.normal_2_N[keep], metadata=dict(tr.metadata))
    part = fit_whole_record(thin, detect_steps(thin), max_points=4000).report()
    for k in ("A_mu", "B_mu", "L_um"):
        assert abs(part["params"][k] - full["params"][k]) < 3 * part["params_sd"][k], k


def test_effective_n_of_correlated_noise():
    rng = np.random.default_rng(0)
    phi, n = 0.8, 20000
    e = rng.standard_normal(n)
    r = np.empty(n)
    r[0] = e[0]
    for i in range(1, n):
        r[i] = phi * r[i - 1] + e[i]
    tau = (1 + phi) / (1 - phi)  # 9 for AR(1)
    assert effective_n(r) == pytest.approx(n / tau, rel=0.25)
    assert effective_n(rng.standard_normal(n)) == pytest.approx(n, rel=0.1)
    # BIC: more parameters cost ln(n_eff) each
    assert information_criterion(1.0, 100, 50, 5) - information_criterion(1.0, 100, 50, 4) == \
        pytest.approx(math.log(50))


def test_cli_law_both_names_rsf_and_bad_uncertainty(tmp_path, both_laws):
    csv = tmp_path / "rec.csv"
    write_csv(_record(("aging_law",)), csv)
    out = tmp_path / "id.json"
    res = CliRunner().invoke(app, ["identify", str(csv), "--law", "both", "--names", "rsf", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert "preferred law: aging" in res.output and "Dc_um" in res.output
    rep = json.loads(out.read_text())
    assert rep["preferred_law"] == "aging" and set(rep["laws"]) == {"slip", "aging", "comparison"}
    for bad in ("bootstrap", "mcmc:5", "hessian"):
        res = CliRunner().invoke(app, ["identify", str(csv), "--uncertainty", bad])
        assert res.exit_code == 2 and "--uncertainty" in res.output and "Traceback" not in res.output


def test_import_map_and_scale(tmp_path):
    src = tmp_path / "lab.csv"
    src.write_text("# machine: biax\nTime,LP_disp,Shear\n0.0,0.000,20.0\n0.1,0.001,20.1\n0.2,0.002,20.0\n")
    out = tmp_path / "lab.mcap"
    res = CliRunner().invoke(app, ["import", str(src), "-o", str(out), "--map",
                                   "time_s=Time,position_um=LP_disp,friction_N=Shear", "--scale", "position_um=1000"])
    assert res.exit_code == 0, res.output
    from rig.log import load_trial

    tr = load_trial(out)
    assert np.allclose(tr.position_um, [0.0, 1.0, 2.0]) and np.allclose(tr.friction_N, [20.0, 20.1, 20.0])
    bad = tmp_path / "bad.mcap"
    for args in (["--map", "time_s=Tme,position_um=LP_disp,friction_N=Shear"], ["--map", "time_s"],
                 ["--map", "time_s=Time,position_um=LP_disp,friction_N=Shear", "--scale", "position_um=x"],
                 ["--map", "speed=Time"]):
        res = CliRunner().invoke(app, ["import", str(src), "-o", str(bad), *args])
        assert res.exit_code == 2 and "Traceback" not in res.output, args
        assert not bad.exists()
