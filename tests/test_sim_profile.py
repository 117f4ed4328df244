"""Rig profile loading: the shipped sim.yaml, and errors that name file, field and line."""

from __future__ import annotations

import numpy as np
import pytest

from rig.model.paper import TABLE2
from rig.profile import ProfileError, RigProfile, load_profile


def test_sim_yaml_loads_with_paper_values(repo_root):
    p = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    assert isinstance(p, RigProfile)
    assert p.loop.rate_hz == 1000.0
    assert p.controller.dither_frequency_hz == 500.0
    assert p.controller.dither_amplitude_fraction == pytest.approx(1e-3)
    assert p.sensors.lvdt.quantization_um == pytest.approx(0.076)
    assert p.sensors.lvdt.max_um - p.sensors.lvdt.min_um == pytest.approx(5000.0)
    assert p.sensors.normal_load_cells.cutoff_hz == 10.0
    assert p.normal.nominal_force_N == 100.0
    assert p.fixture.test_piece_stiffness_N_per_um >= 1.0 and p.fixture.fixture_stiffness_N_per_um >= 10.0
    for name, row in TABLE2.items():
        lp = p.lubricants[name]
        assert (lp.B_mu, lp.L_um) == pytest.approx((row["B_mu"][0], row["L_um"][0]))
        # paraffin: Table 2's A = 0.0* means "below the load-cell noise" -> a small A is used
        assert lp.A_mu == pytest.approx(row["A_mu"][0], abs=1e-4 if name != "paraffin" else 3e-4)
        # a velocity-step jump 2 N A ln 10 below the ±0.25 N noise for paraffin
        if name == "paraffin":
            assert 0 < 2 * 100 * lp.A_mu * np.log(10) < 0.25
        fm = p.friction_model(name)
        assert fm.get("B_mu") == pytest.approx(row["B_mu"][0])
        assert fm.mu_ss(1.0) == pytest.approx(lp.mu0)
    # Table 2's k_cr uses N per rider (eq. 13)
    assert p.k_cr_N_per_um("boundary", total=False) * 1000 == pytest.approx(14.8, abs=0.5)
    assert p.actuator.hydraulic_stiffness_N_per_um == pytest.approx(10.0)


def _write(tmp_path, text):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    return f


def test_unknown_field_names_file_field_and_line(tmp_path):
    f = _write(tmp_path, "name: x\ncontroller:\n  kp_N_per_um: 1.0\n  kp: 2.0\n")
    with pytest.raises(ProfileError) as ei:
        load_profile(f)
    e = ei.value
    assert e.field == "controller.kp" and e.line == 4
    assert str(f) in str(e) and "line 4" in str(e) and "controller.kp" in str(e)


def test_bad_value_names_field_and_line(tmp_path):
    f = _write(tmp_path, "loop:\n  rate_hz: 1000\nactuator:\n  moving_mass_kg: -3\n")
    with pytest.raises(ProfileError) as ei:
        load_profile(f)
    assert ei.value.field == "actuator.moving_mass_kg" and ei.value.line == 4
    f = _write(tmp_path, "lubricants:\n  dry: {mu0: 0.1, A_mu: 0.001, B_mu: zero, L_um: 10}\n")
    with pytest.raises(ProfileError) as ei:
        load_profile(f)
    assert ei.value.field == "lubricants.dry.B_mu" and ei.value.line == 2


def test_invalid_yaml_and_missing_file(tmp_path):
    f = _write(tmp_path, "loop:\n  rate_hz: [1000\n")
    with pytest.raises(ProfileError) as ei:
        load_profile(f)
    assert ei.value.line is not None and "invalid YAML" in str(ei.value)
    with pytest.raises(ProfileError, match="cannot read"):
        load_profile(tmp_path / "nope.yaml")


def test_unknown_lubricant():
    with pytest.raises(ValueError, match="unknown lubricant"):
        RigProfile().friction_model("graphite")
