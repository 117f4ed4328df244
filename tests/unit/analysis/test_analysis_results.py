"""What identify, stability, reproduce and heal say and write at their edge (issue 23 items 3 and 7):
output paths checked before any work, a failed figure named by the path asked for, several files told
apart by name, eq. (13) said as the paper uses it, a negative A warned about, the stability report
typed. In-process and cheap: no trial is simulated and no record identified."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import typer
from rich.console import Console

from rig.analysis import stability as S
from rig.analysis.report import fmt, rounded
from rig.commands import analysis as A
from rig.commands.common import check_output_path, emit_outputs
from rig.model.checks import check_param
from rig.model.paper import TABLE2


def _console() -> Console:
    return Console(record=True, width=300, highlight=False)


def test_rounding_at_the_edge():
    assert rounded(1.23456789e-3) == 1.23457e-3
    assert rounded(2.0 / 3.0, 3) == 0.667
    assert rounded(float("nan")) is None and rounded(None) is None
    assert fmt(None) == "-" and fmt(float("inf")) == "-" and fmt(0.000123456) == "0.0001235"


def test_output_under_a_file_is_refused_before_work(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    with pytest.raises(typer.Exit) as exc:
        check_output_path(blocker / "fig.png", "--plot", (".png",))
    assert exc.value.exit_code == 1  # a file that cannot be written (common.py's exit table)
    err = capsys.readouterr().err
    assert f"--plot {blocker / 'fig.png'}: cannot write there" in err and "not a directory" in err
    assert list(tmp_path.iterdir()) == [blocker]  # nothing written, no temporary file left
    check_output_path(tmp_path / "new" / "dir" / "fig.png", "--plot", (".png",))  # made when written: fine


def test_a_failed_figure_names_the_path_asked_for(tmp_path, capsys):
    plot = tmp_path / "fig.png"

    def draw(path):
        raise PermissionError(13, "Permission denied", str(tmp_path / ".fig.png.x1y2.tmp"))

    with pytest.raises(typer.Exit) as exc:
        emit_outputs(_console(), None, {"a": 1}, plot, draw)
    assert exc.value.exit_code == 1
    err = capsys.readouterr().err
    assert f"cannot write {plot}" in err and ".tmp" not in err


def test_emit_outputs_writes_json_then_figure(tmp_path):
    con = _console()
    emit_outputs(con, tmp_path / "r.json", {"x": 1.5}, tmp_path / "f.png", lambda p: Path(p).write_bytes(b"png"))
    assert json.loads((tmp_path / "r.json").read_text()) == {"x": 1.5}
    assert (tmp_path / "f.png").read_bytes() == b"png"
    assert f"wrote {tmp_path / 'f.png'}" in con.export_text()


def _whole(A_mu: float) -> dict:
    return {"ok": True, "model": "rate_state", "velocity": "segments", "n_eff": 100.0, "n_points": 400,
            "params": {"mu0": 0.1, "A_mu": A_mu, "B_mu": 4e-3, "L_um": 19.0},
            "params_sd": {"mu0": 1e-4, "A_mu": 1e-4, "B_mu": 2e-4, "L_um": 1.0}, "k_cr_kN_per_m": 15.0, "rms_N": 0.2}


def _identification(fits: list, n_trials: int, warnings: list[dict]):
    """A typed identification with no step, ``fits`` its whole-record fits (their reports)."""
    from rig.analysis.identify import Identification, WholeRecordFit

    return Identification([[] for _ in range(n_trials)], [None] * n_trials,
                          [WholeRecordFit(w, params=dict(w["params"])) for w in fits],
                          mean=dict.fromkeys(("A_mu", "B_mu", "L_um", "k_cr_kN_per_m", "t_r_s"), 1.0),
                          sem=dict.fromkeys(("A_mu", "B_mu", "L_um", "k_cr_kN_per_m"), 0.1),
                          sem_over="trials" if n_trials > 1 else "steps", names=[f"f{i}" for i in range(n_trials)],
                          law="slip", warnings=warnings)


def test_several_files_are_told_apart_by_name():
    warns = [{"param": "B_mu", "where": "whole-record fit (trial 1)", "message": "B < 0"}]
    con = _console()
    A._print_identification(con, _identification([_whole(1e-3), _whole(2e-3)], 2, warns), "spec",
                            ["first.csv", "second.mcap"])
    text = con.export_text()
    assert "warning (!): whole-record fit (second.mcap): B < 0" in text  # the JSON's '(trial 1)', named
    lines = [ln for ln in text.splitlines() if ln.startswith("whole-record fit")]
    assert len(lines) == 2
    assert lines[0].startswith("whole-record fit of first.csv (") and lines[1].startswith("whole-record fit of "
                                                                                         "second.mcap (")
    con = _console()
    A._print_identification(con, _identification([_whole(1e-3)], 1, warns), "spec", ["only.csv"])
    assert "whole-record fit (rate_state" in con.export_text()  # one file: no name needed


def test_figure_names_the_files():
    from types import SimpleNamespace

    from rig.analysis.plots import _file_names

    idn = SimpleNamespace(data=["/x/a.csv", "/y/b.mcap"], trials=[0, 1])
    assert _file_names(idn) == ["a.csv", "b.mcap"]
    assert _file_names(SimpleNamespace(data="/x/a.csv", trials=[0])) == ["a.csv"]


def test_negative_A_is_not_physical_not_at_a_bound():
    w = check_param("A_mu", -1.42e-4)
    assert w["kind"] == "not_physical" and "below" in w["message"]
    assert check_param("A_mu", 0.0)["kind"] == "at_bound"  # on the fit's bound: a fit stopped there
    assert check_param("A_mu", 1.1e-3) is None


def test_reproduce_warns_of_one_trials_negative_A():
    from rig.analysis.reproduce import LubricantResult, MeanSem, ReproduceResult

    ok = {"A_mu": 2e-4, "B_mu": 1.1e-2, "L_um": 22.0}
    sem = {"A_mu": 1e-4, "B_mu": 1e-3, "L_um": 2.0}
    lub = LubricantResult("paraffin", 2, "synth", 0.12, [{"recovered": ok}, {"recovered": {**ok, "A_mu": -1.42e-4}}],
                          MeanSem(ok, sem), MeanSem(ok, sem), None, {})
    warns = A._reproduce_warnings(ReproduceResult(2, 0, {"paraffin": lub}))
    assert [(w["where"], w["param"], w["kind"]) for w in warns] == [("paraffin: trial 1 recovered", "A_mu",
                                                                      "not_physical")]


def test_eq13_said_per_interface_with_the_moving_piece_twice_that():
    A_mu, B_mu, L_um = (TABLE2["boundary"][k][0] for k in ("A_mu", "B_mu", "L_um"))
    k1 = (B_mu - A_mu) * 100.0 / L_um * 1e3  # eq. (13), N = 100 N: Table 2's 14.8 ± 2.3 kN/m
    text = S.per_interface_statement(A_mu, B_mu, L_um, 100.0)
    assert f"{k1:.4g} kN/m" in text and f"{2 * k1:.4g} kN/m" in text
    assert "one interface" in text and "paper's" not in text  # the recovered means are not the paper's
    assert abs(k1 - TABLE2["boundary"]["k_cr_kN_per_m"][0]) < TABLE2["boundary"]["k_cr_kN_per_m"][1]


def test_stability_params_from_an_identify_report():
    p, N = S.params_from_report({"mean": {"A_mu": 1e-3, "B_mu": 4e-3, "L_um": 20}, "normal_force_N": 90}, 100.0)
    assert p == {"A_mu": 1e-3, "B_mu": 4e-3, "L_um": 20.0} and N == 90.0
    with pytest.raises(ValueError, match="mean A_mu, B_mu, L_um"):
        S.params_from_report({"steps": []}, 100.0)
    with pytest.raises(ValueError, match="L_um"):
        S.params_from_report({"mean": {"A_mu": 1e-3, "B_mu": 4e-3, "L_um": -1}}, 100.0)


def test_stability_report_typed_and_unrounded():
    inp = S.StabilityInputs(1.1e-3, 4.0e-3, 19.2, 100.0, 10.0, 0.003, 1.0)
    a = S.analyse_set("boundary", {"A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.2}, inp, 2.0)
    res = S.StabilityReport(1.0, 10.0, 0.003, 0.0, 100.0, {"boundary": a}, [])
    doc = res.report()
    assert doc["schema"] == "rig.stability/2" and list(doc)[1:6] == ["V0_um_s", "mass_kg", "kd_N_s_per_um",
                                                                     "ki_N_per_um_s", "normal_force_N"]
    k13 = doc["analyses"]["boundary"]["k_cr_eq13_kN_per_m"]
    assert math.isclose(k13, (4.0e-3 - 1.1e-3) * 100.0 / 19.2 * 1e3, rel_tol=1e-12)  # not rounded for display
    assert doc["analyses"]["boundary"]["statement"].startswith("moving test piece")


def test_law_comparison_from_unrounded_sums_of_squares():
    """compare_laws reads the fits' own SSR and n_eff (WholeRecordFit fields), not their rounded JSON."""
    from rig.analysis.identify import WholeRecordFit, compare_laws
    from rig.fitting.stats import information_criterion

    def fit(ssr: float, n_eff: float) -> WholeRecordFit:
        rep = {"n_points": 1000, "n_params": 5, "rms_mu": rounded(math.sqrt(ssr / 1000)), "n_eff": rounded(n_eff, 4)}
        return WholeRecordFit(rep, params={"A_mu": 1e-3}, ssr=ssr, n_eff=n_eff)

    slip, aging = fit(1.0e-5, 123.456789), fit(1.2e-5, 99.0)
    c = compare_laws({"slip": slip, "aging": aging})
    assert c.n_eff == 123.456789  # the better fit's, unrounded
    assert c.bic["aging"] == information_criterion(1.2e-5, 1000, 123.456789, 5)
    assert c.preferred_law == "slip" and c.delta_bic > 6
    rep = c.report()
    assert rep["n_eff"] == 123.5 and rep["bic"]["slip"] == rounded(c.bic["slip"]) and rep["preferred_law"] == "slip"
    lost = WholeRecordFit({"ok": False, "reason": "least squares failed"})
    failed = compare_laws({"slip": slip, "aging": lost})
    assert failed.report() == {"preferred_law": "undecided", "reason": "a fit failed"}
    con = _console()
    A._print_laws(con, {"slip": lost, "aging": lost}, failed, "spec", None)  # no traceback: each says it failed
    text = con.export_text()
    assert text.count("whole-record fit failed: least squares failed") == 2
    assert "preferred law: undecided (a fit failed)" in text


def test_reproduce_means_are_of_unrounded_trial_values():
    """The means over trials are taken of the trials' own values; the report rounds once, rows included."""
    from rig.analysis.reproduce import lubricant_result

    rows = [{"truth": {"A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.0 + d}, "n_steps": 3, "sim_s": 0.123,
             "recovered": {"A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.0 + d + 1e-6 / 3}, "steps": []}
            for d in (0.0, 1.0000004)]
    res = lubricant_result("boundary", 2, "synth", 0.12, rows, [False, False], False)
    assert res.recovered.mean["L_um"] == pytest.approx(19.5000002 + 1e-6 / 3, rel=1e-15)
    assert res.checks["L_um"]["diff"] == pytest.approx(1e-6 / 3, rel=1e-6)  # not lost to rounding
    rep = res.report()
    assert rep["recovered"]["mean"]["L_um"] == 19.5
    assert rep["checks"]["L_um"]["diff"] == rounded(1e-6 / 3)
    assert rep["trials"][1]["recovered"]["L_um"] == 20.0 and rep["trials"][0]["sim_s"] == 0.12
