"""PID and dither of rig.control against hand-computed values (paper, section 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.control import K_SAT, controller_step_v, make_controller_params, new_controller_state, pid_step


class _Pid:
    """The loop's PID kernel (:func:`rig.control.pid_step`) on its parameter and state arrays,
    without dither: what the tests drive tick by tick."""

    def __init__(self, kp, ki, kd, dt_s=1e-3, integral_max_N=500.0, output_max_N=1e4, ff1_N_s_per_um=0.0):
        self.c = make_controller_params(kp, ki, kd, dt_s, integral_max_N, output_max_N, 1e9,
                                        dither_amplitude_fraction=0.0, ff1_N_s_per_um=ff1_N_s_per_um)
        self.s = new_controller_state()

    def step(self, x_ref_um, x_meas_um, v_ref_um_s=math.nan):
        return pid_step(self.c, self.s, x_ref_um, x_meas_um, v_ref_um_s)

    @property
    def saturated(self):
        return self.s[K_SAT] != 0.0


def test_pid_terms_hand_computed():
    # kp = 2 N/µm, ki = 10 N/(µm s), kd = 0.01 N s/µm, dt = 1 ms
    pid = _Pid(2.0, 10.0, 0.01, dt_s=1e-3, integral_max_N=1e6, output_max_N=1e6)
    errors = [1.0, 3.0, -2.0, 0.5]
    outs = [pid.step(e, 0.0) for e in errors]
    # tick 0: P = 2, I = 0 (no prior errors), D = 0 (no previous error)
    assert outs[0] == pytest.approx((2.0, 2.0, 0.0, 0.0))
    # tick 1: P = 6, I = ki dt (1) = 0.01, D = kd (3 - 1)/dt = 20
    assert outs[1][1:] == pytest.approx((6.0, 0.01, 20.0))
    assert outs[1][0] == pytest.approx(26.01)
    # tick 2: I = 10 * 1e-3 * (1 + 3) = 0.04, D = 0.01 * (-5) / 1e-3 = -50
    assert outs[2][1:] == pytest.approx((-4.0, 0.04, -50.0))
    # tick 3: I = 0.01 * (1 + 3 - 2) = 0.02 (prior errors only), D = 0.01 * 2.5 / 1e-3 = 25
    assert outs[3][1:] == pytest.approx((1.0, 0.02, 25.0))


def test_pid_measured_position_sign():
    pid = _Pid(1.0, 0.0, 0.0)
    out, p, i, d = pid.step(10.0, 7.5)  # error = ref - measured = 2.5 µm
    assert p == pytest.approx(2.5) and out == pytest.approx(2.5)


def test_pid_output_clamp_and_saturated_flag():
    pid = _Pid(100.0, 0.0, 0.0, output_max_N=50.0)
    out, p, _, _ = pid.step(1.0, 0.0)
    assert p == pytest.approx(100.0)
    assert out == pytest.approx(50.0) and pid.saturated
    out, *_ = pid.step(-1.0, 0.0)
    assert out == pytest.approx(-50.0) and pid.saturated
    out, *_ = pid.step(0.1, 0.0)
    assert out == pytest.approx(10.0) and not pid.saturated


def test_pid_anti_windup_stops_integrating_while_saturated():
    pid = _Pid(10.0, 100.0, 0.0, dt_s=1e-3, output_max_N=5.0, integral_max_N=1e6)
    for _ in range(1000):
        pid.step(1.0, 0.0)  # P alone (10 N) saturates: the integral must not grow
    _, _, i_sat, _ = pid.step(1.0, 0.0)
    # the output saturated from the first tick on, so no error entered the sum
    assert i_sat == 0.0
    # an error of the opposite sign (output no longer saturated) integrates
    pid.step(-0.1, 0.0)
    _, _, i2, _ = pid.step(-0.1, 0.0)
    assert i2 == pytest.approx(-100.0 * 1e-3 * 0.1)
    # unsaturated, the integral after 1001 prior errors is 100 * 1e-3 * 1001
    free = _Pid(10.0, 100.0, 0.0, dt_s=1e-3, output_max_N=1e9, integral_max_N=1e9)
    for _ in range(1001):
        free.step(1.0, 0.0)
    assert free.step(1.0, 0.0)[2] == pytest.approx(100.0 * 1e-3 * 1001)


def test_pid_integral_clamp():
    pid = _Pid(0.0, 1000.0, 0.0, dt_s=1e-3, integral_max_N=3.0, output_max_N=1e9)
    for _ in range(100):
        out, _, i, _ = pid.step(1.0, 0.0)
    assert i == pytest.approx(3.0) and out == pytest.approx(3.0)


def _run_controller(c, n, err_fn):
    s = new_controller_state()
    out = np.empty((n, 5))
    for k in range(n):
        out[k] = controller_step_v(c, s, err_fn(k), 0.0, math.nan)
    return out


def test_dither_is_500hz_at_01_percent_of_pid_output_in_valve_command():
    ffs = 1000.0
    c = make_controller_params(2.0, 0.0, 0.0, 1e-3, full_scale_force_N=ffs, output_max_N=ffs,
                               dither_frequency_hz=500.0, dither_amplitude_fraction=1e-3,
                               dither_reference="pid_output", dither_smoothing_s=0.05)
    n = 4096
    out = _run_controller(c, n, lambda k: 10.0)  # constant PID output 20 N
    valve = out[:, 0]
    # steady part: valve = 20/1000 +- 0.001 * 20 / 1000 alternating
    tail = valve[2048:]
    spec = np.abs(np.fft.rfft(tail - tail.mean())) / tail.size
    freqs = np.fft.rfftfreq(tail.size, d=1e-3)
    k = int(np.argmax(spec))
    assert freqs[k] == pytest.approx(500.0)
    # at Nyquist the rfft bin holds the full amplitude (cos(pi n) = +-1)
    assert spec[k] == pytest.approx(1e-3 * 20.0 / ffs, rel=1e-3)
    assert spec[:k].max() < 1e-3 * spec[k]
    assert tail.mean() == pytest.approx(20.0 / ffs, rel=1e-4)
    # the dither reaches the valve at every tick (not sin(pi n) = 0)
    assert np.all(np.abs(out[2048:, 4]) == pytest.approx(0.02, rel=1e-3))


def test_dither_full_scale_mode_and_valve_saturation():
    c = make_controller_params(1e6, 0.0, 0.0, 1e-3, full_scale_force_N=100.0, output_max_N=1e9,
                               dither_amplitude_fraction=1e-3, dither_reference="full_scale")
    out = _run_controller(c, 10, lambda k: 0.0)
    assert np.allclose(np.abs(out[:, 4]), 0.1)  # 0.1 % of 100 N
    assert np.allclose(out[:, 0], out[:, 4] / 100.0)
    sat = _run_controller(c, 4, lambda k: 1.0)  # 1e6 N demand: valve saturates at +1
    assert np.all(sat[:, 0] == 1.0)


def test_ff1_velocity_feed_forward_hand_computed():
    """FF1 (LinuxCNC): ff1 x reference velocity, the backward difference of the reference
    unless the planner's velocity is given; 0 at the first tick; off by default."""
    pid = _Pid(0.0, 0.0, 0.0, dt_s=1e-3, ff1_N_s_per_um=0.05)
    assert pid.step(100.0, 100.0)[0] == pytest.approx(0.0)          # first tick: no velocity yet
    assert pid.step(100.002, 100.002)[0] == pytest.approx(0.05 * 2.0)  # 2 µm/s ramp
    assert pid.step(100.004, 100.004, v_ref_um_s=10.0)[0] == pytest.approx(0.5)  # planner's velocity
    off = _Pid(0.0, 0.0, 0.0, dt_s=1e-3)
    off.step(100.0, 100.0)
    assert off.step(100.002, 100.002)[0] == 0.0
    with pytest.raises(ValueError, match="ff1"):
        make_controller_params(1.0, 0.0, 0.0, 1e-3, ff1_N_s_per_um=-1.0)


def test_ff1_from_the_profile_reaches_the_controller():
    from rig.control import C_FF1, controller_params_from_profile
    from rig.config.profile import default_profile_path, load_profile

    prof = load_profile(default_profile_path())
    assert controller_params_from_profile(prof)[C_FF1] == 0.02  # sim.yaml: FF1 = k_h tau_L
    prof = prof.model_copy(update={"controller": prof.controller.model_copy(update={"ff1_N_s_per_um": 0.05})})
    assert controller_params_from_profile(prof)[C_FF1] == 0.05
    c, s = controller_params_from_profile(prof), new_controller_state()
    controller_step_v(c, s, 500.0, 500.0, math.nan)
    valve, _p, _i, _d, dither = controller_step_v(c, s, 500.001, 500.001, math.nan)
    # valve = (bias + ff1 x 1 µm/s + dither) / full scale
    assert valve * prof.actuator.full_scale_force_N == pytest.approx(0.05 + dither, abs=1e-9)
