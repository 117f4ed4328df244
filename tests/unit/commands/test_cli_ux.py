"""The operator's experience (issue 13): help without Python types, one meaning of --json and -o/--out,
files colleagues can read, warnings as one line, an estimate before a long trial, no traceback."""

from __future__ import annotations

from pathlib import Path
import json
import os
import re
import stat

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import rig
from rig.cli import app
from rig.commands.common import Lubricant
from rig.data import TrialData
from rig.log import write_trial_data


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

runner = CliRunner()
SMOKE = REPO / "config" / "recipes" / "smoke.yaml"
COMMANDS = [["run"], ["info"], ["export"], ["import"], ["recover"], ["identify"], ["stribeck"], ["stability"],
            ["reproduce"], ["diagnose"], ["devices", "check"], ["emulate"], ["loop-bench"], ["warmup"],
            ["catalog", "build"], ["catalog", "query"]]


@pytest.mark.parametrize("cmd", COMMANDS, ids=[" ".join(c) for c in COMMANDS])
def test_help_has_no_python_types(cmd):
    res = runner.invoke(app, [*cmd, "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    leaks = re.findall(r"<(?:bool|str|path|float|int|list\[[^\]]*\])>", res.output)
    assert not leaks, (cmd, leaks)
    if "--json" in res.output:  # one meaning everywhere: a PATH, '-' prints
        assert re.search(r"--json\s+PATH", res.output) and "'-': print" in res.output, res.output


def test_choices_are_shown_and_enforced():
    res = runner.invoke(app, ["stability", "--help"], env={"COLUMNS": "200"})
    assert "<dry|paraffin|boundary>" in res.output  # Table 2's; rig run takes a lab's own name (issue 21)
    res = runner.invoke(app, ["identify", "--help"], env={"COLUMNS": "200"})
    assert "<both|up|down>" in res.output and "<paper|local_poly>" in res.output
    res = runner.invoke(app, ["diagnose", "--help"], env={"COLUMNS": "200"})
    assert "<rate_state|steady_state>" in res.output


def test_lubricant_choices_are_the_recipes_and_table2():
    from rig.config.recipe import LUBRICANTS
    from rig.model.paper import TABLE2

    assert tuple(x.value for x in Lubricant) == tuple(LUBRICANTS) and set(LUBRICANTS) == set(TABLE2)


@pytest.fixture()
def log(tmp_path):
    t = np.arange(100) * 0.04
    p = tmp_path / "t.mcap"
    write_trial_data(TrialData(time_s=t, position_um=t, friction_N=np.full(100, 10.0),
                               metadata={"normal_force_N": "100", "lubricant": "dry"}), p)
    return p


def test_json_dash_prints_json_on_stdout(log, tmp_path):
    res = runner.invoke(app, ["info", str(log), "--json", "-"])
    assert res.exit_code == 0
    doc = json.loads(res.stdout)
    assert doc["complete"] and doc["metadata"]["trial"]["lubricant"] == "dry"
    res = runner.invoke(app, ["stability", "--lubricant", "dry", "--json", "-"])
    assert res.exit_code == 0
    doc = json.loads(res.stdout)  # the table went to stderr
    assert doc["schema"].startswith("rig.stability/") and "k_cr" in res.stderr
    out = tmp_path / "info.json"
    res = runner.invoke(app, ["info", str(log), "--json", str(out)])
    assert res.exit_code == 0 and json.loads(out.read_text())["complete"] and "channels" in res.stdout


def test_export_takes_out_and_keeps_csv_alias(log, tmp_path):
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.parquet"
    assert runner.invoke(app, ["export", str(log), "-o", str(a)]).exit_code == 0
    assert runner.invoke(app, ["export", str(log), "--csv", str(b)]).exit_code == 0
    assert a.read_text() == b.read_text()
    assert runner.invoke(app, ["export", str(log), "--out", str(c)]).exit_code == 0
    assert c.read_bytes()[:4] == b"PAR1"


def test_written_files_are_readable_by_colleagues(log, tmp_path):
    old = os.umask(0o022)
    try:
        csv, mcap, js = tmp_path / "e.csv", tmp_path / "i.mcap", tmp_path / "s.json"
        assert runner.invoke(app, ["export", str(log), "-o", str(csv)]).exit_code == 0
        assert runner.invoke(app, ["import", str(csv), "-o", str(mcap)]).exit_code == 0
        assert runner.invoke(app, ["stability", "--lubricant", "dry", "--json", str(js)]).exit_code == 0
        for p in (csv, mcap, js):
            assert stat.S_IMODE(p.stat().st_mode) == 0o644, p
    finally:
        os.umask(old)


def test_warnings_are_one_clean_line(tmp_path):
    """A PartialLineWarning (and any warning) prints as `warning: ...`, never with a Python source line."""
    src = tmp_path / "cut.csv"
    src.write_text("# rig-trial-csv: 1\n# normal_force_N: 100\ntime_s,position_um,friction_N\n0,1,2\n0.04,2,3\n0.0")
    res = runner.invoke(app, ["identify", str(src)])
    text = res.output
    assert "warning: " in text and "partial line" in text
    assert "PartialLineWarning" not in text and "return read_csv" not in text and ".py:" not in text, text
    assert res.exit_code == 2 and "Traceback" not in text  # and no steps in two rows: bad input


def test_estimate_before_a_long_trial(tmp_path):
    doc = yaml.safe_load(SMOKE.read_text())
    doc["segments"] = [{"kind": "hold", "duration_s": 700}]
    p = tmp_path / "long.yaml"
    p.write_text(yaml.safe_dump(doc))
    res = runner.invoke(app, ["run", str(p), "--sim", "--plan-only"])
    assert res.exit_code == 0 and re.search(r"estimate: about 1\d\.\d MB of log", res.output), res.output
    assert "12 min" in res.output and "on the simulated rig" in res.output


def test_past_the_threshold_it_asks_or_warns(monkeypatch, tmp_path):
    import typer

    from rig.commands import trial as trial_mod

    est = trial_mod.estimate_log(_Plan(10 * 3600), _Recipe(), hardware=False)  # 10 h at 1 kHz
    assert est["log_bytes"] > trial_mod.LOG_SIZE_ASK_BYTES and est["wall_s"] < est["duration_s"]
    out = tmp_path / "x.mcap"
    trial_mod._check_size(est, 1, out, yes=False, hardware=False)  # no terminal: a warning, it goes on
    monkeypatch.setattr(trial_mod.sys.stdin, "isatty", lambda: True, raising=False)
    trial_mod._check_size(est, 1, out, yes=True, hardware=False)  # --yes: no question
    asked = []
    monkeypatch.setattr(trial_mod.typer, "confirm", lambda *a, **k: asked.append(a) or False)
    with pytest.raises(typer.Exit) as exc:
        trial_mod._check_size(est, 1, out, yes=False, hardware=False)
    assert exc.value.exit_code == 130 and asked and "MB of log" in asked[0][0]


class _Plan:
    def __init__(self, d):
        self.duration_s = d


class _Recipe:
    class log:  # noqa: N801
        raw_rate_hz = 1000.0
        decimated_rate_hz = 25.0


def test_readme_uses_the_venv_rig():
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    for b in blocks:
        for m in re.finditer(r"(\S*)\brig (run|identify|export|import|info|warmup)\b", b):
            assert m.group(1).endswith(".venv/bin/"), m.group(0)
    assert ".venv/bin/activate" in text and "rig warmup" in text


def test_mcap_messages_say_what_the_file_is(tmp_path):
    """A record length past the end of the file (mcap's RecordLengthLimitExceeded), a directory, a PNG:
    each one line that says what is wrong, exit 2."""
    import struct

    huge = tmp_path / "huge.mcap"
    huge.write_bytes(b"\x89MCAP0\r\n" + bytes([0x01]) + struct.pack("<Q", 2**62) + b"abc")
    png = tmp_path / "plot.mcap"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(32))
    d = tmp_path / "out"
    d.mkdir()
    for path, needle in ((huge, "truncated"), (png, "this is a PNG image, not an MCAP trial log"),
                         (d, "is a directory, not an MCAP trial log")):
        for cmd in (["info", str(path)], ["export", str(path), "-o", str(tmp_path / "x.csv")],
                    ["identify", str(path)] if path.suffix == ".mcap" else ["info", str(path)]):
            res = runner.invoke(app, cmd)
            assert res.exit_code == 2 and needle in res.output, (cmd, res.output)
            assert "RecordLengthLimitExceeded" not in res.output and "Traceback" not in res.output
    assert not (tmp_path / "x.csv").exists()


def test_values_are_checked_as_typer_checks_them_without_its_adapters(tmp_path):
    """rig.commands.common.quick_coercion passes plain values through (a default within its range, a str, a
    path) and leaves the rest to typer: an out-of-range or malformed number is typer's usage error, exit 2."""
    for args, words in ((["--seed", "-1"], "greater than or equal to 0"), (["--live-port", "70000"], "65535"),
                        (["--seed", "x"], "integer")):
        res = runner.invoke(app, ["run", str(SMOKE), "--sim", "--plan-only", *args], terminal_width=200)
        assert res.exit_code == 2 and words in res.output, (args, res.output)
    res = runner.invoke(app, ["info", str(tmp_path / "missing.mcap")])
    assert res.exit_code == 2 and "missing.mcap" in res.output  # the path's own check (exists) still runs
    res = runner.invoke(app, ["run", str(SMOKE), "--plan-only", "--seed", "3", "--live-port", "0"])
    assert res.exit_code == 0, res.output
