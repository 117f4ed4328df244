"""Simulated plant: sensors, repeatability, sticking without NaN, implicit slip solve, extensions."""

from __future__ import annotations

import numpy as np
import pytest

from rig.model.spec import FrictionModel
from rig.model.sensors import lowpass_uneven
from rig.model.friction import mu_regularized, mu_series
from rig.sim.plant import BLOCK_KEYS, solve_slip
from rig.config.profile import load_profile
from rig.sim import SimRig


@pytest.fixture(scope="module")
def profile(repo_root):
    return load_profile(repo_root / "config" / "rigs" / "sim.yaml")


def _hold(rig, n, valve=0.0):
    rows = [rig.plant_step(valve) for _ in range(n)]
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def test_sensor_noise_and_quantization_at_rest(profile):
    rig = SimRig(profile, "boundary", seed=11)
    rig.reset(1234.5)
    d = _hold(rig, 20000)
    assert np.all(d["true_velocity_um_s"] == 0.0) and np.all(d["true_position_um"] == 1234.5)
    x = d["position_um"]
    q = profile.sensors.lvdt.quantization_um
    assert np.allclose(x / q, np.round(x / q), atol=1e-6)  # on the 0.076 µm grid
    sig_expected = np.hypot(profile.sensors.lvdt.noise_sigma_um, q / np.sqrt(12))
    assert x.std() == pytest.approx(sig_expected, rel=0.05)
    assert x.mean() == pytest.approx(1234.5, abs=0.01)
    f = d["friction_N"]
    assert f.std() == pytest.approx(profile.sensors.friction_load_cell.noise_sigma_N, rel=0.05)
    assert abs(f.mean()) < 0.01
    for i in (1, 2):
        n = d[f"normal_{i}_N"]
        assert n.std() == pytest.approx(profile.sensors.normal_load_cells.noise_sigma_N, rel=0.05)
        assert n.mean() == pytest.approx(d[f"true_normal_{i}_N"].mean(), abs=0.02)
    # the riders differ (static mismatch), both near 100 N
    assert abs(d["true_normal_1_N"][0] - d["true_normal_2_N"][0]) > 0.5
    assert 95 < d["true_normal_1_N"][0] < 105 and 95 < d["true_normal_2_N"][0] < 105
    # the noise enters before the 100 Hz analog filter (the hardware's order): at 1 kHz its
    # lag-1 autocorrelation is the filter's exp(-dt/tau) = 0.53, at the 25 Hz log it is white
    a = np.exp(-profile.dt_s * 2 * np.pi * profile.sensors.friction_load_cell.cutoff_hz)
    assert np.corrcoef(f[:-1], f[1:])[0, 1] == pytest.approx(a, abs=0.03)
    f25 = f[::40]
    assert abs(np.corrcoef(f25[:-1], f25[1:])[0, 1]) < 0.1


def test_lvdt_range_clips(profile):
    rig = SimRig(profile, "boundary", seed=0)
    rig.reset(profile.sensors.lvdt.max_um + 10.0)
    assert rig.plant_step(0.0)["position_um"] == profile.sensors.lvdt.max_um


def test_repeatable_for_a_seed_and_independent_of_block_size(profile):
    x = 1000.0 + 2.0 * np.arange(3000) / 1000.0
    a = SimRig(profile, "boundary", seed=5).run(x)
    blocks = list(SimRig(profile, "boundary", seed=5).run_blocks(x, block_ticks=37))
    assert all(set(b) == set(BLOCK_KEYS) for b in blocks)
    assert [b["t_s"].size for b in blocks[:2]] == [37, 37] and blocks[-1]["t_s"].size == 3000 % 37
    b = {k: np.concatenate([blk[k] for blk in blocks]) for k in BLOCK_KEYS}
    for k in BLOCK_KEYS:
        assert np.array_equal(a[k], b[k]), k
    c = SimRig(profile, "boundary", seed=6).run(x)
    assert not np.array_equal(a["position_um"], c["position_um"])
    assert np.allclose(a["t_s"], np.arange(3000) * 1e-3)


