"""The batch engine (rig.catalog.batch) on a real local Dask cluster of 2 worker processes:
results identical to the serial run (bit for bit, seeded), a failed file reported while the
rest go on, `rig identify DIR --scheduler` writing into the catalogue, `rig reproduce` trials."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rig.sim import synth
from rig.analysis.reproduce import reproduce
from rig.catalog import query
from rig.catalog.batch import BatchError, mapper, run_tasks
from rig.catalog.tasks import identify_file
from rig.cli import app
from rig.data import write_csv
from rig.model.spec import FrictionModel


distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    from distributed import LocalCluster

    c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40)
    yield c
    c.close()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    out = []
    for k, lub in enumerate(("boundary", "dry", "boundary", "paraffin", "dry", "boundary")):
        model = FrictionModel.for_lubricant(lub, 0.12)
        segs = synth.paper_step_protocol(highs=(5.0,), pre_um=60.0, post_um=300.0, back_um=60.0)
        tr = synth.generate(model, segs, seed=k, lubricant=lub).trial
        tr.metadata["lubricant"] = lub
        p = root / f"t{k}.csv"
        write_csv(tr, p)
        out.append(p)
    bad = root / "zz_bad.csv"
    bad.write_text("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,0,1\n1,oops,2\n")
    return root, out, bad


WALL_CLOCK = ("fit_time_s", "sim_s")  # elapsed seconds: the only fields that may differ


def _strip(x):
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in WALL_CLOCK}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def _canon(x):
    """Every other value, floats by their exact repr."""
    return json.dumps(_strip(x), sort_keys=True)


def test_dask_batch_equals_serial_and_failure_is_isolated(cluster, files):
    root, good, bad = files
    items = [(str(p), {"whole_record": True}) for p in good + [bad]]
    serial = run_tasks(identify_file, items, jobs=1)
    seen = []
    from distributed import Client

    with Client(cluster) as client:
        par = run_tasks(identify_file, items, client=client, progress=lambda d, t, r: seen.append((d, t)))
        workers = {r.worker for r in par}
    assert [r.item for r in par] == [r.item for r in serial]  # input order
    assert seen[-1] == (len(items), len(items)) and len(seen) == len(items)
    assert all(r.ok for r in par[:-1]) and all(r.ok for r in serial[:-1])
    # bit for bit: the same reports, every float equal
    for a, b in zip(serial[:-1], par[:-1]):
        assert _canon(a.value) == _canon(b.value)
    # the bad file: reported (its name and line), the others done
    assert not par[-1].ok and "zz_bad.csv" in par[-1].error and "line" in par[-1].error
    assert not serial[-1].ok and serial[-1].error == par[-1].error
    assert all(w.startswith("tcp://") for w in workers) and len(workers) == 2


def test_cli_identify_dir_on_a_scheduler_writes_the_catalogue(cluster, files, tmp_path):
    root, good, bad = files
    db = tmp_path / "c.duckdb"
    r = CliRunner().invoke(app, ["identify", str(root), "--scheduler", cluster.scheduler_address, "--db", str(db)])
    text = r.output
    assert r.exit_code == 1, text  # one file failed: listed, exit 1; the rest are in the catalogue
    assert "6 of 7 files done" in text and "zz_bad.csv" in text and "Traceback" not in text
    rows = query(db, "SELECT path, ok, error, B_mu, rig_version FROM identify_results ORDER BY path").records()
    assert len(rows) == 7
    assert all(r_["ok"] and r_["B_mu"] > 0 and r_["rig_version"] for r_ in rows[:-1])
    assert not rows[-1]["ok"] and "line" in rows[-1]["error"]
    # the same numbers as the serial API
    serial = run_tasks(identify_file, [(str(good[0]), {"use_events": True, "velocity_method": "local_poly",
                                                       "whole_record": True, "whole_velocity": "segments",
                                                       "stiffness": None, "directions": "both",
                                                       "min_ratio": 1.25})], jobs=1)[0]
    assert rows[0]["B_mu"] == serial.value["report"]["mean"]["B_mu"]
    # the catalogue view joins the file's metadata and the result
    v = query(db, "SELECT lubricant, B_mu, identify_current FROM catalog WHERE path = ?", [rows[0]["path"]]).rows
    assert v == [("boundary", rows[0]["B_mu"], True)]
    # a glob selects files the same way; --jobs 0 and a bad scheduler are clear errors
    r = CliRunner().invoke(app, ["identify", str(root / "t[01].csv"), "--jobs", "1", "--db", str(db)])
    assert r.exit_code == 0 and "2 of 2 files done" in r.output
    r = CliRunner().invoke(app, ["identify", str(root), "--jobs", "0"])
    assert r.exit_code == 2 and "--jobs" in r.output
    r = CliRunner().invoke(app, ["identify", str(root), "--scheduler", "localhost:1"])
    assert r.exit_code == 2 and "tcp://HOST:PORT" in r.output


def test_reproduce_on_the_cluster_is_the_serial_run(cluster):
    serial = reproduce(2, seed=3, lubricants=["dry"], engine="synth")
    with mapper(scheduler=cluster.scheduler_address) as map_fn:
        par = reproduce(2, seed=3, lubricants=["dry"], engine="synth", map_fn=map_fn)
    assert len(par["lubricants"]["dry"]["trials"]) == 2
    assert _canon(serial) == _canon(par)


def test_unreachable_scheduler_is_one_error(monkeypatch):
    import rig.catalog.batch as B

    monkeypatch.setattr(B, "CONNECT_TIMEOUT_S", 1.0)  # a shorter wait, the same real connection attempt
    with pytest.raises(BatchError, match="cannot connect"):
        run_tasks(identify_file, [("a", {}), ("b", {})], scheduler="tcp://127.0.0.1:9")


def test_cli_diagnose_batch_records_findings(files, tmp_path):
    root, good, bad = files
    db = tmp_path / "d.duckdb"
    r = CliRunner().invoke(app, ["diagnose", str(root / "t0.csv"), "--jobs", "1", "--db", str(db)])
    assert r.exit_code == 0, r.output
    rows = query(db, "SELECT ok, baseline, holdout_rms_N, n_findings, causes, rig_version, report "
                     "FROM diagnose_results").records()
    assert len(rows) == 1 and rows[0]["ok"] and rows[0]["baseline"] == "rate_state"
    rep = json.loads(rows[0]["report"])
    assert rep["schema"] == "rig.diagnosis/1" and rows[0]["causes"] == [f["cause"] for f in rep["findings"]]
    assert 0 < rows[0]["holdout_rms_N"] < 1.0  # the synthetic noise is 0.25 N


def _worker_env(_):
    import os

    import dask

    return (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS"),
            dask.config.get("distributed.worker.profile.enabled"))


def _echo(x):
    return x


def test_local_cluster_workers_and_longest_first_order():
    """The engine's own LocalCluster: workers without glibc's aggressive trimming (it costs a
    reproduce trial 22 % more CPU, docs/scaling.md), one BLAS thread, no profiler; a ``cost``
    makes the work run longest first while the results stay in the input order."""
    from rig.catalog.batch import dask_client, lpt_order
    from rig.analysis.reproduce import plan_lubricant, trial_cost_s

    with dask_client(1) as client:
        env = run_tasks(_worker_env, [0], client=client)[0]
        assert env.ok and env.value == (None, "1", False)
        done = []
        items = [3.0, 9.0, 1.0, 9.0, 5.0]
        res = run_tasks(_echo, items, client=client, cost=lambda x: x, progress=lambda d, t, r: done.append(r.item))
    assert [r.value for r in res] == items  # input order
    assert done == [9.0, 9.0, 5.0, 3.0, 1.0]  # one worker: completion order is the run order
    assert lpt_order(items, None) == [0, 1, 2, 3, 4] and lpt_order(items, float) == [1, 3, 4, 0, 2]
    # a reproduce trial's cost grows with its L (a longer slide before each step, 6 L, at least
    # 120 µm): dry's L = 79 µm draw of seed 0 costs more than any boundary trial
    dry, _, _ = plan_lubricant("dry", 8, seed=0, engine="synth")
    boundary, _, _ = plan_lubricant("boundary", 8, seed=0, engine="synth")
    longest = max(dry, key=trial_cost_s)
    assert longest["params"]["L_um"] == max(t["params"]["L_um"] for t in dry)
    assert trial_cost_s(longest) > max(trial_cost_s(t) for t in boundary)
    assert trial_cost_s({"params": {"L_um": 5.0}}) == trial_cost_s({"params": {"L_um": 19.0}})


def test_short_batch_runs_in_this_process(files):
    """A batch whose measured work is below what the workers' start costs runs as --jobs 1 does: no
    worker (so --jobs N is never slower than serial on a short batch); the results are the same."""
    from rig.catalog.batch import Engine

    root, good, bad = files
    items = [(str(p), {}) for p in good]
    eng = Engine(2, start_cost_s=600.0)
    try:
        par = eng.run(identify_file, items, cost=lambda it: 1.0)
        assert eng._pool is None  # never started
    finally:
        eng.close()
    assert all(r.worker.startswith("local") for r in par) and eng.estimate_s is not None
    serial = run_tasks(identify_file, items, jobs=1)
    assert [_canon(a.value) for a in serial] == [_canon(b.value) for b in par]


def test_own_workers_and_this_process_share_the_batch(files):
    """run_tasks(jobs=2) with no cluster: this process and its forked worker take the files from one
    queue; the results are the serial ones, in order, each reported once."""
    root, good, bad = files
    items = [(str(p), {}) for p in good]
    serial = run_tasks(identify_file, items, jobs=1)
    seen = []
    par = run_tasks(identify_file, items, jobs=2, cost=lambda it: int(it[0][-5]),
                    progress=lambda d, t, r: seen.append(d), start_cost_s=0.0)  # workers whatever the work
    assert seen == list(range(1, len(items) + 1))
    where = {r.worker.split(":")[0] for r in par}
    assert where <= {"local", "pool"} and "pool" in where
    assert [_canon(a.value) for a in serial] == [_canon(b.value) for b in par]


def _dies_in_a_worker(x):
    import os

    from rig.catalog import batch

    if batch._POOL_WORKER:
        os._exit(3)
    return x


def test_a_dead_worker_fails_its_task_only():
    """A worker process that dies (a crash in native code, the OOM killer) fails the task it ran; the
    batch's other tasks finish in this process; the next run gets new workers."""
    from rig.catalog.batch import Engine

    eng = Engine(2, start_cost_s=0.0)
    try:
        res = eng.run(_dies_in_a_worker, list(range(8)))
        assert [r.value for r in res if r.ok] == [r.item for r in res if r.ok]
        failed = [r for r in res if not r.ok]
        assert len(failed) == 1 and "BrokenProcessPool" in failed[0].error
        again = eng.run(_dies_in_a_worker, list(range(8)))
        assert len(again) == 8 and all(r.ok or "BrokenProcessPool" in r.error for r in again)
    finally:
        eng.close()
