"""Property-based fuzzing (hypothesis) of the three readers an operator feeds files to, through the CLI.

For the measured-data CSV reader (`rig import`), the recipe loader (`rig run --plan-only`) and the MCAP
reader (`rig info`, `rig export`), whatever the bytes:

- no traceback and no internal error: every failure is one `error:` line;
- a failure exits with 2 (bad input) and names the file (CSV errors also name the line where the
  file has one);
- nothing half-written: after a failure the output file does not exist and no temporary file is left;
  after a success the output is complete and readable.

In-process through typer's CliRunner (fast); one subprocess check at the end covers the real entry
point. Bounded: derandomized, 40-80 examples each, about 30-60 s in all on the 2-core machine.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import rig
from rig.cli import app
from rig.data import TrialData
from rig.log import read_trial, write_trial_data


REPO = Path(rig.__file__).resolve().parents[1]  # the checkout of the editable install

runner = CliRunner()  # click 8.2: res.output holds stdout and stderr, interleaved
FUZZ = settings(max_examples=int(os.environ.get("RIG_FUZZ_EXAMPLES", "60")), deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


def _clean_failure(res, path: Path, out: Path | None, workdir: Path) -> str:
    """The properties every failing command must have; returns the text."""
    text = res.output
    assert "Traceback" not in text and "internal error" not in text, text
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert res.exit_code == 2, (res.exit_code, text)
    assert str(path) in text, text  # the file is named
    lines = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, text  # one error line
    if out is not None:
        assert not out.exists(), "half-written output after a failure"
    leftovers = [p.name for p in workdir.iterdir() if p.name.endswith(".tmp")]
    assert not leftovers, leftovers
    return text


# ---------------------------------------------------------------------------
# the measured-data CSV (rig import)
# ---------------------------------------------------------------------------

NAMES = ["time_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd",
         "note", "gain", "", " time_s", "friction_N"]
FIELDS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**20, 10**20).map(str),
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e309", "1_000", "١٢٣", "１２", "0x10", "1,5", "abc", '"1"',
                     "1e-400", "--1", "+", ".", "1.2.3", "\t", "é"]),
)
META = st.sampled_from(["# normal_force_N: 100", "# normal_force_N: -100", "# normal_force_N: 0",
                        "# normal_force_N: abc", "# lubricant: dry", "# position_source: load_point",
                        "# position_source: elsewhere", "# started_utc: 2024-01-01T00:00:00Z",
                        "# started_utc: yesterday", "#", "# a comment", "# start_time_ns: -5"])


@st.composite
def csv_bytes(draw) -> bytes:
    lines = []
    magic = draw(st.sampled_from(["# rig-trial-csv: 1", "# rig-trial-csv: 1", "# rig-trial-csv: 2",
                                  "rig-trial-csv: 1", "", "#rig-trial-csv:1"]))
    lines.append(magic)
    lines += draw(st.lists(META, max_size=3))
    if draw(st.booleans()):
        header = ["time_s", "position_um", "friction_N"] + draw(st.lists(st.sampled_from(NAMES), max_size=3))
    else:
        header = draw(st.lists(st.sampled_from(NAMES), min_size=0, max_size=6))
    lines.append(",".join(header))
    n_rows = draw(st.integers(0, 12))
    t = 0.0
    for _ in range(n_rows):
        if draw(st.integers(0, 5)) == 0:  # a broken row
            row = draw(st.lists(FIELDS, min_size=0, max_size=len(header) + 2))
        else:
            t += draw(st.sampled_from([0.04, 0.001, 0.0, -0.04, 1e12]))
            row = [repr(t)] + [draw(st.sampled_from(["1", "2.5", "-3e2", "100", "0"])) for _ in header[1:]]
        lines.append(",".join(row))
    text = "\n".join(lines) + draw(st.sampled_from(["\n", "", "\r\n", "\n\n"]))
    data = text.encode("utf-8")
    cut = draw(st.one_of(st.none(), st.integers(0, max(0, len(data)))))
    if cut is not None:
        data = data[:cut]
    if draw(st.integers(0, 9)) == 0:
        data += draw(st.binary(max_size=20))
    return data


@FUZZ
@given(csv_bytes())
def test_fuzz_csv_import(data):
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        src, out = d / "in.csv", d / "out.mcap"
        src.write_bytes(data)
        res = runner.invoke(app, ["import", str(src), "-o", str(out)])
        if res.exit_code == 0:
            tr = read_trial(out, "raw")  # complete and readable
            assert len(tr) >= 1 and np.all(np.diff(tr.time_s) > 0)
            assert "Traceback" not in res.output
            return
        text = _clean_failure(res, src, out, d)
        if "cannot read file" not in text and "empty file" not in text:
            assert f"{src}, line " in text or "time_s reaches" in text, text  # CSV errors name the line


# ---------------------------------------------------------------------------
# the recipe loader (rig run --plan-only: validate and compile, write nothing)
# ---------------------------------------------------------------------------

SMOKE = (REPO / "config" / "recipes" / "smoke.yaml").read_text()
VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.floats(allow_nan=True),
                   st.text(max_size=8), st.sampled_from(["[1, 2", "{a: 1}", "*x", "&x 1", "!!python/object 1",
                                                         "- a", "1e999", "0x1F", "~", "'", '"', "\t"]))


@st.composite
def recipe_text(draw) -> str:
    lines = SMOKE.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        action = draw(st.integers(0, 3))
        line = lines[i]
        if action == 0:  # delete a line
            lines.pop(i)
        elif action == 1 and ":" in line:  # replace a value
            key = line.split(":", 1)[0]
            lines[i] = f"{key}: {draw(VALUES)}"
        elif action == 2:  # duplicate a line (duplicate keys)
            lines.insert(i, line)
        else:  # break the indentation or insert junk
            lines[i] = draw(st.sampled_from(["  ", " ", "\t", ""])) + line + draw(st.sampled_from(["", ":", " ]"]))
    return "\n".join(lines) + "\n"


@FUZZ
@given(recipe_text())
def test_fuzz_recipe_loader(text):
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        src = d / "recipe.yaml"
        src.write_text(text, encoding="utf-8")
        res = runner.invoke(app, ["run", str(src), "--sim", "--plan-only"])
        if res.exit_code == 0:
            assert "ticks at" in res.output
        else:
            _clean_failure(res, src, None, d)
        assert sorted(p.name for p in d.iterdir()) == ["recipe.yaml"]  # plan-only writes nothing


# ---------------------------------------------------------------------------
# the MCAP reader (rig info, rig export)
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_mcap(tmp_path_factory) -> bytes:
    t = np.arange(60) * 0.04
    tr = TrialData(time_s=t, position_um=np.sin(t), friction_N=10 + np.cos(t), normal_1_N=np.full(60, 100.0),
                   normal_2_N=np.full(60, 100.0), metadata={"normal_force_N": "100", "lubricant": "dry"},
                   events=[{"t_s": 1.0, "kind": "marker"}])
    p = tmp_path_factory.mktemp("mcap") / "small.mcap"
    write_trial_data(tr, p)
    return p.read_bytes()


@st.composite
def mutations(draw):
    """(kind, position fraction, payload): flip bytes, cut the file, insert or overwrite a run of bytes."""
    kind = draw(st.sampled_from(["flip", "cut", "insert", "overwrite", "flip", "zero"]))
    return kind, draw(st.floats(0, 1)), draw(st.binary(min_size=1, max_size=16)), draw(st.integers(1, 400))


def _mutate(data: bytes, muts) -> bytes:
    b = bytearray(data)
    for kind, frac, payload, n in muts:
        i = min(len(b) - 1, int(frac * len(b))) if b else 0
        if kind == "flip" and b:
            b[i] ^= payload[0] or 0xFF
        elif kind == "cut":
            del b[i:]
        elif kind == "insert":
            b[i:i] = payload
        elif kind == "overwrite":
            b[i:i + len(payload)] = payload
        elif kind == "zero":
            b[i:i + n] = bytes(len(b[i:i + n]))
    return bytes(b)


@FUZZ
@given(st.lists(mutations(), min_size=1, max_size=3))
def test_fuzz_mcap_reader(small_mcap, muts):
    data = _mutate(small_mcap, muts)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        src, out = d / "trial.mcap", d / "out.csv"
        src.write_bytes(data)
        res = runner.invoke(app, ["info", str(src)])
        text = res.output
        assert "Traceback" not in text and "internal error" not in text, text
        assert res.exit_code in (0, 2), (res.exit_code, text)
        if res.exit_code == 2:
            _clean_failure(res, src, None, d)
        res = runner.invoke(app, ["export", str(src), "-o", str(out)])
        if res.exit_code == 0:
            assert out.exists() and out.read_text().startswith("# rig-trial-csv: 1")
        else:
            _clean_failure(res, src, out, d)


def test_mutations_do_damage(small_mcap):
    """The MCAP fuzzing is not vacuous: a fixed sample of mutations yields readable, damaged and
    unreadable files alike."""
    rng = random.Random(5)
    codes = set()
    with tempfile.TemporaryDirectory() as d:
        src = Path(d) / "m.mcap"
        for _ in range(30):
            muts = [(rng.choice(["flip", "cut", "zero"]), rng.random(), b"\x55", rng.randint(1, 200))]
            src.write_bytes(_mutate(small_mcap, muts))
            codes.add(runner.invoke(app, ["export", str(src), "-o", str(Path(d) / "o.csv")]).exit_code)
    assert codes == {0, 2}


def test_real_entry_point_bad_csv(tmp_path):
    """The installed entry point, in a real process: one error line, exit 2, no traceback, no output."""
    src = tmp_path / "bad.csv"
    src.write_bytes(b"# rig-trial-csv: 1\ntime_s,position_um,friction_N\n0,1,2\n0.04,\xff\xfe,3\n")
    out = tmp_path / "o.mcap"
    r = subprocess.run([sys.executable, "-m", "rig.cli", "import", str(src), "-o", str(out)], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and f"{src}, line 4" in r.stderr and "UTF-8" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()
