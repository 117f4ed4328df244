"""Issue 21: never lose or confuse a trial. Unique outputs that are never overwritten, the trial's
identity (trial_uid) through info, export, import and the catalogue, who and what (specimen,
operator, metadata, required keys, a lab's lubricant names), calibration records, the log's clock."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import rig


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install
from rig.cli import app
from rig.log import read_log, read_trial

TINY = """\
name: tiny
lubricant: boundary
seed: 3
metadata: {specimen: S-recipe, operator: recipe-op, humidity_pct: 40}
segments:
  - kind: hold
    duration_s: 0.3
  - kind: move
    position_um: 520
    speed_um_s: 100
"""

runner = CliRunner()


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture()
def lab(tmp_path, monkeypatch):
    """A lab directory (the cwd) with the tiny recipe."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tiny.yaml").write_text(TINY)
    return tmp_path


def _run(*args):
    res = runner.invoke(app, ["run", "tiny.yaml", "-q", *map(str, args)])
    return res.exit_code, res.output


def test_two_runs_without_out_give_two_files_and_out_existing_is_refused(lab):
    code, text = _run("--sim")
    assert code == 0, text
    first = list((lab / "out" / "tiny").glob("*.mcap"))
    assert len(first) == 1
    digest = _sha(first[0])
    code, text = _run("--sim")
    assert code == 0, text
    # the first trial first (by name they sort by start second, then by uid when both started in one second)
    files = sorted((lab / "out" / "tiny").glob("*.mcap"), key=lambda f: f != first[0])
    assert len(files) == 2 and _sha(first[0]) == digest  # the first trial is untouched
    uids = {read_log(f, topics=set()).metadata_dict()["trial"]["trial_uid"] for f in files}
    assert len(uids) == 2 and all(f.name.split("-")[-1] == f"{u[:8]}.mcap" for f, u in
                                  zip(files, (read_log(f, topics=set()).metadata_dict()["trial"]["trial_uid"]
                                              for f in files)))
    # --out EXISTING: exit 2 naming it, the file unchanged; --overwrite replaces it
    target = lab / "keep.mcap"
    shutil.copy(files[0], target)
    code, text = _run("--sim", "--out", target)
    assert code == 2 and "keep.mcap" in text and "--overwrite" in text
    assert _sha(target) == digest
    code, text = _run("--sim", "--out", target, "--overwrite")
    assert code == 0, text
    assert _sha(target) != digest
    # the same rule for export, recover and import outputs
    csv = lab / "t.csv"
    assert runner.invoke(app, ["export", str(target), "-o", str(csv)]).exit_code == 0
    before = _sha(csv)
    res = runner.invoke(app, ["export", str(files[1]), "-o", str(csv)])
    assert res.exit_code == 2 and "t.csv" in res.output and _sha(csv) == before
    assert runner.invoke(app, ["export", str(files[1]), "-o", str(csv), "--overwrite"]).exit_code == 0
    assert _sha(csv) != before
    res = runner.invoke(app, ["import", str(csv), "-o", str(files[0])])
    assert res.exit_code == 2 and _sha(files[0]) == digest
    res = runner.invoke(app, ["recover", str(files[1]), "-o", str(files[0])])
    assert res.exit_code == 2 and _sha(files[0]) == digest


