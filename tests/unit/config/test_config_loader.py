"""The one configuration loader (rig.config.loader): YAML with a line for every node, strict
validation, model files validated by the class passed in."""

from __future__ import annotations

import time

import pytest
from pydantic import Field

from rig.config.loader import (MAX_DEPTH, ConfigError, StrictModel, field_error, fmt_loc, load_model_yaml,


                               parse_loc, parse_yaml, read_yaml, validate)


class Spec(StrictModel):
    baseline: str = "rate_state"
    params: dict[str, float] = Field(default_factory=dict)
    extensions: list[str] = Field(default_factory=list)


def test_model_file_with_wrapper_key(tmp_path):
    f = tmp_path / "m.yaml"
    f.write_text("friction_model:\n  baseline: rate_state\n  params:\n    mu0: 0.1\n    L_um: 1e1\n")
    m = load_model_yaml(f, Spec, key="friction_model")
    assert m.params == {"mu0": 0.1, "L_um": 10.0}
    f.write_text("friction_model:\n  baseline: rate_state\n  params:\n    mu0: 0.1\n    L_um: ten\n")
    with pytest.raises(ConfigError) as ei:
        load_model_yaml(f, Spec, key="friction_model")
    assert (ei.value.path, ei.value.field, ei.value.line) == (str(f), "friction_model.params.L_um", 5)
    f.write_text("baseline: rate_state\nparams: {mu0: 0.1}\nparams: {mu0: 0.2}\n")  # no wrapper, duplicate
    with pytest.raises(ConfigError, match="duplicate key 'params' .first at line 2, again at line 3"):
        load_model_yaml(f, Spec, key="friction_model")
    f.write_text("baseline: rate_state\nextension: [a]\n")
    with pytest.raises(ConfigError) as ei:
        load_model_yaml(f, Spec)
    assert ei.value.field == "extension" and ei.value.line == 2 and "unknown field" in str(ei.value)


def test_friction_model_file(tmp_path):
    """The real model class: what `rig diagnose --model-out` writes reads back, and a fault is placed."""
    from rig.model.spec import FrictionModel

    m = FrictionModel(extensions=["position_periodic"], params={"mu0": 0.1, "A_mu": 0.001, "B_mu": 0.004,
                                                                "L_um": 19.2, "wavelength_um": 50.0})
    m.to_yaml(tmp_path / "m.yaml")
    assert load_model_yaml(tmp_path / "m.yaml", FrictionModel, key="friction_model") == m
    text = (tmp_path / "m.yaml").read_text().replace("position_periodic", "position_periodik")
    (tmp_path / "m.yaml").write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_model_yaml(tmp_path / "m.yaml", FrictionModel, key="friction_model")
    assert ei.value.field == "friction_model.extensions" and "position_periodik" in str(ei.value)
    assert ei.value.line == text.splitlines().index("  extensions:") + 1


def test_every_node_has_a_line():
    doc = parse_yaml("a:\n  b: [1, 2]\n  c:\n    - x: 1\n    - y: 2\n", "t.yaml")
    assert doc.location(("a", "c", 1, "y")).line == 5
    assert doc.location(("a", "b", 1)).line == 2
    assert doc.location(("a", "missing")).line == 1   # a missing field: its parent
    assert fmt_loc(("a", "c", 1, "y")) == "a.c[1].y" and parse_loc("a.c[1].y") == ("a", "c", 1, "y")


def test_depth_limit_and_speed():
    ok = "a: " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1) + "\n"
    assert parse_yaml(ok).data["a"]
    for n in (MAX_DEPTH + 5, 5000, 50_000):
        t0 = time.perf_counter()
        with pytest.raises(ConfigError, match="nested deeper than"):
            parse_yaml("a: " + "{b: " * n + "1" + "}" * n + "\n")
        assert time.perf_counter() - t0 < 10.0


def test_recursive_alias_refused():
    with pytest.raises(ConfigError, match="nested deeper than|more than"):
        parse_yaml("a: &x [*x]\n")


def test_field_error_places_cross_field_checks(tmp_path):
    from pydantic import model_validator

    class Range(StrictModel):
        lo: float = 0
        hi: float = 1

        @model_validator(mode="after")
        def _order(self):
            if self.lo >= self.hi:
                raise field_error("hi", "must exceed lo")
            return self

    f = tmp_path / "r.yaml"
    f.write_text("lo: 5\n\nhi: 2\n")
    with pytest.raises(ConfigError) as ei:
        validate(Range, read_yaml(f))
    assert (ei.value.field, ei.value.line) == ("hi", 3) and "must exceed lo" in str(ei.value)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        read_yaml(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="directory"):
        read_yaml(tmp_path)
    (tmp_path / "bin.yaml").write_bytes(b"a: \xff\xfe\n")
    with pytest.raises(ConfigError, match="UTF-8"):
        read_yaml(tmp_path / "bin.yaml")