def test_no_nan_at_zero_velocity_and_while_holding(profile):
    a_zero = FrictionModel(params={"mu0": 0.12, "A_mu": 0.0, "B_mu": 0.0111, "L_um": 22.4})  # Table 2 paraffin
    for lub in ("dry", "paraffin", "boundary", a_zero):
        rig = SimRig(profile, lub, seed=0)
        d = _hold(rig, 200, valve=0.0)  # at rest, no force: v = 0 exactly
        assert np.all(np.isfinite(np.column_stack([d[k] for k in d])))
        assert np.all(d["true_velocity_um_s"] == 0.0) and np.all(d["true_mu"] == 0.0)
        # closed loop holding a position for 5 s, then a move and a hold again
        x = np.concatenate([np.full(5000, 800.0), 800.0 + 5.0 * np.arange(2000) / 1000.0, np.full(3000, 810.0)])
        r = rig.run(x)
        for k in BLOCK_KEYS:
            assert np.all(np.isfinite(r[k])), (lub, k)
        assert abs(r["true_position_um"][-1] - 810.0) < 1.0


def test_solve_slip_residual_and_monotone():
    base, a, v0, vreg, ntot, q2 = 0.1, 1.1e-3, 1.0, 0.01, 200.0, -5e-4
    ps = np.concatenate([-np.logspace(-3, 3, 40)[::-1], [0.0], np.logspace(-3, 3, 40)]) + 0.0
    ps = np.concatenate([ps, 200 * 0.1 + np.linspace(-1, 1, 41)])
    prev = None
    for p2 in np.sort(ps):
        v, mu = solve_slip(p2, q2, ntot, base, a, v0, vreg)
        assert np.isfinite(v) and np.isfinite(mu)
        assert mu == pytest.approx(mu_regularized(v, base, 0.0, a, v0, vreg), rel=1e-9, abs=1e-15)
        assert p2 + q2 * v - ntot * mu == pytest.approx(0.0, abs=1e-9 * max(1.0, abs(p2)))
        if prev is not None:
            assert v >= prev
        prev = v
    # a force below friction gives a tiny creep, not slip
    v, _ = solve_slip(15.0, q2, ntot, base, a, v0, vreg)
    assert 0 < v < 1e-6
    # A = 0 (paraffin): smooth sign, spring-limited slip above friction
    v, mu = solve_slip(30.0, q2, ntot, base, 0.0, v0, vreg)
    assert 0 < mu < base and 30.0 + q2 * v == pytest.approx(ntot * mu, rel=1e-9)


def _linear_valve(profile):
    return profile.model_copy(update={"servovalve": profile.servovalve.model_copy(update={"stiction_band_cmd": 0.0})})


def test_force_offset_drift_and_sensor_lag(profile):
    profile = _linear_valve(profile)  # a constant open-loop command: no spool play (sim.yaml has 5e-4)
    fm = profile.friction_model("boundary").model_copy(
        update={"extensions": ["force_offset_drift", "sensor_lag"], "params": {
            **profile.friction_model("boundary").params, "rate_N_per_s": 0.5, "tau_s": 0.2}})
    rig = SimRig(profile, fm, seed=0)
    ffs = profile.actuator.full_scale_force_N
    d = _hold(rig, 1000, valve=10.0 / ffs)  # 10 N: below static friction (~20 N), stuck
    t = d["t_s"]
    assert d["true_friction_N"][-1] == pytest.approx(10.0, rel=1e-3)
    assert abs(d["true_velocity_um_s"][-1]) < 1e-6
    # measured = first-order lag (0.2 s) of the true friction (+ the 100 Hz cell) + drift
    expected = lowpass_uneven(t, d["true_friction_N"], 0.2) + 0.5 * t
    i = np.searchsorted(t, 0.2)
    assert np.mean(d["friction_N"][i - 20:i + 20]) == pytest.approx(np.mean(expected[i - 20:i + 20]), abs=0.1)
    assert np.mean(d["friction_N"][-50:]) == pytest.approx(np.mean(expected[-50:]), abs=0.1)
    assert np.mean(d["friction_N"][-50:]) > 10.0 + 0.4  # the drift shows after 1 s
    plain = SimRig(profile, "boundary", seed=0)
    e = _hold(plain, 1000, valve=10.0 / ffs)
    assert np.mean(e["friction_N"][i - 20:i + 20]) == pytest.approx(np.mean(e["true_friction_N"][i - 20:i + 20]),
                                                                     abs=0.1)