def test_identity_specimen_operator_through_info_export_import_and_catalogue(lab):
    from rig.catalog import build, query

    out = lab / "archive" / "a.mcap"
    code, text = _run("--sim", "--out", out, "--specimen", "P-7", "--operator", "ann", "--note", "fresh oil",
                      "--md", "batch=B12")
    assert code == 0, text
    res = runner.invoke(app, ["info", str(out), "--json", "-"])
    info = json.loads(res.stdout)
    uid = info["trial_uid"]
    assert len(uid) == 36 and info["specimen"] == "P-7" and info["operator"] == "ann"  # flags override the recipe
    trial = info["metadata"]["trial"]
    assert trial["humidity_pct"] == "40" and trial["batch"] == "B12" and trial["note"] == "fresh oil"
    end = info["metadata"]["trial_end"]  # numbers are numbers, never 'np.float64(...)'
    assert float(end["mean_friction_N"]) == pytest.approx(float(end["mean_friction_N"]))
    # the CSV export carries them; importing it keeps the uid
    csv = lab / "archive" / "a.csv"
    assert runner.invoke(app, ["export", str(out), "-o", str(csv)]).exit_code == 0
    head = [ln for ln in csv.read_text().splitlines() if ln.startswith("#")]
    assert f"# trial_uid: {uid}" in head and "# specimen: P-7" in head and "# operator: ann" in head
    assert "# batch: B12" in head
    imp = lab / "elsewhere" / "imported.mcap"
    assert runner.invoke(app, ["import", str(csv), "-o", str(imp)]).exit_code == 0
    assert read_log(imp, topics=set()).metadata_dict()["trial"]["trial_uid"] == uid
    # a CSV without one (another system's): the import takes the UUID of the CSV's content, the one the
    # catalogue gives that CSV, so the two are one trial
    from rig.data import content_uid

    bare = lab / "ext" / "bare.csv"
    bare.parent.mkdir()
    bare.write_text("\n".join(ln for ln in csv.read_text().splitlines() if not ln.startswith("# trial_uid")) + "\n")
    assert runner.invoke(app, ["import", str(bare), "-o", str(lab / "ext" / "bare.mcap")]).exit_code == 0
    other = read_log(lab / "ext" / "bare.mcap", topics=set()).metadata_dict()["trial"]["trial_uid"]
    assert other == content_uid(_sha(bare)) and other != uid
    build(lab / "ext")
    assert query(lab / "ext" / "catalog.duckdb", "SELECT trial_uid, n_files FROM trials").rows == [(other, 2)]
    # the catalogue: the log and its export are one trial with both paths; the specimens view
    rep = build(lab / "archive")
    assert len(rep.read) == 2
    db = lab / "archive" / "catalog.duckdb"
    rows = query(db, "SELECT trial_uid, path, n_files, paths, specimen, operator, kind FROM trials").records()
    assert len(rows) == 1
    r = rows[0]
    assert r["trial_uid"] == uid and r["n_files"] == 2 and r["kind"] == "mcap" and r["path"].endswith("a.mcap")
    assert sorted(Path(p).name for p in r["paths"]) == ["a.csv", "a.mcap"]
    assert (r["specimen"], r["operator"]) == ("P-7", "ann")
    sp = query(db, "SELECT specimen, trials, cumulative_slip_mm, operators FROM specimens").records()
    assert sp == [{"specimen": "P-7", "trials": 1, "cumulative_slip_mm": pytest.approx(0.02, abs=0.002),
                   "operators": ["ann"]}]


def test_moved_file_keeps_identify_results_and_never_computed_says_so(lab):
    from rig.catalog import build, query
    from rig.model.spec import FrictionModel
    from rig.sim import synth
    from rig.data import write_csv

    model = FrictionModel.for_lubricant("boundary", 0.12)
    segs = synth.paper_step_protocol(highs=(5.0,), pre_um=20.0, post_um=60.0, back_um=20.0)
    tr = synth.generate(model, segs, seed=11, lubricant="boundary").trial
    tr.metadata.update({"lubricant": "boundary", "normal_force_N": "100", "specimen": "P-9"})
    root = lab / "arch"
    write_csv(tr, lab / "step.csv")
    assert runner.invoke(app, ["import", str(lab / "step.csv"), "-o", str(root / "step.mcap")]).exit_code == 0
    db = root / "catalog.duckdb"
    build(root)
    res = runner.invoke(app, ["catalog", "query", "SELECT B_mu, results FROM catalog", "--db", str(db), "--json", "-"])
    text = res.output
    assert res.exit_code == 0 and "rig identify DIR" in text  # the note and the results column say so
    assert json.loads(res.stdout)[0]["results"].startswith("identify not computed")
    assert runner.invoke(app, ["identify", str(root), "--jobs", "1"]).exit_code == 0
    b_mu = query(db, "SELECT B_mu FROM catalog").rows[0][0]
    assert b_mu is not None
    # moved and renamed: after a rebuild the trial keeps its result (keyed by trial_uid)
    (root / "2026").mkdir()
    (root / "step.mcap").rename(root / "2026" / "renamed.mcap")
    build(root)
    rows = query(db, "SELECT path, B_mu, identify_current, results FROM catalog").records()
    assert len(rows) == 1 and rows[0]["path"].endswith("renamed.mcap")
    assert rows[0]["B_mu"] == b_mu and rows[0]["identify_current"] and "identify done" in rows[0]["results"]


