"""The figures, checked for what a reader of the printed page would notice: no 'None' or
'nan' in any text, no two tick labels of an axis overlapping, no text outside the page
(a footnote cut off), no empty panel, parameter warnings marked, one page width.

Records: a synthetic velocity-step trial like the main job's, the real Leeman record (one
step, a negative k_cr), the real sepiolite record (its only step rejected, B < 0 in the
whole-record fit), the diagnosis of the Leeman record, the stability map of docs/ and a
reproduce report."""

from __future__ import annotations

import json
import math

import pytest

from rig.analysis import plots
from rig.analysis.identify import identify_files, identify_trials
from rig.model.spec import FrictionModel
from rig.sim import synth


BOUNDARY = FrictionModel(params={"mu0": 0.1, "A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.2})


def _texts(fig):
    from matplotlib.text import Text

    return [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]


def check_figure(fig, *, n_data_axes_min: int = 1):
    """The properties every figure must have (asserts; returns the figure's texts)."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    texts = _texts(fig)
    for t in texts:
        s = t.get_text()
        assert "None" not in s and "nan" not in s.split() and "nan " not in s, s
    # nothing outside the page (1 px tolerance)
    W, H = fig.bbox.width, fig.bbox.height
    ticks = {id(t) for ax in fig.axes for axis in (ax.xaxis, ax.yaxis) for t in axis.get_ticklabels(which="both")}
    for t in texts:
        if id(t) in ticks:
            continue
        bb = t.get_window_extent(r)
        assert bb.x0 >= -1 and bb.y0 >= -1 and bb.x1 <= W + 1 and bb.y1 <= H + 1, (t.get_text()[:60], bb, W, H)
    # tick labels of one axis never overlap
    data_axes = 0
    for ax in fig.axes:
        if not ax.axison:
            continue
        for axis, horiz in ((ax.xaxis, True), (ax.yaxis, False)):
            lo, hi = sorted(axis.get_view_interval())
            labs = [t for minor in (False, True)
                    for loc, t in zip(axis.get_ticklocs(minor=minor), axis.get_ticklabels(minor=minor))
                    if t.get_visible() and t.get_text().strip() and lo <= loc <= hi]
            bbs = sorted((t.get_window_extent(r) for t in labs), key=lambda b: b.x0 if horiz else b.y0)
            for a, b in zip(bbs, bbs[1:]):
                gap = (b.x0 - a.x1) if horiz else (b.y0 - a.y1)
                assert gap > -0.5, f"overlapping tick labels on {ax.get_title()[:40]!r}"
        # no axes without data
        has = any(len(getattr(ln, "get_xdata")()) for ln in ax.lines) or any(
            len(c.get_offsets()) for c in ax.collections if hasattr(c, "get_offsets")) or ax.patches or ax.containers
        assert has, f"an empty panel: {ax.get_title()[:60]!r}"
        data_axes += 1
    assert data_axes >= n_data_axes_min
    assert fig.get_figwidth() == pytest.approx(plots.PAGE_WIDTH_IN)
    return " ".join(t.get_text() for t in texts)


def test_identify_figure_main_job_like():
    rec = synth.generate(BOUNDARY, synth.paper_step_protocol(), seed=11, rate_hz=25.0)
    idn = identify_trials([rec.trial], names=["steps.csv"])
    fig = plots.build_identification(idn)
    text = check_figure(fig, n_data_axes_min=2 + 3)
    assert "window kept" in text and "other μ2 windows" in text  # the shaded windows have a legend
    assert f"mean over {idn.report()['n_steps']} steps" in text
    assert "k_cr" not in fig.axes[0].get_title()  # shown only when flagged
    # fewer significant figures: no number in a title carries more than 4
    import re

    for t in (ax.get_title() for ax in fig.axes):
        for num in re.findall(r"\d+\.\d+", t):
            assert len(num.replace(".", "").lstrip("0")) <= 4, (num, t)


def test_identify_figure_single_step_real_record_warns(real_data_dir):
    idn = identify_files([real_data_dir / "leeman-p4309-step2.csv"])
    fig = plots.build_identification(idn)
    text = check_figure(fig, n_data_axes_min=3)  # record, velocity, one step: no empty panels
    assert "k_cr (eq. 13)" in text and "(!)" in text and "is no stiffness" in text
    assert "k_cr = -2.63 kN/m (!)" in fig.axes[0].get_title() and "(mean over 1 step)" in fig.axes[0].get_title()


def test_identify_figure_all_steps_rejected(real_data_dir):
    idn = identify_files([real_data_dir / "giacomel-sepiolite-tr2.csv"])
    assert idn.report()["n_steps"] == 0
    fig = plots.build_identification(idn)
    text = check_figure(fig)
    assert "no accepted step (1 rejected)" in text
    assert "rejected step at t =" in text and "B_mu" in text and "(!)" in text


def test_diagnosis_figure(real_data_dir):
    from rig.commands.diagnose import diagnosis_warnings
    from rig.diagnosis import diagnose
    from rig.diagnosis.plot import build_diagnosis
    from rig.log import load_trial

    d = diagnose(load_trial(real_data_dir / "leeman-p4309-step2.csv"))
    rep = d.report()
    fig = build_diagnosis(d, diagnosis_warnings(rep))
    text = check_figure(fig, n_data_axes_min=5)
    titled = [ax.get_title() for ax in fig.axes if ax.axison]
    assert sum(t.startswith("residual against") for t in titled) == 3
    # the legend is the figure's, above the panels: no legend inside a data panel
    assert all(ax.get_legend() is None for ax in fig.axes)
    assert fig.legends
    for f in rep["findings"]:
        assert f["cause"] in text


def test_stability_map_figure(repo_root):
    scans = json.loads((repo_root / "docs" / "stability-map.json").read_text())
    from rig.analysis.stability import ONSET_SPREAD, SPREAD_MAX

    fig = plots.build_stability_map(scans, title="kp scan", spread_max=SPREAD_MAX, onset_spread=ONSET_SPREAD)
    text = check_figure(fig, n_data_axes_min=len(scans))
    assert "fig1" not in text and "SimRig" not in text and "rig_loop" not in text
    assert "sim/analysis−1 ∈ [" in text  # the simulated boundary as its bracket, never a point


def test_reproduce_figure_with_warning():
    rep = {"n_trials": 2, "lubricants": {}}
    from rig.model.paper import TABLE2

    for lub, row in TABLE2.items():
        m = {k: row[k][0] for k in ("A_mu", "B_mu", "L_um", "k_cr_kN_per_m")}
        e = {k: row[k][1] for k in m}
        rep["lubricants"][lub] = {"paper": {k: {"mean": m[k], "sem": e[k]} for k in m},
                                  "truth": {"mean": m, "sem": e}, "recovered": {"mean": dict(m), "sem": e}}
    rep["lubricants"]["boundary"]["recovered"]["mean"]["B_mu"] = -1e-3
    from rig.model.checks import check_params

    warns = check_params(rep["lubricants"]["boundary"]["recovered"]["mean"], where="boundary: recovered mean")
    assert [w["param"] for w in warns] == ["B_mu", "k_cr_kN_per_m"] or "B_mu" in {w["param"] for w in warns}
    fig = plots.build_reproduce(rep, warns)
    text = check_figure(fig, n_data_axes_min=4)
    assert "A (direct effect, eq. 5)" in text and "L (µm)" in text and "k_cr (kN/m)" in text
    assert "(!)" in text and "boundary: recovered mean" in text


def test_plot_writes_png_at_print_size(tmp_path, real_data_dir):
    idn = identify_files([real_data_dir / "leeman-p4309-step2.csv"])
    p = tmp_path / "id.png"
    plots.plot_identification(idn, p)
    from PIL import Image

    w, _ = Image.open(p).size
    assert w == pytest.approx(plots.PAGE_WIDTH_IN * plots.DPI, abs=2)
    assert math.isfinite(w)


def test_stribeck_figure():
    from rig.analysis.stribeck import build_stribeck, stribeck

    paraffin = FrictionModel(params={"mu0": 0.12, "A_mu": 2e-4, "B_mu": 0.0111, "L_um": 22.4})
    rec = synth.generate(paraffin, synth.stribeck_protocol((1.0, 2.0, 5.0, 10.0, 50.0, 100.0)), seed=3, jitter=0.3)
    rep = stribeck([rec.trial], use_events=False)
    fig = build_stribeck(rep)
    text = check_figure(fig, n_data_axes_min=2)
    assert "up branch (6 levels)" in text and "eq. (7): A − B" in text
    assert "1 trials" not in text