def test_finite_stiffness_replaces_the_fixture_compliance_between_lvdt_and_interface(profile):
    profile = _linear_valve(profile)  # a constant open-loop command: no spool play (sim.yaml has 5e-4)
    base = profile.friction_model("boundary")
    fm = base.model_copy(update={"extensions": ["finite_stiffness"],
                                 "params": {**base.params, "stiffness_kN_per_m": 1000.0}})
    ffs = profile.actuator.full_scale_force_N
    shifts = []
    for model in (base, fm):
        rig = SimRig(profile, model, seed=0)
        rig.reset(1000.0)
        d = _hold(rig, 500, valve=10.0 / ffs)
        shifts.append(d["true_position_um"][-1] - 1000.0)
    k_fx = profile.fixture.fixture_stiffness_N_per_um
    assert shifts[0] == pytest.approx(10.0 / k_fx, rel=0.02)           # fixture only
    # the model's 1 N/µm replaces the fixture's compliance (rig.model.loading), it does not add to it
    assert shifts[1] == pytest.approx(10.0 / 1.0, rel=0.02)


def test_time_delay_uses_the_velocity_delay_s_ago(profile):
    # |mu| = mu_ss(v(t - delay)) (log argument held at v_reg), the sign that of v(t); at this
    # rig's stiffness a 0.1 s delay makes sliding unstable (phase shift >> pi, section 2.2),
    # so the test checks the law on whatever motion results
    c, delay_s, mu0 = 0.003, 0.1, 0.1
    fm = FrictionModel(baseline="steady_state", extensions=["time_delay"],
                       params={"mu0": mu0, "c_mu": c, "delay_s": delay_s})
    rig = SimRig(profile, fm, seed=0)
    x = 1000 + 2.0 * np.arange(20000) / 1000.0
    r = rig.run(x)
    v, mu = r["true_velocity_um_s"], r["true_mu"]
    assert np.all(np.isfinite(mu)) and np.all(np.isfinite(v))
    d = int(round(delay_s * 1000))
    vreg = fm.v_reg_um_s
    j = np.arange(d + 2, v.size)
    expected = (mu0 + c * np.log(np.maximum(np.abs(v[j - d]), vreg))) * v[j] / np.hypot(v[j], vreg)
    assert np.allclose(mu[j], expected, rtol=1e-9, atol=1e-12)
    assert np.ptp(v[5000:]) > 1.0  # it moves (the law is exercised over a range of speeds)


def test_steady_state_positive_slope_model(profile):
    fm = FrictionModel(baseline="steady_state", params={"mu0": 0.1, "c_mu": 0.003})
    rig = SimRig(profile, fm, seed=0)
    n1 = 20000
    x = np.concatenate([1000 + np.arange(n1) / 1000.0, 1020 + 10.0 * np.arange(1, 5001) / 1000.0])
    r = rig.run(x)
    assert r["true_mu"][n1 - 1000:n1].mean() == pytest.approx(0.1, abs=2e-4)
    assert r["true_mu"][-1000:].mean() == pytest.approx(0.1 + 0.003 * np.log(10.0), abs=2e-4)


