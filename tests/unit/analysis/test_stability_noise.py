"""The LVDT's noise through the linearised discrete loop (rig.analysis.stability.noise_spread):
what the noisy scan's spread criterion measures on a stable rig (docs/paper.md, the stability
statement). Checked against the full simulated rig (rig.sim) at a quarter of the profile's
noise, where the response stays small enough to be linear."""

from __future__ import annotations

import math

import pytest
import yaml

from rig.analysis import stability as S
from rig.config.profile import default_profile_path, load_profile


@pytest.fixture(scope="module")
def prof():
    return load_profile(default_profile_path())


def _lm(prof, lub, ki):
    return S.LoopModel.from_profile(prof, prof.friction_model(lub), ki_N_per_um_s=ki)


def test_noise_spread_is_linear_in_the_noise_and_infinite_below_k_cr(prof):
    lm = _lm(prof, "paraffin", prof.controller.ki_N_per_um_s)
    k = S.k_cr_loop(lm)
    s1 = S.noise_spread(lm, 1.5 * k, 0.125, 0.076)
    assert s1 > 0.1
    assert S.noise_spread(lm, 1.5 * k, 0.0625, 0.038) == pytest.approx(0.5 * s1, rel=1e-6)
    assert S.noise_spread(lm, 1.5 * k, 0.0, 0.0) == 0.0
    assert math.isinf(S.noise_spread(lm, 0.95 * k, 0.125, 0.076))
    # closer to k_cr the lightly damped mode rings longer: more spread
    assert S.noise_spread(lm, 1.1 * k, 0.125, 0.076) > s1


def test_pid_noise_criterion_lies_far_above_k_cr_and_pd_on_it(prof):
    """PID: the I-friction mode is lightly damped above k_cr, so the rig's LVDT noise keeps
    the spread above the criterion's 0.3 V0 well beyond k_cr; PD has no such mode."""
    sig, qz = prof.sensors.lvdt.noise_sigma_um, prof.sensors.lvdt.quantization_um
    for lub in ("paraffin", "boundary"):
        pid = _lm(prof, lub, prof.controller.ki_N_per_um_s)
        assert S.k_noise_criterion(pid, sig, qz) > 1.3 * S.k_cr_loop(pid)
        pd = _lm(prof, lub, 0.0)
        assert S.k_noise_criterion(pd, sig, qz) == pytest.approx(S.k_cr_loop(pd), rel=0.01)


def test_noise_spread_matches_the_simulated_rig_at_a_quarter_of_the_noise(prof, tmp_path):
    path = tmp_path / "quarter.yaml"
    lv = prof.sensors.lvdt
    path.write_text(yaml.safe_dump({"extends": str(default_profile_path()), "name": "quarter-noise",
                                    "sensors": {"lvdt": {"noise_sigma_um": lv.noise_sigma_um / 4,
                                                         "quantization_um": lv.quantization_um / 4}}}))
    q = load_profile(path)
    ki, kd = q.controller.ki_N_per_um_s, q.controller.kd_N_s_per_um
    lm = _lm(q, "paraffin", ki)
    k = S.k_cr_loop(lm)
    for f in (1.3, 2.0):
        sim = S.sliding_run(str(path), "paraffin", f * k, ki, kd, 300.0, seed=0, bump_L=0.0)["spread"]
        lin = S.noise_spread(lm, f * k, q.sensors.lvdt.noise_sigma_um, q.sensors.lvdt.quantization_um)
        assert sim == pytest.approx(lin, rel=0.15), (f, sim, lin)
