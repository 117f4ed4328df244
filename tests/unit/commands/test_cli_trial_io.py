"""CLI: rig export (CSV, Parquet) / import / info / recover, corrupt chunks, v1 logs, and the CSV spec's bad
inputs (no partial output)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import rig
from rig.cli import app
from rig.data import read_csv
from rig.log import BLOCK_KEYS, TrialLogWriter, read_trial


runner = CliRunner()


@pytest.fixture()
def small_log(tmp_path):
    rng = np.random.default_rng(3)
    path = tmp_path / "trial.mcap"
    w = TrialLogWriter(path, metadata={"lubricant": "paraffin", "normal_force_N": 100.0, "seed": 1},
                       flush_interval_s=0.0)  # one chunk per block
    for b in range(20):
        t = (b * 100 + np.arange(100)) / 1000.0
        blk = {k: rng.normal(size=100) for k in BLOCK_KEYS}
        blk.update(t_s=t, position_ref_um=500 + t, position_um=500 + t + 0.01 * rng.normal(size=100),
                   friction_N=20 + rng.normal(size=100), normal_1_N=100 + rng.normal(size=100),
                   normal_2_N=100 + rng.normal(size=100))
        w.write_block(blk)
    w.event(0.5, "velocity_step", v1_um_s=1.0, v2_um_s=2.0)
    w.close()
    return path


def test_export_25hz_matches_spec(small_log, tmp_path):
    csv = tmp_path / "out.csv"
    res = runner.invoke(app, ["export", str(small_log), "--csv", str(csv)])
    assert res.exit_code == 0, res.output
    lines = csv.read_text().splitlines()
    assert lines[0] == "# rig-trial-csv: 1"
    header = next(ln for ln in lines if not ln.startswith("#"))
    assert header.split(",") == ["time_s", "position_um", "friction_N", "normal_1_N", "normal_2_N",
                                 "position_ref_um", "valve_cmd"]
    assert "# normal_force_N: 100.0" in lines and "# lubricant: paraffin" in lines
    tr = read_csv(csv)
    ref = read_trial(small_log, "25hz")
    assert len(tr) == 50
    for name in ("time_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd"):
        assert np.allclose(getattr(tr, name), getattr(ref, name), rtol=1e-8, atol=1e-12), name


def test_export_raw_keeps_extra_columns(small_log, tmp_path):
    csv = tmp_path / "raw.csv"
    res = runner.invoke(app, ["export", str(small_log), "--csv", str(csv), "--rate", "raw"])
    assert res.exit_code == 0, res.output
    tr = read_csv(csv)
    assert len(tr) == 2000 and "true_mu" in tr.extra and "pid_p" in tr.extra
    res = runner.invoke(app, ["export", str(small_log), "--csv", str(tmp_path / "n.csv"), "--rate", "raw",
                              "--no-extra"])
    assert res.exit_code == 0 and read_csv(tmp_path / "n.csv").extra == {}


def test_csv_round_trip_export_import_export(small_log, tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    imp = tmp_path / "imported.mcap"
    assert runner.invoke(app, ["export", str(small_log), "--csv", str(a)]).exit_code == 0
    res = runner.invoke(app, ["import", str(a), "--out", str(imp)])
    assert res.exit_code == 0, res.output
    assert runner.invoke(app, ["export", str(imp), "--csv", str(b)]).exit_code == 0
    data_a = [ln for ln in a.read_text().splitlines() if not ln.startswith("#")]
    data_b = [ln for ln in b.read_text().splitlines() if not ln.startswith("#")]
    assert data_a == data_b  # identical columns and values
    tr = read_trial(imp, "raw")
    assert tr.metadata["lubricant"] == "paraffin" and tr.metadata["imported_from"] == str(a)


GOOD_HEAD = "# rig-trial-csv: 1\n# normal_force_N: 100\n"


@pytest.mark.parametrize("body,line,what", [
    ("time_s,position_um\n0,1\n", 3, "missing required column"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,abc,2\n", 5, "non-numeric"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,1,2\n0.04,1,2\n", 6, "not strictly increasing"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,1,nan\n", 5, "NaN"),
    ("time_s,position_um,friction_N\n", 3, "empty data"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,١٢٣,2\n", 5, "non-numeric"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,１２,2\n", 5, "non-numeric"),
    ("time_s,position_um,friction_N\n0,1,2\n0.04,1_000,2\n", 5, "non-numeric"),
])
def test_import_bad_input_one_error_no_output(tmp_path, body, line, what):
    src = tmp_path / "bad.csv"
    src.write_text(GOOD_HEAD + body)
    out = tmp_path / "bad.mcap"
    res = runner.invoke(app, ["import", str(src), "--out", str(out)])
    assert res.exit_code == 2
    text = res.output
    assert str(src) in text and f"line {line}" in text and what in text
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [src]  # no temporary file either


def test_import_empty_file(tmp_path):
    src = tmp_path / "empty.csv"
    src.write_text("")
    res = runner.invoke(app, ["import", str(src), "--out", str(tmp_path / "e.mcap")])
    assert res.exit_code == 2 and "empty" in res.output
    assert not (tmp_path / "e.mcap").exists()


def test_import_partial_trailing_line_is_a_warning(tmp_path):
    src = tmp_path / "cut.csv"
    src.write_text(GOOD_HEAD + "time_s,position_um,friction_N\n0,1,2\n0.04,2,3\n0.08,3")
    out = tmp_path / "cut.mcap"
    res = runner.invoke(app, ["import", str(src), "--out", str(out)])
    assert res.exit_code == 0
    assert "warning" in res.output and "partial" in res.output
    tr = read_trial(out, "raw")
    assert len(tr) == 2 and np.array_equal(tr.position_um, [1.0, 2.0])


def test_info_and_recover_cli(small_log, tmp_path):
    res = runner.invoke(app, ["info", str(small_log)])
    assert res.exit_code == 0, res.output
    text = res.output
    for topic in ("/raw", "/log25", "/events", "/loop_stats"):
        assert topic in text
    assert "complete" in text and "recovered: no" in text and "velocity_step" in text

    data = small_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    res = runner.invoke(app, ["info", str(cut)])
    assert res.exit_code == 0 and "TRUNCATED" in res.output
    res = runner.invoke(app, ["export", str(cut), "--csv", str(tmp_path / "x.csv")])
    assert res.exit_code == 2 and "rig recover" in res.output
    assert not (tmp_path / "x.csv").exists()

    fixed = tmp_path / "fixed.mcap"
    res = runner.invoke(app, ["recover", str(cut), "--out", str(fixed)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["info", str(fixed)])
    assert res.exit_code == 0 and "recovered from" in res.output
    assert read_trial(fixed).metadata["recovered"] == "true"


@pytest.mark.parametrize("value", ["abc", "-100", "0", "nan", "١٠٠"])
def test_import_invalid_normal_force_metadata_names_the_line(tmp_path, value):
    src = tmp_path / "nf.csv"
    src.write_text(f"# rig-trial-csv: 1\n# lubricant: dry\n# normal_force_N: {value}\ntime_s,position_um,friction_N\n"
                   "0,1,2\n0.04,2,3\n", encoding="utf-8")
    out = tmp_path / "nf.mcap"
    res = runner.invoke(app, ["import", str(src), "--out", str(out)])
    assert res.exit_code == 2
    text = res.output
    assert f"{src}, line 3" in text and "normal_force_N" in text and "positive" in text
    assert not out.exists()


def test_import_keeps_text_and_empty_extra_columns_and_zero_normals(tmp_path):
    src = tmp_path / "x.csv"
    src.write_text("# rig-trial-csv: 1\ntime_s,position_um,friction_N,normal_1_N,normal_2_N,note,spare,gain\n"
                   "0,1,2,0,0,start,,1.5\n0.04,2,3,0,0,ok,,\n0.08,3,4,0,0,end,,2\n", encoding="utf-8")
    out = tmp_path / "x.mcap"
    res = runner.invoke(app, ["import", str(src), "--out", str(out)])
    assert res.exit_code == 0, res.output  # extra columns are never an error; zero normals divide nothing
    tr = read_trial(out, "raw")
    assert np.isnan(tr.extra["spare"]).all() and np.allclose(tr.extra["gain"], [1.5, np.nan, 2], equal_nan=True)
    assert np.isnan(tr.mu).all()
    assert "text_columns.json" in (runner.invoke(app, ["info", str(out)])).output
    back = tmp_path / "back.csv"
    assert runner.invoke(app, ["export", str(out), "--csv", str(back), "--rate", "raw"]).exit_code == 0
    assert read_csv(back).extra.keys() >= {"spare", "gain"}


def test_import_huge_times_is_one_clear_error(tmp_path):
    src = tmp_path / "ns.csv"
    src.write_text("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n1e19,1,2\n2e19,2,3\n")
    res = runner.invoke(app, ["import", str(src), "--out", str(tmp_path / "ns.mcap")])
    assert res.exit_code == 2 and "time_s" in res.output and "seconds" in res.output
    assert not (tmp_path / "ns.mcap").exists()


def test_export_parquet_beside_csv(small_log, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    csv, par = tmp_path / "o.csv", tmp_path / "o.parquet"
    res = runner.invoke(app, ["export", str(small_log), "--csv", str(csv), "--parquet", str(par), "--rate", "raw"])
    assert res.exit_code == 0, res.output
    table = pq.read_table(par)
    tr = read_csv(csv)
    assert table.num_rows == len(tr) == 2000
    assert table.column_names[:3] == ["time_s", "position_um", "friction_N"] and "pid_p" in table.column_names
    assert np.allclose(table.column("friction_N").to_numpy(), tr.friction_N, rtol=1e-8)
    assert table.schema.metadata[b"rig.lubricant"] == b"paraffin"
    res = runner.invoke(app, ["export", str(small_log)])
    assert res.exit_code == 2 and "--parquet" in res.output


def test_export_reads_v1_logs():
    from pathlib import Path
    v1 = Path(rig.__file__).resolve().parents[1] / "tests" / "data" / "v1-sim-1khz.mcap"
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "v1.csv"
        res = runner.invoke(app, ["export", str(v1), "--csv", str(out), "--rate", "raw"])
        assert res.exit_code == 0, res.output
        assert len(read_csv(out)) == 1678


def test_corrupt_chunk_warns_in_export_and_info_and_fails_strict(small_log, tmp_path, corrupt_middle_chunk):
    bad = tmp_path / "bad.mcap"
    corrupt_middle_chunk(small_log, bad)
    csv = tmp_path / "b.csv"
    res = runner.invoke(app, ["export", str(bad), "--csv", str(csv), "--rate", "raw"])
    assert res.exit_code == 0, res.output
    text = res.output
    assert "warning" in text and "CRC mismatch" in text and "/raw" in text
    n = len(read_csv(csv))
    assert 1000 < n < 2000
    ref = read_trial(small_log, "raw")
    got = read_csv(csv)
    keep = np.isin(np.round(ref.time_s, 6), np.round(got.time_s, 6))
    assert np.allclose(got.normal_1_N, ref.normal_1_N[keep], atol=1e-9)  # no corrupt value exported

    res = runner.invoke(app, ["export", str(bad), "--csv", str(tmp_path / "s.csv"), "--strict"])
    assert res.exit_code == 2 and "damaged chunk" in res.output and not (tmp_path / "s.csv").exists()
    res = runner.invoke(app, ["info", str(bad)])
    assert res.exit_code == 0 and "corrupt chunk" in res.output and "DAMAGED" in res.output
    fixed = tmp_path / "fixed.mcap"
    res = runner.invoke(app, ["recover", str(bad), "--out", str(fixed)])
    assert res.exit_code == 0 and "was complete" not in res.output and "corrupt" in res.output
    assert len(read_trial(fixed, "raw")) == n
