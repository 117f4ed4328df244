"""The one exit-code table (rig.commands.common), kept by every subcommand.

0 done; 1 a failed run, trip or write; 2 bad input (nothing written); 130 aborted. Every registered
subcommand has cases here (a new command without one fails `test_every_subcommand_is_covered`); the
130 cases are in tests/system/commands/test_cli_trial_run.py (a real SIGINT, and one while the log is finished).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import rig
from rig.cli import app
from rig.commands.common import EXIT_ABORTED, EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, ExitCode
from rig.data import TrialData
from rig.log import write_trial_data


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

runner = CliRunner()
SMOKE = REPO / "config" / "recipes" / "smoke.yaml"
SIM = REPO / "config" / "rigs" / "sim.yaml"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("exit")
    good_csv = d / "good.csv"
    good_csv.write_text("# rig-trial-csv: 1\n# normal_force_N: 100\ntime_s,position_um,friction_N\n"
                        + "".join(f"{0.04 * i:.2f},{0.04 * i:.2f},10\n" for i in range(20)))
    one_csv = d / "one.csv"
    one_csv.write_text("# rig-trial-csv: 1\n# normal_force_N: 100\ntime_s,position_um,friction_N\n0,0,10\n")
    bad_csv = d / "bad.csv"
    bad_csv.write_text("# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,1,2\n0.04,abc,2\n")
    png = d / "fig.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    mcap = d / "good.mcap"
    t = np.arange(50) * 0.04
    write_trial_data(TrialData(time_s=t, position_um=t, friction_N=np.full(50, 10.0),
                               metadata={"normal_force_N": "100"}), mcap)
    bad_json = d / "id.json"
    bad_json.write_text("{not json")
    return {"good_csv": good_csv, "bad_csv": bad_csv, "png": png, "mcap": mcap, "dir": d, "bad_json": bad_json,
            "missing": d / "missing.csv", "one_csv": one_csv}


# (command words, args from the files, expected exit, what the error must name)
CASES = [
    ("run", lambda f: ["run", str(f["missing"]), "--sim"], EXIT_BAD_INPUT, "missing.csv"),
    ("run", lambda f: ["run", str(SMOKE), "--sim", "--seed", "-1"], EXIT_BAD_INPUT, "--seed"),
    ("run", lambda f: ["run", str(SMOKE), "--sim", "--lubricant", "oil"], EXIT_BAD_INPUT, "--lubricant"),
    ("run", lambda f: ["run", str(SMOKE), "--sim", "--friction-model", str(SMOKE)], EXIT_BAD_INPUT,
     "this is a recipe, not a friction model"),
    ("run", lambda f: ["run", str(SMOKE), "--sim", "-o", str(f["dir"])], EXIT_BAD_INPUT, "is a directory"),
    ("run", lambda f: ["run", str(SMOKE), "--plan-only"], EXIT_OK, "ticks at"),
    ("run", lambda f: ["run", str(SIM), "--sim", "--plan-only"], EXIT_BAD_INPUT, "this is a rig profile, not a recipe"),
    ("run", lambda f: ["run", str(SMOKE), "--hardware", str(SMOKE)], EXIT_BAD_INPUT,
     "this is a recipe, not a rig profile"),
    ("run", lambda f: ["run", str(SMOKE), "--sim", "-q", "-o", "/proc/rig-cannot-write/x.mcap"], EXIT_FAILED,
     "cannot write"),
    ("info", lambda f: ["info", str(f["dir"])], EXIT_BAD_INPUT, "is a directory"),
    ("info", lambda f: ["info", str(f["png"])], EXIT_BAD_INPUT, "this is a PNG image, not an MCAP trial log"),
    ("info", lambda f: ["info", str(f["mcap"])], EXIT_OK, "complete"),
    ("export", lambda f: ["export", str(f["png"]), "-o", str(f["dir"] / "x.csv")], EXIT_BAD_INPUT, "fig.png"),
    ("export", lambda f: ["export", str(f["mcap"]), "-o", str(f["dir"] / "x.txt")], EXIT_BAD_INPUT, ".parquet"),
    ("export", lambda f: ["export", str(f["mcap"]), "-o", str(f["dir"] / "x.csv")], EXIT_OK, "wrote"),
    ("import", lambda f: ["import", str(f["bad_csv"]), "-o", str(f["dir"] / "b.mcap")], EXIT_BAD_INPUT,
     "bad.csv, line 4"),
    ("import", lambda f: ["import", str(f["good_csv"]), "-o", str(f["dir"] / "g.mcap")], EXIT_OK, "wrote"),
    ("recover", lambda f: ["recover", str(f["good_csv"]), "-o", str(f["dir"] / "r.mcap")], EXIT_BAD_INPUT,
     "good.csv"),
    ("identify", lambda f: ["identify", str(f["missing"])], EXIT_BAD_INPUT, "missing.csv"),
    ("identify", lambda f: ["identify", str(f["good_csv"]), "--direction", "sideways"], EXIT_BAD_INPUT,
     "--direction"),
    ("identify", lambda f: ["identify", str(f["bad_csv"])], EXIT_BAD_INPUT, "bad.csv, line 4"),
    ("identify", lambda f: ["identify", str(f["one_csv"])], EXIT_BAD_INPUT, "one.csv: 1 sample(s): too few"),
    ("stribeck", lambda f: ["stribeck", str(f["png"])], EXIT_BAD_INPUT, "fig.png"),
    ("stability", lambda f: ["stability", "--v0", "-1"], EXIT_BAD_INPUT, "--v0"),
    ("stability", lambda f: ["stability", "--params", str(f["bad_json"])], EXIT_BAD_INPUT, "id.json, line 1"),
    ("stability", lambda f: ["stability", "--lubricant", "dry"], EXIT_OK, "k_cr"),
    ("stability", lambda f: ["stability", "--profile", str(SMOKE)], EXIT_BAD_INPUT, "smoke.yaml, line 1: this is a "
                                                                                    "recipe"),
    ("reproduce", lambda f: ["reproduce", "--lubricant", "oil"], EXIT_BAD_INPUT, "--lubricant"),
    ("reproduce", lambda f: ["reproduce", "--trials", "1"], EXIT_BAD_INPUT, "--trials"),
    ("diagnose", lambda f: ["diagnose", str(f["png"])], EXIT_BAD_INPUT, "fig.png"),
    ("diagnose", lambda f: ["diagnose", str(f["good_csv"]), "--baseline", "linear"], EXIT_BAD_INPUT, "--baseline"),
    ("heal", lambda f: ["heal", str(f["png"])], EXIT_BAD_INPUT, "fig.png"),
    ("tune step", lambda f: ["tune", "step", str(f["good_csv"])], EXIT_BAD_INPUT, "trial log (.mcap)"),
    ("tune frf", lambda f: ["tune", "frf", str(f["good_csv"]), "--nperseg", "8"], EXIT_BAD_INPUT, "--nperseg"),
    ("tune autotune", lambda f: ["tune", "autotune", "--hardware", str(f["missing"]), "-o", str(f["dir"] / "g.yaml")],
     EXIT_BAD_INPUT, "missing.csv"),
    ("devices check", lambda f: ["devices", "check", "--hardware", str(SIM)], EXIT_BAD_INPUT, "hardware"),
    ("calibrate tare", lambda f: ["calibrate", "tare", "--hardware", str(SIM)], EXIT_BAD_INPUT, "hardware"),
    ("calibrate shunt", lambda f: ["calibrate", "shunt", "--hardware", str(SIM)], EXIT_BAD_INPUT, "hardware"),
    ("calibrate verify", lambda f: ["calibrate", "verify", "--hardware", str(SIM), "--points", "10,x"],
     EXIT_BAD_INPUT, "--points"),
    ("emulate", lambda f: ["emulate", "--hardware", str(f["missing"])], EXIT_BAD_INPUT, "missing.csv"),
    ("loop-bench", lambda f: ["loop-bench", "--hardware", str(SIM)], EXIT_BAD_INPUT, "hardware"),
    ("loop-bench", lambda f: ["loop-bench", "--seconds", "-1"], EXIT_BAD_INPUT, "--seconds"),
    ("pause", lambda f: ["pause", "--pid", "-3"], EXIT_BAD_INPUT, "--pid -3"),
    ("pause", lambda f: ["pause", "--pid", "999999999"], EXIT_FAILED, "no `rig run` of pid 999999999"),
    ("resume", lambda f: ["resume", "--pid", "999999999"], EXIT_FAILED, "no `rig run` of pid 999999999"),
    ("reset", lambda f: ["reset", "--hardware", str(SIM)], EXIT_BAD_INPUT, "hardware"),
    ("reset", lambda f: ["reset", "--hardware", str(f["missing"])], EXIT_BAD_INPUT, "missing.csv"),
    ("warmup", lambda f: ["warmup", "--no-such-option"], EXIT_BAD_INPUT, "--no-such-option"),
    ("catalog build", lambda f: ["catalog", "build", str(f["dir"] / "nodir")], EXIT_BAD_INPUT, "no such directory"),
    ("catalog query", lambda f: ["catalog", "query", "SELECT 1", "--db", str(f["dir"] / "none.duckdb")],
     EXIT_BAD_INPUT, "no such catalogue"),
]


@pytest.mark.parametrize("name,args,code,needle", CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_exit_code(files, name, args, code, needle):
    res = runner.invoke(app, args(files))
    text = res.output
    assert res.exit_code == code, (res.exit_code, text)
    assert needle in text, text
    assert "Traceback" not in text and "internal error" not in text, text
    if code == EXIT_BAD_INPUT and not text.lstrip().startswith("Usage"):  # our errors: one line
        assert len([ln for ln in text.splitlines() if ln.startswith("error:")]) == 1, text


def _subcommands(group, prefix: str = "") -> set[str]:
    names = set()
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):  # a group (typer vendors its own click)
            names |= _subcommands(cmd, f"{prefix}{name} ")
        else:
            names.add(f"{prefix}{name}")
    return names


def test_every_subcommand_is_covered():
    group = typer.main.get_command(app)
    registered = _subcommands(group)
    covered = {c[0] for c in CASES}
    assert registered - covered == set(), "subcommands without an exit-code case"
    assert {c[2] for c in CASES} >= {EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT}


def test_the_table():
    assert [int(c) for c in ExitCode] == [0, 1, 2, 130] and EXIT_ABORTED == 130
    res = runner.invoke(app, ["--help"])
    assert "0 done; 1 failed run, trip or write; 2 bad input" in " ".join(res.output.split())
    assert "130 aborted" in res.output


def test_usage_errors_are_bad_input():
    assert runner.invoke(app, ["no-such-command"]).exit_code == EXIT_BAD_INPUT
    assert runner.invoke(app, ["info"]).exit_code == EXIT_BAD_INPUT  # missing argument