def _profile(lab: Path, **extra) -> Path:
    p = lab / "lab-rig.yaml"
    p.write_text(yaml.safe_dump({"extends": str(REPO / "config/rigs/sim.yaml"), **extra}))
    return p


def test_required_metadata_and_lab_lubricant_names(lab):
    prof = _profile(lab, required_metadata=["specimen", "operator", "shift"],
                    lubricant_map={"Shell Tellus 46": "paraffin"})
    code, text = _run("--sim", "--profile", prof, "--out", lab / "x.mcap", "--operator", "")
    assert code == 2 and "operator, shift" in text and "--md shift=" in text
    assert not (lab / "x.mcap").exists() and not (lab / "out").exists()  # nothing written
    ok = ("--md", "shift=night")
    code, text = _run("--sim", "--profile", prof, "--plan-only", "--lubricant", "Shell Tellus 46", *ok)
    assert code == 0, text
    code, text = _run("--sim", "--profile", prof, "--plan-only", "--lubricant", "castor oil", *ok)
    assert code == 2 and "'castor oil'" in text and "lubricant_map" in text
    code, text = _run("--sim", "--md", "trial_uid=x")  # rig's own keys cannot be set
    assert code == 2 and "trial_uid" in text


def _hw_profile(lab: Path, private_profile, **overrides) -> Path:

    prof = private_profile(lab, **overrides)
    # YAML dates, as a lab writes them (safe_dump quotes the strings)
    prof.write_text(re.sub(r"'(\d{4}-\d\d-\d\d)'", r"\1", prof.read_text()))
    return prof


def test_calibration_expired_and_shunt_drift_refused_override_logged(lab, private_profile):
    """One emulated rig whose friction cell is past due and whose bridges drifted 0.4 %."""
    cal = {"serial": "LC-1234", "capacity_N": 500.0, "verified_range_N": [5.0, 500.0], "class": "1",
           "calibrated_on": "2019-01-01", "due_on": "2020-01-01", "uncertainty_N": 0.05, "shunt_reference_N": 250.0}
    prof = _hw_profile(lab, private_profile, loadcells={"friction": {"calibration": cal}},
                       emulators={"faults": {"loadcells": {"drift": 0.004}}})
    code, text = _run("--hardware", prof, "--out", lab / "h.mcap")
    assert code == 2 and "friction" in text and "LC-1234" in text and "2020-01-01" in text, text
    assert not (lab / "h.mcap").exists()
    # the reference-load input: 0.4 % is within class 1 (1 %)
    res = runner.invoke(app, ["calibrate", "verify", "--hardware", str(prof), "--cal-dir", str(lab / "cal"),
                              "--points", "10,100", "--samples", "5"])
    rec = json.loads(next((lab / "cal").glob("LC-1234-*.json")).read_text())
    assert res.exit_code == 0 and rec["passed"] is True, res.output
    assert [p["relative_error"] for p in rec["points"]] == [pytest.approx(0.004, abs=1e-5)] * 2
    # the override runs and logs both (the shunt check before the trial caught the drift through the
    # emulator's shunt-calibration registers), naming the channel; the MCAP records the calibration snapshot
    import time

    t0 = time.time_ns()
    code, text = _run("--hardware", prof, "--out", lab / "h.mcap", "--allow-expired-calibration")
    t1 = time.time_ns()
    assert code == 0, text
    tr = read_trial(lab / "h.mcap")
    # the log's clock is the loop's: trial time 0 is its first tick's wall-clock time, after the emulators and
    # the loop process started, and the last sample was taken before the command returned
    start, last = int(tr.metadata["start_time_ns"]), int(tr.metadata["start_time_ns"]) + tr.time_s[-1] * 1e9
    assert tr.metadata["clock"] == "first_sample" and t0 < start and last < t1
    c = read_log(lab / "h.mcap", topics={"/events"})
    opened = [m.log_time for m in c.messages if json.loads(m.data)["kind"] == "trial_start"][0]
    assert start - opened > 0.1e9  # the log opened before the loop process had even started
    ev = [(e["kind"], e["channel"]) for e in tr.events if e["kind"].startswith("calibration_")]
    assert ev == [("calibration_expired", "friction"), ("calibration_shunt_drift", "friction"),
                  ("calibration_shunt_drift", "normal_1"), ("calibration_shunt_drift", "normal_2")]
    assert [e["due_on"] for e in tr.events if e["kind"] == "calibration_expired"] == ["2020-01-01"]
    snap = json.loads(tr.metadata["calibration"])
    assert snap["friction"]["serial"] == "LC-1234" and snap["normal_1"]["serial"] == "EMU-LC-N01"


