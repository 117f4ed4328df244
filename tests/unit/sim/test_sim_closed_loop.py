"""Closed-loop behaviour of the simulated rig against the paper (sections 2.1, 3, 4.2)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import curve_fit

from rig.model.paper import k_cr_eq8
from rig.config.profile import load_profile
from rig.sim import SimRig


FS = 1000


@pytest.fixture(scope="module")
def profile(repo_root):
    return load_profile(repo_root / "config" / "rigs" / "sim.yaml")


@pytest.fixture(scope="module")
def velocity_step(profile):
    """Boundary lubricant: 1 µm/s for 150 µm, then 10 µm/s for 250 µm (paper, section 4.2)."""
    v1, v2 = 1.0, 10.0
    n1, n2 = int(150 / v1 * FS), int(250 / v2 * FS)
    x0 = 1000.0
    x = np.concatenate([x0 + v1 * np.arange(n1) / FS, x0 + 150 + v2 * np.arange(1, n2 + 1) / FS])
    r = SimRig(profile, "boundary", seed=3).run(x)
    return r, n1, v1, v2


def test_lvdt_tracks_the_reference(velocity_step):
    r, n1, *_ = velocity_step
    e_meas = r["position_ref_um"] - r["position_um"]
    e_true = r["position_ref_um"] - r["true_position_um"]
    for sl in (slice(20 * FS, n1), slice(n1 + FS, None)):  # after the initial loading / the step
        # within the paper's +-0.5 µm (integral gain criterion), noise included
        assert abs(e_meas[sl].mean()) < 0.05
        assert e_meas[sl].std() < 0.2
        assert np.abs(e_true[sl]).max() < 0.6
    # during the step transient the error stays a few µm (paper: rise < 0.5 s, < 5 µm)
    assert np.abs(e_true[n1:n1 + FS]).max() < 5.0


def test_friction_jump_and_decay_match_table2_parameters(velocity_step, profile):
    r, n1, v1, v2 = velocity_step
    lp = profile.lubricants["boundary"]
    f = r["friction_N"]
    n_mean = 0.5 * (r["normal_1_N"] + r["normal_2_N"]).mean()
    lnr = np.log(v2 / v1)
    f1 = f[n1 - 50 * FS:n1].mean()            # last 50 µm before the step
    f2 = f[-50 * FS // 10:].mean()            # last 50 µm at 10 µm/s
    fsm = np.convolve(f, np.ones(50) / 50, mode="same")
    imax = n1 + int(np.argmax(fsm[n1:n1 + 3 * FS]))
    fmax = fsm[imax]
    # eq. (10): direct effect, f_max - f1 = 2 N A ln(v2/v1) (0.51 N), within 20 %
    assert (fmax - f1) == pytest.approx(2 * n_mean * lp.A_mu * lnr, rel=0.2)
    # eqs. (7), (11): new steady state, f2 - f1 = 2 N (A - B) ln(v2/v1) (-1.34 N), within 8 %
    assert (f2 - f1) == pytest.approx(2 * n_mean * (lp.A_mu - lp.B_mu) * lnr, rel=0.08)
    # eq. (12): exponential decay over the slip distance L, within 20 %
    x = r["position_um"]
    d = x[imax:] - x[imax]
    popt, _ = curve_fit(lambda d, a, L, c: c + a * np.exp(-d / L), d, f[imax:], p0=(0.5, 20.0, f2))
    assert popt[1] == pytest.approx(lp.L_um, rel=0.2)
    # the peak comes within a few µm of the step (velocity rise < 5 µm, section 4.2)
    assert x[imax] - x[n1] < 5.0
    # the noiseless truth: steady-state mu before and after the step (eq. 7)
    mu = r["true_mu"]
    assert mu[n1 - FS:n1].mean() == pytest.approx(lp.mu0, abs=2e-4)
    assert mu[-FS:].mean() == pytest.approx(lp.mu0 + (lp.A_mu - lp.B_mu) * lnr, abs=2e-4)


def test_dither_not_detectable_in_lvdt(velocity_step, profile):
    r, n1, *_ = velocity_step
    seg = slice(n1 - 8192, n1)
    x = r["true_position_um"][seg]
    x = x - np.polyval(np.polyfit(np.arange(x.size), x, 1), np.arange(x.size))
    amp500 = np.abs(np.fft.rfft(x))[-1] / x.size  # Nyquist bin: full amplitude
    # far below the LVDT's 0.25 µm resolution (paper, section 3)
    assert amp500 < 0.01
    # while the valve command carries it at 0.1 % of the PID output's range (the profile's
    # dither_reference: full_scale, 10 N), alternating sign
    ffs = profile.actuator.full_scale_force_N
    pid = (r["pid_p"] + r["pid_i"] + r["pid_d"])[seg]
    dz = r["dither"][seg]
    ff = profile.controller.ff1_N_s_per_um * np.diff(r["position_ref_um"], prepend=r["position_ref_um"][0])[seg] * FS
    assert np.allclose(r["valve_cmd"][seg] * ffs - pid - ff, dz, atol=1e-6)
    assert np.abs(dz).mean() == pytest.approx(1e-3 * ffs, rel=0.02)
    assert np.all(np.sign(dz[1:]) == -np.sign(dz[:-1]))


def _constant_velocity_run(profile, kp, v=5.0, seconds=80.0, lubricant="boundary"):
    """P(D) control with the friction force as bias (no integral), as in the k_cr analysis."""
    p = profile.model_copy(deep=True)
    lp = p.lubricants[lubricant]
    p.controller.kp_N_per_um = kp
    p.controller.ki_N_per_um_s = 0.0
    p.controller.bias_N = 2 * p.normal.nominal_force_N * lp.mu0
    n = int(seconds * FS)
    x = 1500.0 + v * np.arange(n) / FS
    r = SimRig(p, lubricant, seed=1).run(x)
    return r["true_velocity_um_s"][n // 2:], r


def test_stick_slip_below_critical_stiffness_not_above(profile):
    lp = profile.lubricants["boundary"]
    n_tot = 2 * profile.normal.nominal_force_N  # both interfaces act on the test piece
    k_cr13 = (lp.B_mu - lp.A_mu) * n_tot / lp.L_um  # eq. (13) with the total normal force, N/µm
    # eq. (8) with the rig's damping (D gain + leaky actuator) at 5 µm/s, for reference
    k_v = profile.controller.kd_N_s_per_um + profile.actuator.hydraulic_damping_N_s_per_um  # N s/µm
    k_cr8 = k_cr_eq8(lp.A_mu * n_tot, lp.B_mu * n_tot, lp.L_um * 1e-6, profile.actuator.moving_mass_kg,
                     k_v * 1e6, 5e-6) * 1e-6
    assert 0.5 * k_cr13 < k_cr8 < k_cr13
    v = 5.0
    slow, r = _constant_velocity_run(profile, 0.25 * k_cr13, v)
    assert np.all(np.isfinite(slow))
    assert slow.max() > 5 * v and slow.min() < 0.3 * v           # stick-slip
    fast, _ = _constant_velocity_run(profile, 4.0 * k_cr13, v)
    lo, hi = np.percentile(fast, [0.5, 99.5])
    assert 0.5 * v < lo and hi < 1.5 * v                          # steady sliding (noise only)


def test_dither_overcomes_spool_stiction(profile):
    """A spool stiction band makes the loop hunt; a dither larger than the band removes it
    (paper, section 3). 0.1 % of the PID output (0.02 N here) is far below a 2 N band;
    0.1 % of full scale (10 N) is above it."""
    x = 1000 + 1.0 * np.arange(40 * FS) / FS
    errs = {}
    for label, frac, ref in (("none", 0.0, "pid_output"), ("full_scale", 1e-3, "full_scale")):
        p = profile.model_copy(deep=True)
        p.servovalve.stiction_band_cmd = 2e-4
        p.controller.dither_amplitude_fraction = frac
        p.controller.dither_reference = ref
        r = SimRig(p, "boundary", seed=0).run(x)
        errs[label] = (r["position_ref_um"] - r["true_position_um"])[20 * FS:].std()
    assert errs["none"] > 0.3          # hunting: µm-scale limit cycle
    assert errs["full_scale"] < 0.05   # smooth tracking
