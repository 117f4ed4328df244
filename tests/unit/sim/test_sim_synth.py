"""rig.sim.synth: the one synthetic-record generator, its sensors from the rig profile."""

from __future__ import annotations

import numpy as np
import pytest

from rig.model.spec import FrictionModel
from rig.config.profile import default_profile_path, load_profile
from rig.sim import synth


def test_sensor_chain_is_the_profiles():
    prof = load_profile(default_profile_path())
    ch = synth.SensorChain.from_profile(prof)
    # the paper's ±0.25 N / ±0.25 µm / ±0.6 N are 2 sigma in the profile
    assert ch.friction_sigma_N == prof.sensors.friction_load_cell.noise_sigma_N == 0.125
    assert ch.lvdt_sigma_um == prof.sensors.lvdt.noise_sigma_um
    assert ch.normal_sigma_N == prof.sensors.normal_load_cells.noise_sigma_N
    assert synth.SensorChain.from_profile(prof, noise_scale=2.0).friction_sigma_N == pytest.approx(0.25)


def test_readings_have_the_profiles_sigma_and_lvdt_grid():
    ch = synth.SensorChain.from_profile()
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 400.0, 1e-3)
    ts = t[::40]  # 25 Hz
    x, f, n1, n2 = synth.measure(t, np.full(t.size, 100.0), np.full(t.size, 22.0), np.full(t.size, 100.0),
                                 np.full(t.size, 100.0), ts, ch, rng)
    assert f.std() == pytest.approx(ch.friction_sigma_N, rel=0.05)
    assert n1.std() == pytest.approx(ch.normal_sigma_N, rel=0.08)
    assert np.allclose(x / ch.lvdt_quantization_um, np.round(x / ch.lvdt_quantization_um), atol=1e-9)
    assert x.std() == pytest.approx(np.hypot(ch.lvdt_sigma_um, ch.lvdt_quantization_um / np.sqrt(12)), rel=0.06)
    # white at 25 Hz (the 100 Hz filter's memory is 1.6 ms)
    assert abs(np.corrcoef(f[:-1], f[1:])[0, 1]) < 0.05


def test_both_protocol_front_ends_use_the_forward_model():
    m = FrictionModel(params={"mu0": 0.1, "A_mu": 0.0011, "B_mu": 0.004, "L_um": 19.2})
    rec = synth.generate(m, synth.paper_step_protocol(highs=(10.0,)), seed=1, chain=synth.SensorChain.from_profile()
                         .noiseless())
    # noiseless: the friction is mu (N1 + N2) of the forward model, through the 100 Hz filter only
    tr = rec.trial
    ratio = tr.friction_N / (tr.normal_1_N + tr.normal_2_N)
    assert np.max(np.abs(ratio - rec.truth["true_mu"])[50:]) < 2e-4
    trial, truth = synth.make_record(synth.SynthSpec(duration_s=200.0, seed=2,
                                                     effects={"position_periodic": {"amplitude_mu": 0.002,
                                                                                    "wavelength_um": 80.0,
                                                                                    "phase_rad": 0.0}}))
    assert "position_periodic" in truth["extensions"]
    assert trial.metadata["synthetic"] == "rig.sim.synth"
