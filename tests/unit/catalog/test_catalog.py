"""The trial catalogue (rig.catalog, `rig catalog build|query`): ~20 small simulated and
imported trials indexed into DuckDB, queried, rebuilt incrementally; corrupt files recorded."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import rig
from rig.sim import synth
from rig.catalog import SCHEMA_VERSION, CatalogError, build, query
from rig.cli import app
from rig.data import read_csv, write_csv
from rig.model.spec import FrictionModel
from rig.log import TrialLogWriter, recover


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

LUBS = ("boundary", "dry", "paraffin")


def small_trial(k: int, lubricant: str):
    """A short synthetic record (one velocity step, ~40 s at 25 Hz)."""
    model = FrictionModel.for_lubricant(lubricant, 0.12)
    segs = synth.paper_step_protocol(highs=(5.0,), pre_um=20.0, post_um=60.0, back_um=20.0)
    tr = synth.generate(model, segs, seed=100 + k, lubricant=lubricant).trial
    tr.metadata.update({"lubricant": lubricant, "normal_force_N": "100",
                        "started_utc": f"2026-{1 + k % 6:02d}-15T09:00:00+00:00", "lab": "test"})
    return tr


def write_log(trial, path: Path, status: str, chunk_size: int = 1 << 20, **meta) -> Path:
    """A trial log as the session writes it (backend, recipe, profile metadata; trial_end status)."""
    w = TrialLogWriter(path, loop_rate_hz=25.0, decimated_rate_hz=25.0, fsync=False, threaded=False,
                       chunk_size=chunk_size,
                       metadata={**trial.metadata, "backend": "sim", "recipe": "steps-short", "profile_name": "sim",
                                 "seed": 7, **meta})
    cols = {"t_s": trial.time_s, **{k: v for k, v in trial.columns().items() if k != "time_s"}}
    for i in range(0, len(trial), 250):
        w.write_block({k: np.asarray(v[i:i + 250], dtype=float) for k, v in cols.items()})
    for e in trial.events:
        e = dict(e)
        w.event(e.pop("t_s", 0.0), e.pop("kind", "marker"), **e)
    w.close(status)
    return path


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    (root / "imported").mkdir()
    (root / "logs" / "2026").mkdir(parents=True)
    for k in range(8):  # imported CSVs (other acquisition systems)
        write_csv(small_trial(k, LUBS[k % 3]), root / "imported" / f"csv{k:02d}.csv")
    statuses = ["completed"] * 6 + ["interrupted", "failed"]
    for k, st in enumerate(statuses):  # simulated trial logs
        write_log(small_trial(20 + k, LUBS[k % 3]), root / "logs" / "2026" / f"sim{k:02d}.mcap", st)
    # a log cut off by a crash, rewritten by `rig recover`
    full = write_log(small_trial(40, "boundary"), root / "full.tmp", "completed", chunk_size=16384)
    data = full.read_bytes()
    cut = root / "cut.tmp"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    recover(cut, root / "logs" / "recovered.mcap")
    full.unlink()
    cut.unlink()
    # one trial run on the simulated rig by `rig run --sim` (the smoke recipe, ~20 s of rig time)
    res = CliRunner().invoke(app, ["run", str(REPO / "config" / "recipes" / "smoke.yaml"), "--sim",
                                   "--out", str(root / "logs" / "smoke.mcap"), "--quiet"])
    assert res.exit_code == 0, res.output
    # two corrupt files: not fatal, recorded with their error
    (root / "logs" / "broken.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(500))
    (root / "imported" / "broken.csv").write_text("time_s,position_um\n0,1\n")
    return root


def test_build_query_incremental_and_corrupt(archive, tmp_path):
    root = tmp_path / "a"
    shutil.copytree(archive, root)
    db = tmp_path / "cat.duckdb"
    rep = build(root, db)
    assert len(rep.read) == 20
    assert set(Path(p).name for p in rep.failed) == {"broken.mcap", "broken.csv"}
    assert "broken.csv" in rep.failed[str((root / "imported" / "broken.csv").resolve())]

    # the schema is versioned
    assert query(db, "SELECT version FROM schema_version").rows == [(SCHEMA_VERSION,)]
    # files: every file, the corrupt ones with ok = false and their error
    files = query(db, "SELECT path, ok, error, reads, length(sha256) FROM files ORDER BY path").records()
    assert len(files) == 20
    bad = {Path(f["path"]).name: f for f in files if not f["ok"]}
    assert set(bad) == {"broken.mcap", "broken.csv"} and all(f["error"] for f in bad.values())
    assert all(f["length(sha256)"] == 64 and f["reads"] == 1 for f in files)
    # trials: 18 readable ones, with the metadata and the four statuses
    st = dict(query(db, "SELECT status, count(*) FROM trials GROUP BY status").rows)
    assert st["aborted"] == 1 and st["tripped"] == 1 and st["recovered"] == 1
    assert st["completed"] == 15  # 8 CSVs, 6 completed logs, the rig run
    assert sum(st.values()) == 18
    smoke = query(db, "SELECT recipe, lubricant, backend, rig_profile, duration_s, started_utc, n_samples, "
                      "written_by FROM trials WHERE path LIKE '%smoke.mcap'").records()[0]
    assert smoke["recipe"] == "smoke" and smoke["lubricant"] == "boundary" and smoke["backend"] == "sim"
    assert smoke["rig_profile"] and smoke["duration_s"] > 10 and smoke["started_utc"] is not None
    assert smoke["n_samples"] > 100 and smoke["written_by"]
    # a question across trials: boundary-lubricant trials since March
    q = query(db, "SELECT path FROM trials WHERE lubricant = 'boundary' AND started_utc >= TIMESTAMP '2026-03-01' "
                  "ORDER BY path").rows
    expect = [k for k in range(8) if LUBS[k % 3] == "boundary" and 1 + k % 6 >= 3]
    assert [Path(p).name for (p,) in q if "csv" in Path(p).name] == [f"csv{k:02d}.csv" for k in expect]
    assert query(db, "SELECT count(*) FROM catalog").rows == [(18,)]

    # nothing changed: nothing is read
    rep2 = build(root, db)
    assert rep2.read == [] and len(rep2.unchanged) == 20

    # change one file: only it is re-read; touch another (same bytes): not re-read
    changed = root / "imported" / "csv03.csv"
    tr = read_csv(changed)
    tr.metadata["lubricant"] = "graphite"
    write_csv(tr, changed)
    touched = root / "imported" / "csv04.csv"
    os.utime(touched, ns=(touched.stat().st_atime_ns, touched.stat().st_mtime_ns + 5_000_000_000))
    rep3 = build(root, db)
    assert rep3.read == [str(changed.resolve())]
    assert rep3.touched == [str(touched.resolve())]
    assert query(db, "SELECT lubricant FROM trials WHERE path = ?", [str(changed.resolve())]).rows == [("graphite",)]
    reads = dict(query(db, "SELECT path, reads FROM files").rows)
    assert reads[str(changed.resolve())] == 2 and reads[str(touched.resolve())] == 1
    assert sorted(reads.values()).count(1) == 19

    # a deleted file leaves the catalogue
    (root / "logs" / "2026" / "sim00.mcap").unlink()
    rep4 = build(root, db)
    assert [Path(p).name for p in rep4.removed] == ["sim00.mcap"] and rep4.read == []
    assert query(db, "SELECT count(*) FROM trials").rows == [(17,)]


def test_cli_build_and_query(archive, tmp_path):
    root = tmp_path / "a"
    shutil.copytree(archive, root)
    r = CliRunner().invoke(app, ["catalog", "build", str(root), "--quiet"])
    assert r.exit_code == 0, r.output
    text = r.output
    assert "read 20" in text and "2 unreadable" in text and "broken.mcap" in text
    db = root / "catalog.duckdb"
    assert db.exists()
    sql = "SELECT lubricant, count(*) AS n FROM trials GROUP BY lubricant ORDER BY lubricant"
    r = CliRunner().invoke(app, ["catalog", "query", sql, "--db", str(db), "--json", "-"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    assert {d["lubricant"]: d["n"] for d in rows} == {"boundary": 8, "dry": 6, "paraffin": 4}
    r = CliRunner().invoke(app, ["catalog", "query", sql, "--db", str(db), "--csv", "-"])
    assert list(csv.reader(io.StringIO(r.stdout)))[0] == ["lubricant", "n"]
    r = CliRunner().invoke(app, ["catalog", "query", sql, "--db", str(db)])
    assert r.exit_code == 0 and "paraffin" in r.output and "3 row(s)" in r.output
    # a bad query, a missing catalogue: one clear error, exit 2 (bad input), no traceback
    r = CliRunner().invoke(app, ["catalog", "query", "SELECT nope FROM trials", "--db", str(db)])
    assert r.exit_code == 2 and "query failed" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["catalog", "query", "SELECT 1", "--db", str(tmp_path / "none.duckdb")])
    assert r.exit_code == 2 and "no such catalogue" in r.output
    r = CliRunner().invoke(app, ["catalog", "build", str(tmp_path / "nodir")])
    assert r.exit_code == 2 and "no such directory" in r.output


def test_other_schema_version_is_refused(tmp_path):
    import duckdb

    db = tmp_path / "old.duckdb"
    con = duckdb.connect(str(db))
    con.execute("CREATE TABLE schema_version (version INTEGER, created_utc TIMESTAMP, rig_version VARCHAR)")
    con.execute("INSERT INTO schema_version VALUES (99, now()::TIMESTAMP, 'x')")
    con.close()
    with pytest.raises(CatalogError, match="schema version 99"):
        build(tmp_path, db)