def test_normal_forces_vary_along_the_test_piece(profile):
    rig = SimRig(profile, "boundary", seed=0)
    x = 500.0 + 100.0 * np.arange(30000) / 1000.0  # 3 mm at 100 µm/s
    r = rig.run(x)
    for k in ("normal_1_N", "normal_2_N"):
        sm = np.convolve(r[k], np.ones(500) / 500, mode="valid")
        rel = (sm.max() - sm.min()) / sm.mean()
        assert 0.002 < rel < 0.05, (k, rel)  # varies, within the paper's 5 %


def test_bad_inputs_raise_clear_errors(profile):
    with pytest.raises(ValueError, match="normal_force_N"):
        SimRig(profile, "boundary", normal_force_N=0.0)
    with pytest.raises(ValueError, match="unknown lubricant"):
        SimRig(profile, "graphite")
    rig = SimRig(profile, "boundary")
    with pytest.raises(ValueError, match="outside the LVDT range"):
        next(rig.run_blocks(np.array([100.0, 6000.0])))
    with pytest.raises(ValueError, match="NaN"):
        next(rig.run_blocks(np.array([100.0, np.nan])))
    with pytest.raises(ValueError, match="finite"):
        rig.plant_step(float("nan"))


def test_normal_force_override(profile):
    rig = SimRig(profile, "boundary", normal_force_N=50.0, seed=0)
    d = rig.plant_step(0.0)
    assert d["true_normal_1_N"] + d["true_normal_2_N"] == pytest.approx(100.0, rel=0.01)


@pytest.mark.parametrize("extensions", [[], ["second_state_variable", "position_periodic", "slip_wear_drift"],
                                        ["second_state_variable", "aging_law"]])
def test_simulated_mu_is_the_shared_friction_model(profile, extensions, tmp_path):
    """The analysis' forward model (rig.model.friction.mu_series) on the simulation's true
    kinematics reproduces the simulation's true mu: one friction model for both."""
    fm = FrictionModel(extensions=extensions, params={
        "mu0": 0.1, "A_mu": 0.0011, "B_mu": 0.004, "L_um": 19.2, "B2_mu": 0.002, "L2_um": 80.0,
        "amplitude_mu": 0.002, "wavelength_um": 100.0, "phase_rad": 0.3, "rate_mu_per_mm": 0.003})
    fm.to_yaml(tmp_path / "model.yaml")  # as `rig run --sim --friction-model` reads it
    fm = FrictionModel.from_yaml(tmp_path / "model.yaml")
    n1, n2 = 60000, 15000
    x = np.concatenate([1000 + np.arange(n1) / 1000.0, 1060 + 10.0 * np.arange(1, n2 + 1) / 1000.0])
    r = SimRig(profile, fm, seed=0).run(x)
    # position-periodic friction acts at the interface: x0 + slip (each tick reports the slip
    # velocity of the tick before it)
    v = r["true_velocity_um_s"]
    x_interface = x[0] + np.concatenate([[0.0], np.cumsum(v[1:])]) * profile.dt_s
    mu_fwd = mu_series(fm.to_array(), r["t_s"], v, x_interface, 1.0)
    diff = np.abs(mu_fwd - r["true_mu"])[10000:]  # after the initial loading
    assert diff.max() < 2e-5  # 2 % of A; the step's jump is 2.5e-3


def test_lvdt_filter_lag_is_the_100hz_time_constant(profile):
    """A ramp through a first-order 100 Hz filter lags by tau = 1/(2 pi 100 Hz) = 1.59 ms."""
    v = 100.0
    x = 500.0 + v * np.arange(20000) / 1000.0
    r = SimRig(profile, "boundary", seed=2).run(x)
    lag_um = (r["true_position_um"] - r["position_um"])[5000:].mean()
    tau = 1.0 / (2 * np.pi * profile.sensors.lvdt.cutoff_hz)
    assert lag_um == pytest.approx(v * tau, abs=0.01)
