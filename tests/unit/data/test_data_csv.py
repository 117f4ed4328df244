"""The measured-data CSV format (../shared/specs/measured-data.md) at the library level."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import rig
from rig.data import DataFormatError, PartialLineWarning, TrialData, read_csv, write_csv
from rig.log import load_trial


GOOD = (
    "# rig-trial-csv: 1\n"
    "# normal_force_N: 100\n"
    "# lubricant: boundary\n"
    "# operator: ada\n"
    "time_s,position_um,friction_N,normal_1_N,normal_2_N,position_ref_um\n"
    "0.000,0.000,0.842,100.21,99.87,0.000\n"
    "0.040,0.037,0.851,100.19,99.90,0.040\n"
    "0.080,0.081,0.849,100.20,99.88,0.080\n"
)


def _write(tmp_path, text, name="t.csv", mode="w"):
    p = tmp_path / name
    if mode == "wb":
        p.write_bytes(text)
    else:
        p.write_text(text, encoding="utf-8", newline="")
    return p


def test_reads_spec_example_with_metadata_and_optional_columns(tmp_path):
    tr = read_csv(_write(tmp_path, GOOD))
    assert len(tr) == 3
    assert tr.metadata["lubricant"] == "boundary"
    assert tr.metadata["operator"] == "ada"  # unknown keys kept
    assert tr.normal_force_N == 100.0
    np.testing.assert_allclose(tr.position_ref_um, [0.0, 0.04, 0.08])
    np.testing.assert_allclose(tr.mu[0], 0.842 / (100.21 + 99.87))


def test_any_column_order_crlf_and_extra_columns_kept(tmp_path):
    text = ("# rig-trial-csv: 1\r\n"
            "friction_N,temperature_C,time_s,position_um\r\n"
            "1.0,21.5,0.0,0.0\r\n1.1,21.6,0.5,0.4\r\n")
    tr = read_csv(_write(tmp_path, text))
    np.testing.assert_allclose(tr.time_s, [0.0, 0.5])
    np.testing.assert_allclose(tr.friction_N, [1.0, 1.1])
    np.testing.assert_allclose(tr.extra["temperature_C"], [21.5, 21.6])
    assert tr.normal_1_N is None


def test_nominal_normal_force_from_median_when_metadata_absent(tmp_path):
    text = GOOD.replace("# normal_force_N: 100\n", "")
    tr = read_csv(_write(tmp_path, text))
    assert tr.normal_force_N == pytest.approx(np.median([(100.21 + 99.87) / 2, (100.19 + 99.90) / 2,
                                                          (100.20 + 99.88) / 2]))


def test_mu_without_normals_uses_twice_nominal(tmp_path):
    text = "# rig-trial-csv: 1\n# normal_force_N: 50\ntime_s,position_um,friction_N\n0,0,10\n1,1,12\n"
    tr = read_csv(_write(tmp_path, text))
    np.testing.assert_allclose(tr.mu, [0.1, 0.12])


@pytest.mark.parametrize("text, line, fragment", [
    ("time_s,position_um,friction_N\n0,0,1\n", 1, "first line"),
    ("# rig-trial-csv: 1\ntime_s,friction_N\n0,1\n", 2, "missing required column(s): position_um"),
    ("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,0,1\n0.1,abc,1\n", 4, "non-numeric value 'abc'"),
    ("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,0,1\n0.1,0,1\n0.1,0,1\n", 5, "not strictly increasing"),
    ("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,0,1\n0.1,0,nan\n", 4, "NaN"),
    ("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n", 2, "empty data"),
    ("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,0,1\n0.1,0\n0.2,0,1\n", 4, "expected 3 fields"),
])
def test_bad_input_names_file_line_and_fault(tmp_path, text, line, fragment):
    p = _write(tmp_path, text)
    with pytest.raises(DataFormatError) as info:
        read_csv(p)
    err = info.value
    assert err.line == line
    assert fragment in str(err)
    assert str(p) in str(err)


def test_trailing_partial_line_is_a_warning_and_complete_rows_kept(tmp_path):
    text = GOOD + "0.120,0.1"  # cut off mid-write, no newline
    p = _write(tmp_path, text)
    with pytest.warns(PartialLineWarning, match="line 9"):
        tr = read_csv(p)
    assert len(tr) == 3
    assert tr.warnings and "partial" in tr.warnings[0]


def test_nan_in_optional_column_is_allowed(tmp_path):
    text = GOOD.replace("100.19,99.90", "nan,99.90")
    tr = read_csv(_write(tmp_path, text))
    assert np.isnan(tr.normal_1_N[1])


def test_write_then_read_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    n = 500
    t = np.cumsum(rng.uniform(0.001, 0.05, n))
    tr = TrialData(time_s=t, position_um=np.round(rng.normal(0, 100, n) / 0.076) * 0.076,
                   friction_N=rng.normal(20, 0.3, n), normal_1_N=rng.normal(100, 0.6, n),
                   normal_2_N=rng.normal(100, 0.6, n), position_ref_um=t * 1.0,
                   valve_cmd=rng.uniform(-1, 1, n), extra={"temp_C": rng.normal(21, 1, n)},
                   metadata={"lubricant": "dry", "note": "multi\nline"})
    p = write_csv(tr, tmp_path / "out.csv")
    back = read_csv(p)
    for name, arr in tr.columns().items():
        np.testing.assert_allclose(back.columns()[name], arr, rtol=1e-8, atol=1e-12, err_msg=name)
    assert back.metadata["lubricant"] == "dry"
    assert back.metadata["note"] == "multi line"
    assert p.read_text().splitlines()[0] == "# rig-trial-csv: 1"
    assert not list(tmp_path.glob(".out.csv.*"))  # no temporary left behind


def test_load_trial_rejects_unknown_suffix(tmp_path):
    p = _write(tmp_path, GOOD, name="t.txt")
    with pytest.raises(DataFormatError, match="unknown data file type"):
        load_trial(p)


def test_real_records_load(real_data_dir):
    for p in sorted(real_data_dir.glob("*.csv")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            tr = read_csv(p)
        assert len(tr) > 1000
        assert np.all(np.diff(tr.time_s) > 0)
        assert 0.3 < float(np.median(tr.mu)) < 1.0  # rock friction coefficients


def test_extra_columns_text_or_empty_are_kept_never_an_error(tmp_path):
    text = ("# rig-trial-csv: 1\ntime_s,position_um,friction_N,comment,blank,num\n"
            "0,1,2,hello,,1\n0.04,2,3,world,,\n")
    tr = read_csv(_write(tmp_path, text))
    assert list(tr.extra["comment"]) == ["hello", "world"]
    assert np.isnan(tr.extra["blank"]).all() and tr.extra["num"][0] == 1 and np.isnan(tr.extra["num"][1])
    out = tmp_path / "back.csv"
    write_csv(tr, out)
    back = read_csv(out)
    assert list(back.extra["comment"]) == ["hello", "world"] and np.array_equal(back.position_um, [1.0, 2.0])


@pytest.mark.parametrize("value", ["١٢٣", "１２", "1_0", "٣.٥", "1e٣"])
def test_non_ascii_digits_are_not_numbers(tmp_path, value):
    text = f"# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,1,2\n0.04,{value},2\n0.08,3,4\n"
    with pytest.raises(DataFormatError, match=r"line 4: column 'position_um': non-numeric"):
        read_csv(_write(tmp_path, text))


@pytest.mark.parametrize("value", ["abc", "-100", "0", "nan", "inf", ""])
def test_invalid_normal_force_metadata_is_an_error_naming_the_line(tmp_path, value):
    text = f"# rig-trial-csv: 1\n# lubricant: dry\n# normal_force_N: {value}\ntime_s,position_um,friction_N\n0,1,2\n"
    with pytest.raises(DataFormatError, match=r"line 3: normal_force_N metadata must be a positive number"):
        read_csv(_write(tmp_path, text))


def test_zero_normal_forces_never_divide_by_zero(tmp_path):
    text = "# rig-trial-csv: 1\ntime_s,position_um,friction_N,normal_1_N,normal_2_N\n0,1,2,0,0\n0.04,2,3,50,50\n"
    tr = read_csv(_write(tmp_path, text))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even a RuntimeWarning
        mu = tr.mu
    assert np.isnan(mu[0]) and mu[1] == pytest.approx(0.03)
    zero = read_csv(_write(tmp_path, text.replace("50,50", "0,0"), name="z.csv"))
    with pytest.raises(ValueError, match="nominal normal force is unknown"):
        zero.normal_force_N
    write_csv(zero, tmp_path / "z_out.csv")  # still writable, without a normal_force_N line
    assert "normal_force_N" not in (tmp_path / "z_out.csv").read_text()


def test_converted_public_records_load_with_source_and_licence():
    """tests/data's converted public records (tests/data/convert_giacomel.py) read without a
    warning, to the spec, and say where they come from and under which licence."""
    files = sorted((Path(rig.__file__).resolve().parents[1] / "tests" / "data").glob("giacomel-*.csv"))
    assert len(files) >= 3
    for p in files:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            tr = read_csv(p)
        assert len(tr) > 1000 and np.all(np.diff(tr.time_s) > 0)
        assert tr.metadata["position_source"] == "load_point"
        assert "github.com/pgiacomel/steadystate, commit" in tr.metadata["source"]
        assert tr.metadata["licence"].startswith("MIT")
        assert 0.3 < float(np.median(tr.mu)) < 1.0


def test_missing_first_line_points_at_the_spec_and_at_map(tmp_path):
    p = _write(tmp_path, "Time,Displ,Friction\n0,0,1\n0.1,0.2,1\n")
    with pytest.raises(DataFormatError) as info:
        read_csv(p)
    msg = str(info.value)
    assert info.value.line == 1
    assert "measured-data.md" in msg and '"Layout"' in msg
    assert "rig import" in msg and "--map" in msg
    # the same file read with a map needs no first line
    tr = read_csv(p, column_map={"time_s": "Time", "position_um": "Displ", "friction_N": "Friction"})
    np.testing.assert_allclose(tr.position_um, [0.0, 0.2])


@pytest.mark.parametrize("meta, expected", [
    ("# position_source: load_point\n", True),
    ("# position_source:  load_point \n", True),
    ("# position_source: on_sample\n# original_units: LP_Disp micron (load-point displacement)\n", False),
    ("# note: load point displacement\n", False),
    ("", False),
])
def test_is_load_point_is_the_spec_key_only(tmp_path, meta, expected):
    tr = read_csv(_write(tmp_path, "# rig-trial-csv: 1\n" + meta + "time_s,position_um,friction_N\n0,0,1\n1,1,1\n"))
    assert tr.is_load_point is expected
