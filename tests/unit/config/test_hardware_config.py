"""The shipped emulated profile and smoke recipe validate; bad hardware sections are named;
the device configs are one class each and import nothing from rig."""

from __future__ import annotations

import ast

import pytest

from drivers.config import HardwareConfigError, hardware_of_profile, parse_hardware


def test_emulated_profile_validates(repo_root):
    from rig.config.profile import load_profile

    p = load_profile(repo_root / "config/rigs/emulated.yaml")
    hw = hardware_of_profile(p)
    assert hw is p.hardware  # typed at load time, not validated later
    assert hw.loadcells.transport == "tcp" and hw.valve.interface == "rig_unix"
    assert hw.emulators.autostart
    assert hw.lvdt.um_per_count == p.sensors.lvdt.quantization_um == pytest.approx(0.076)
    # (that its plant is sim.yaml's: tests/unit/config/test_sim_profile.py::test_emulated_is_an_overlay_of_sim)


def test_smoke_recipe_validates_and_compiles(repo_root):
    from rig.config.profile import load_profile
    from rig.config.recipe import load_recipe
    from rig.config.recipe import compile_recipe

    r = load_recipe(repo_root / "config/recipes/smoke.yaml")
    plan = compile_recipe(r, load_profile(repo_root / "config/rigs/emulated.yaml"))
    assert 15.0 <= plan.duration_s <= 25.0
    assert plan.events_of("velocity_step")[0]["run_up_L"] == pytest.approx(6.0)


def test_bad_hardware_section_names_the_field():
    with pytest.raises(HardwareConfigError) as ei:
        parse_hardware({"loadcells": {"port": "x"}, "lvdt": {}, "valve": {}}, where="rig.yaml: hardware")
    assert "rig.yaml: hardware.loadcells.port" in str(ei.value)
    with pytest.raises(HardwareConfigError) as ei:
        parse_hardware({"loadcells": {"transport": "rtu"}, "lvdt": {}, "valve": {}})
    assert "serial_port" in str(ei.value)
    with pytest.raises(HardwareConfigError) as ei:
        parse_hardware(None, where="sim.yaml: hardware")
    assert "no 'hardware' section" in str(ei.value)


def test_span_covers_all_registers_in_one_request():
    hw = parse_hardware({"loadcells": {}, "lvdt": {}, "valve": {}})
    assert hw.loadcells.span() == (0, 8)


def test_device_configs_import_nothing_from_rig(repo_root):
    tree = ast.parse((repo_root / "drivers" / "config.py").read_text())
    mods = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    mods += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in mods if m == "rig" or m.startswith("rig.")]


def test_one_class_per_device_config():
    """LvdtConfig / LoadCellConfig exist once (the devices); the profile's sensor-chain
    parameters have their own names, and every config model has the one strict base."""
    import drivers.config as dc
    import rig.config.profile as prof
    import rig.config.recipe as rec
    from rig.config.loader import StrictModel

    assert not hasattr(prof, "LvdtConfig") and not hasattr(prof, "LoadCellConfig")
    assert prof.SensorsConfig.model_fields["lvdt"].annotation is prof.LvdtSignal
    assert prof.RigProfile.model_fields["hardware"].annotation == (dc.HardwareConfig | None)
    for mod in (dc, prof, rec):
        for name, obj in vars(mod).items():
            if isinstance(obj, type) and obj.__module__ == mod.__name__ and hasattr(obj, "model_fields"):
                assert issubclass(obj, StrictModel), name