def test_shunt_drift_is_caught_through_the_emulator(lab, private_profile):
    prof = _hw_profile(lab, private_profile, emulators={"faults": {"loadcells": {"drift": -0.003}}})
    res = runner.invoke(app, ["calibrate", "shunt", "--hardware", str(prof), "--cal-dir", str(lab / "cal")])
    text = res.output
    assert res.exit_code == 1 and "friction (EMU-LC-F01) drifted -0.300 %" in text, text
    rec = json.loads(next((lab / "cal").glob("shunt-*.json")).read_text())
    assert [r["ok"] for r in rec["channels"]] == [False, False, False]
    assert [r["deviation_fraction"] for r in rec["channels"]] == [pytest.approx(-0.003, abs=1e-6)] * 3


def test_log_time_is_the_samples_wall_clock_on_a_paced_run(lab):
    import time

    t0 = time.time_ns()
    code, text = _run("--sim", "--pace", "1", "--out", lab / "p.mcap")
    t1 = time.time_ns()
    assert code == 0, text
    c = read_log(lab / "p.mcap")
    trial = c.metadata_dict()["trial"]
    start = int(trial["start_time_ns"])
    assert trial["clock"] == "first_sample" and t0 < start < t1
    from rig.log.schemas import LOG25_TOPIC

    times = np.array([m.log_time for m in c.messages if c.topic_of(m) == LOG25_TOPIC])
    tr = read_trial(lab / "p.mcap")
    # each sample's log_time is its trial time after the first sample's wall clock, and it had happened
    # by the time the run ended (a paced run hands a block over once its samples are due)
    assert np.allclose((times - start) / 1e9, tr.time_s, atol=0.06)
    assert times[-1] <= t1 + 20e6 and times[-1] > t1 - 3e9  # 20 ms: the monotonic pacing vs the wall clock


def test_calibration_warnings_range_and_uncertainty():
    from rig.data import TrialData, calibration_warnings

    f = np.r_[np.full(90, 20.0), np.full(10, 2.0)]  # 10 % below the verified range's 5 N
    snap = {"friction": {"serial": "LC-1", "verified_range_N": [5.0, 500.0], "uncertainty_N": 0.1},
            "normal_1": {"serial": "LC-2", "verified_range_N": [10.0, 1000.0]}, "lvdt": None}
    tr = TrialData(time_s=np.arange(100.0), position_um=np.zeros(100), friction_N=f,
                   normal_1_N=np.full(100, 100.0), normal_2_N=np.full(100, 100.0),
                   metadata={"calibration": json.dumps(snap)})
    w = calibration_warnings(tr, {"the direct effect": 0.05, "the evolution effect": 0.5})
    assert [x["where"] for x in w] == ["calibration of friction (LC-1)"] * 2
    assert "10.0 % of its readings" in w[0]["message"] and "the direct effect: 0.05 N" in w[1]["message"]
    tr.metadata.pop("calibration")
    assert calibration_warnings(tr, {"the direct effect": 0.05}) == []  # no snapshot: nothing to say
