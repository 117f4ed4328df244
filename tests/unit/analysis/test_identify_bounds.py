"""identify bounded by physics, and bad records that give one clear error (issue 10).

Per step: |A|, |B| < 0.05, L inside the slip the decay was fitted over, r2 >= 0.2; a step that
fails is rejected with its reason and listed; with 4 or more steps an outlier (4 robust sigma)
is rejected too. A record no analysis can use (1, 2 or 10 rows; time in nanoseconds; a
position that never moves; friction = 1e300) is one clear error naming the file, non-zero exit, no
traceback, for identify and diagnose alike.
"""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from rig.analysis.identify import AB_MAX, R2_MIN, physical_check
from rig.cli import app


HDR = "# rig-trial-csv: 1\n# normal_force_N: 100\ntime_s,position_um,friction_N\n"


def _write(path, t, x, f):
    path.write_text(HDR + "".join(f"{float(a)!r},{float(b)!r},{float(c)!r}\n" for a, b, c in zip(t, x, f)))
    return path


def test_physical_check_rejects_with_reasons():
    assert physical_check(0.0011, 0.004, 19.2, 0.9, 1.0, 300.0) == (True, "")
    ok, why = physical_check(2.8e14, 2.8e14, 19.2, 0.12, 1.0, 300.0)  # the 10-step staircase's bad step
    assert not ok and str(AB_MAX) in why
    ok, why = physical_check(0.0011, 0.004, 900.0, 0.9, 1.0, 300.0)
    assert not ok and "outside the fitted window" in why
    ok, why = physical_check(0.0011, 0.004, 19.2, 0.1, 1.0, 300.0)
    assert not ok and f"< {R2_MIN}" in why
    ok, why = physical_check(0.0011, 0.004, 19.2, 0.9, -1.0, 300.0)
    assert not ok and "expected sign" in why


def _bad_records(tmp):
    t = np.arange(2000) * 0.04
    x = np.where(t < 40, t, 40 + 10 * (t - 40))
    f = 20 + np.random.default_rng(1).normal(0, 0.1, t.size)
    huge = f.copy()
    huge[100] = 1e300
    return {
        "one": (_write(tmp / "one.csv", t[:1], x[:1], f[:1]), "too few samples"),
        "two": (_write(tmp / "two.csv", t[:2], x[:2], f[:2]), "too few samples"),
        "ten": (_write(tmp / "ten.csv", t[:10], x[:10], f[:10]), "too few samples"),
        "ns": (_write(tmp / "ns.csv", t * 1e9, x, f), "nanoseconds"),
        "constant_position": (_write(tmp / "const.csv", t, 0 * t + 5.0, f), "does not move"),
        "huge_friction": (_write(tmp / "huge.csv", t, x, huge), "beyond any load cell"),
    }


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_bad_records_give_one_clear_error(tmp_path, command):
    for name, (path, phrase) in _bad_records(tmp_path).items():
        res = CliRunner().invoke(app, [command, str(path)])
        assert res.exit_code != 0, (name, res.output)
        text = " ".join(res.output.split())  # the console wraps long lines at spaces
        assert phrase in text and str(path.name) in text, (name, res.output)
        assert "Traceback" not in res.output


def test_load_point_record_fits_stiffness_and_says_so(real_data_dir, tmp_path):
    import json

    out = tmp_path / "id.json"
    res = CliRunner().invoke(app, ["identify", str(real_data_dir / "leeman-p4309-step2.csv"), "--json", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert "finite_stiffness" in rep["whole_record"]["model"]
    assert any("rigid machine" in n for n in rep["notes"])
    assert any("includes the machine stiffness" in n for n in rep["notes"])
    # within ~2 sigma of the authors' xlook fit (a 0.007722 +- 0.000202, b 0.007067 +- 0.000183)
    p, e = rep["whole_record"]["params"], rep["whole_record"]["err_corr"]
    assert abs(p["A_mu"] - 0.007722) < 2 * max(e["A_mu"], 0.000202)
    assert abs(p["B_mu"] - 0.007067) < 2 * max(e["B_mu"], 0.000183)
