"""Recipe validation: one RecipeError naming the file, the field path and the line."""

from __future__ import annotations

import textwrap

import pytest

from rig.config.recipe import (DEFAULT_PASS_VELOCITIES_UM_S, RecipeError, SteppedPass, VelocitySteps, load_recipe,


                        parse_recipe)

GOOD = textwrap.dedent("""\
    name: t
    lubricant: boundary
    normal_force_N: 100
    segments:
      - kind: hold
        duration_s: 1
      - kind: velocity_steps
        steps:
          - v1_um_s: 1
            v2_um_s: 2
      - kind: stepped_pass
      - kind: move
        position_um: 500
        speed_um_s: 50
    """)


def write(tmp_path, text, name="r.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_shipped_recipes_load(repo_root):
    names = set()
    for p in sorted((repo_root / "config" / "recipes").glob("*.yaml")):
        r = load_recipe(p)
        names.add(r.name)
        assert r.source_text and r.source_path == str(p)
    assert {"run-in", "stribeck-pass", "velocity-steps"} <= names


def test_good_recipe_defaults(tmp_path):
    r = load_recipe(write(tmp_path, GOOD))
    assert r.log.decimated_rate_hz == 25 and r.log.raw_rate_hz == 1000
    sp = r.segments[2]
    assert isinstance(sp, SteppedPass)
    assert tuple(sp.velocities_um_s) == DEFAULT_PASS_VELOCITIES_UM_S and len(sp.velocities_um_s) == 7
    assert sp.pass_um == 3500 and sp.level_um == 250 and sp.window_um == 50
    assert sp.levels_um_s() == list(DEFAULT_PASS_VELOCITIES_UM_S) + list(DEFAULT_PASS_VELOCITIES_UM_S[::-1])
    assert isinstance(r.segments[1], VelocitySteps)


@pytest.mark.parametrize("old,new,field,line", [
    ("v2_um_s: 2", "v2_um_s: -2", "segments[1].steps[0].v2_um_s", 10),
    ("duration_s: 1", "duration_z: 1", "segments[0].duration_s", 5),  # missing -> the segment's line
    ("lubricant: boundary", "lubricant: \"\"", "lubricant", 2),  # a free name (issue 21), not an empty one
    ("speed_um_s: 50", "speed_um_s: fast", "segments[3].speed_um_s", 14),
    ("  - kind: stepped_pass", "  - kind: stepped_pas", "segments[2]", 11),
    ("normal_force_N: 100", "normal_force_N: .nan", "normal_force_N", 3),
])
def test_errors_name_file_field_line(tmp_path, old, new, field, line):
    assert old in GOOD
    p = write(tmp_path, GOOD.replace(old, new))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    e = ei.value
    assert e.field == field
    assert e.line == line
    msg = str(e)
    assert str(p) in msg and f"line {line}" in msg and field in msg


def test_unknown_field_is_an_error(tmp_path):
    p = write(tmp_path, GOOD.replace("  - kind: hold\n", "  - kind: hold\n    speed: 3\n"))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    assert ei.value.field == "segments[0].speed" and ei.value.line == 6
    assert "unknown field" in str(ei.value)


def test_yaml_syntax_error_has_line(tmp_path):
    p = write(tmp_path, GOOD.replace("speed_um_s: 50", "speed_um_s: [50"))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    assert "YAML syntax" in str(ei.value) and ei.value.line is not None and ei.value.line >= 14


@pytest.mark.parametrize("text", ["", "- just\n- a list\n"])
def test_empty_or_not_mapping(tmp_path, text):
    with pytest.raises(RecipeError) as ei:
        load_recipe(write(tmp_path, text))
    assert ei.value.line == 1


def test_missing_file(tmp_path):
    with pytest.raises(RecipeError, match="no such file"):
        load_recipe(tmp_path / "nope.yaml")


def test_stepped_pass_geometry_rules():
    base = "name: x\nlubricant: dry\nsegments:\n  - kind: stepped_pass\n"
    with pytest.raises(RecipeError, match="strictly increasing"):
        parse_recipe(base + "    velocities_um_s: [1, 5, 2]\n")
    with pytest.raises(RecipeError, match="pass_um"):
        parse_recipe(base + "    pass_um: 3000\n")
    with pytest.raises(RecipeError, match="window_um"):
        parse_recipe(base + "    window_um: 250\n")
    r = parse_recipe(base + "    velocities_um_s: [1, 10]\n")
    assert r.segments[0].pass_um == 1000


def test_equal_step_velocities_rejected():
    with pytest.raises(RecipeError) as ei:
        parse_recipe("name: x\nlubricant: dry\nsegments:\n  - kind: velocity_steps\n"
                     "    steps: [{v1_um_s: 1, v2_um_s: 1}]\n", "s.yaml")
    assert ei.value.field == "segments[0].steps[0]" and ei.value.line == 5


# --- what used to pass and fail later (issue 8, item 5) ---------------------------------

@pytest.mark.parametrize("old,new,field,line,words", [
    ("normal_force_N: 100", "normal_force_N: 100\nseed: -1", "seed", 4, "greater than or equal to 0"),
    ("normal_force_N: 100", "normal_force_N: 100\ntrials: true", "trials", 4, "valid integer"),
    ("normal_force_N: 100", "normal_force_N: 1e12", "normal_force_N", 3, "less than or equal to 1000"),
    ("name: t", "name: ../../escape", "name", 1, "should match pattern"),
    ("name: t", "name: a/b", "name", 1, "should match pattern"),
    ("name: t", "name: .hidden", "name", 1, "should match pattern"),
    ("duration_s: 1", "duration_s: '1'", "segments[0].duration_s", 6, "valid number"),
    ("speed_um_s: 50", "speed_um_s: 1.0e9", "segments[3].speed_um_s", 14, "less than or equal"),
])
def test_caught_at_load(tmp_path, old, new, field, line, words):
    p = write(tmp_path, GOOD.replace(old, new))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    assert (ei.value.field, ei.value.line) == (field, line)
    assert words in str(ei.value) and str(p) in str(ei.value)


def test_duplicate_key_names_both_lines(tmp_path):
    p = write(tmp_path, GOOD.replace("normal_force_N: 100", "normal_force_N: 100\nlubricant: dry"))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    e = ei.value
    assert e.line == 4 and e.field == "lubricant"
    assert "duplicate key 'lubricant'" in str(e) and "first at line 2" in str(e) and "again at line 4" in str(e)
    # inside a segment too
    p = write(tmp_path, GOOD.replace("position_um: 500", "position_um: 500\n    position_um: 900"))
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    assert ei.value.line == 14 and ei.value.field == "segments[3].position_um"


def test_deep_nesting_is_a_clear_error(tmp_path):
    p = write(tmp_path, "name: t\nlubricant: dry\nsegments: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(RecipeError) as ei:
        load_recipe(p)
    assert "nested deeper than" in str(ei.value) and ei.value.line == 3


def test_alias_bomb_is_refused(tmp_path):
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for i in range(1, 9):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    p = write(tmp_path, "\n".join(lines) + "\nname: t\n")
    with pytest.raises(RecipeError, match="more than .* YAML nodes"):
        load_recipe(p)


def test_other_yaml_features_refused(tmp_path):
    with pytest.raises(RecipeError, match="merge keys"):
        load_recipe(write(tmp_path, "base: &b {lubricant: dry}\n<<: *b\nname: t\n"))
    with pytest.raises(RecipeError, match="unsupported YAML tag") as ei:
        load_recipe(write(tmp_path, "name: !!binary aGVsbG8=\n"))
    assert ei.value.line == 1


def test_cli_refuses_before_writing(tmp_path, monkeypatch):
    """`rig run` on a bad recipe exits 2 with the file/line/field, and writes no MCAP."""
    from typer.testing import CliRunner
    from rig.cli import app

    monkeypatch.chdir(tmp_path)
    for old, new, field in (("normal_force_N: 100", "normal_force_N: 100\nseed: -1", "seed"),
                            ("name: t", "name: ../../escape", "name")):
        p = write(tmp_path, GOOD.replace(old, new), name="bad.yaml")
        res = CliRunner().invoke(app, ["run", str(p), "--sim", "-q"])
        assert res.exit_code == 2, res.output
        assert f"field '{field}'" in res.output and "line " in res.output
        assert "Traceback" not in res.output
    assert not list(tmp_path.rglob("*.mcap")) and not list(tmp_path.parent.parent.glob("escape*"))


def test_strict_types_still_take_ints_for_floats_and_lists_for_tuples(tmp_path):
    r = load_recipe(write(tmp_path, GOOD))
    assert isinstance(r.normal_force_N, float) and r.normal_force_N == 100.0


@pytest.mark.parametrize("old, new, field, hint", [
    ("  - kind: hold\n", "  - kind: hlod\n", "segments[0]", "did you mean 'hold'?"),
    ("    duration_s: 1\n", "    duraton_s: 1\n", "segments[0].duraton_s", "did you mean 'duration_s'?"),
    ("        v2_um_s: 2\n", "        v2_um_s: 2\n        slip_befor_um: 30\n",
     "segments[1].steps[0].slip_befor_um", "did you mean 'slip_before_um'?"),
    ("normal_force_N: 100\n", "normal_force: 100\n", "normal_force", "did you mean 'normal_force_N'?"),
])
def test_a_typo_gets_did_you_mean_in_its_one_error(tmp_path, old, new, field, hint):
    with pytest.raises(RecipeError) as ei:
        load_recipe(write(tmp_path, GOOD.replace(old, new)))
    assert f"{field}" in str(ei.value) and f"{hint}" in str(ei.value)  # first, or among the "also:" list


def test_no_did_you_mean_without_a_close_name(tmp_path):
    with pytest.raises(RecipeError) as ei:
        load_recipe(write(tmp_path, GOOD.replace("    duration_s: 1\n", "    duration_s: 1\n    zzz: 1\n")))
    assert ei.value.field == "segments[0].zzz" and "did you mean" not in str(ei.value)


def test_another_lubricant_renames_the_recipes_wording(tmp_path):
    """`rig run --lubricant dry` on a recipe written for boundary: its description and labels say dry."""
    text = GOOD.replace("name: t\n", "name: t\ndescription: Steps on the boundary lubricant (stability boundary-ish)\n")
    text = text.replace("    duration_s: 1\n", "    duration_s: 1\n    label: boundary settle\n")
    r = load_recipe(write(tmp_path, text))
    d = r.with_lubricant("dry")
    assert (d.lubricant, d.segments[0].label) == ("dry", "dry settle")
    assert d.description == "Steps on the dry lubricant (stability boundary-ish)"  # a word, not a part of one
    assert (r.lubricant, r.segments[0].label) == ("boundary", "boundary settle")  # the original is unchanged
    assert d.source_text == r.source_text
    with pytest.raises(ValueError):
        r.with_lubricant("bad\nname")
