"""Every format rig writes, rig reads: the Parquet of `rig export` loads where a CSV does (load_trial, so
identify, stribeck, diagnose; the catalogue), with the CSV's metadata from its key-value metadata."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from rig.catalog.tasks import TRIAL_SUFFIXES, index_file
from rig.cli import app
from rig.data import DataFormatError, TrialData, write_csv
from rig.log import load_trial, write_parquet


runner = CliRunner()


def trial(n=400):
    t = np.arange(n) / 25.0
    rng = np.random.default_rng(5)
    return TrialData(time_s=t, position_um=500 + 2 * t, friction_N=20 + rng.normal(size=n) * 0.2,
                     normal_1_N=np.full(n, 100.0), normal_2_N=np.full(n, 100.0), position_ref_um=500 + 2 * t,
                     valve_cmd=rng.normal(size=n) * 0.01, extra={"pid_p": rng.normal(size=n),
                                                                 "note": np.array(["a"] * n)},
                     metadata={"lubricant": "boundary", "normal_force_N": "100", "recipe": "unit"})


def test_parquet_loads_as_the_csv_does(tmp_path):
    tr = trial()
    write_csv(tr, tmp_path / "t.csv")
    write_parquet(load_trial(tmp_path / "t.csv"), tmp_path / "t.parquet")
    a, b = load_trial(tmp_path / "t.csv"), load_trial(tmp_path / "t.parquet")
    assert list(a.columns()) == list(b.columns())
    for k, v in a.columns().items():
        if k == "note":
            assert list(b.columns()[k]) == ["a"] * 400
        else:
            assert np.array_equal(np.asarray(v, float), np.asarray(b.columns()[k], float)), k
    assert b.metadata["lubricant"] == "boundary" and b.normal_force_N == 100.0 and b.metadata == a.metadata
    assert ".parquet" in TRIAL_SUFFIXES
    row = index_file(str(tmp_path / "t.parquet"))  # rig catalog build
    assert row["kind"] == "parquet" and row["n_samples"] == 400 and row["lubricant"] == "boundary"
    assert row["backend"] == "imported" and row["normal_force_N"] == 100.0


@pytest.mark.parametrize("table, what", [
    (pa.table({"time_s": [0.0, 1.0], "friction_N": [1.0, 2.0]}), "missing required column(s): position_um"),
    (pa.table({"time_s": [0.0, 0.0], "position_um": [1.0, 2.0], "friction_N": [1.0, 2.0]}),
     "time_s not strictly increasing at row 2"),
    (pa.table({"time_s": [0.0, 1.0], "position_um": ["a", "b"], "friction_N": [1.0, 2.0]}),
     "column 'position_um'"),
    (None, "not a readable Parquet file"),
])
def test_bad_parquet_is_one_clear_error(tmp_path, table, what):
    p = tmp_path / "bad.parquet"
    if table is None:
        p.write_bytes(b"PAR1 this is not parquet")
    else:
        pq.write_table(table, p)
    with pytest.raises(DataFormatError, match=what.replace("(", r"\(").replace(")", r"\)")):
        load_trial(p)
    r = runner.invoke(app, ["stribeck", str(p)])
    assert r.exit_code == 2 and "Traceback" not in r.output and "bad.parquet" in r.output
