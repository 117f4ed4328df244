"""Loop tuning: the square and sine_sweep segments, the H1 estimate, `rig tune step|frf|autotune`
on a simulated sweep (measured vs rig stability's loop model, the plant fit, gains within 15 %
of the analytic advice, the overlay profile)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from rig.analysis.tuning import h1_estimate, margins
from rig.cli import app
from rig.config.recipe import RecipeError, compile_recipe, parse_recipe
from trajectories import PlanError, RigLimits


LIM = RigLimits(loop_rate_hz=1000.0, stroke_min_um=0.0, stroke_max_um=5000.0, max_speed_um_s=1000.0,
                initial_position_um=500.0, source="test")


def rec(seg: str, extra: str = ""):
    return parse_recipe(f"name: t\nlubricant: boundary\n{extra}segments:\n{seg}")


def test_square_is_speed_limited_edges_about_the_position():
    p = compile_recipe(rec("  - {kind: square, amplitude_um: 4, frequency_hz: 5, cycles: 3}\n"), limits=LIM)
    ev = p.events_of("square")[0]
    x, v = p.x_ref_um, p.v_ref_um_s
    assert ev["edge_s"] == pytest.approx(8e-3) and len(ev["edges_t_s"]) == 7
    assert x.max() == pytest.approx(504.0) and x.min() == pytest.approx(496.0) and x[-1] == pytest.approx(500.0)
    assert np.abs(v).max() == pytest.approx(1000.0)            # the edges at the rig's maximum speed
    for k, te in enumerate(ev["edges_t_s"][:-1]):              # each level held after its edge
        i = int(round((te + 0.05) * 1000))
        assert x[i] == pytest.approx(500.0 + (4.0 if k % 2 == 0 else -4.0))


def test_sine_sweep_is_a_log_chirp_within_the_limits():
    p = compile_recipe(rec("  - {kind: sine_sweep, f0_hz: 1, f1_hz: 50, amplitude_um: 2, duration_s: 10}\n"),
                       limits=LIM)
    ev = p.events_of("sine_sweep")[0]
    x = p.x_ref_um - 500.0
    t = p.t_s - ev["t_s"]
    assert np.abs(x).max() <= 2.0 + 1e-9 and abs(x[0]) < 1e-9 and abs(x[-1]) < 1e-6
    # zero crossings follow the instantaneous frequency f0 (f1/f0)^(t/T)
    zc = t[1:][(np.sign(x[1:]) != np.sign(x[:-1])) & (x[:-1] != 0)]
    def phase(tt):
        return 2 * np.pi * 1.0 * 10.0 / np.log(50.0) * (50.0 ** (tt / 10.0) - 1.0)

    for t1, t2 in ((2.0, 4.0), (5.0, 7.0), (8.0, 9.0)):
        n_zc = int(((zc > t1) & (zc < t2)).sum())
        assert abs(n_zc - (phase(t2) - phase(t1)) / np.pi) <= 1.0
    # on a slide: the reference moves on beneath the chirp
    p = compile_recipe(rec("  - {kind: sine_sweep, f0_hz: 1, f1_hz: 50, amplitude_um: 0.2, duration_s: 2, "
                           "velocity_um_s: 100}\n"), limits=LIM)
    assert p.v_ref_um_s.min() > 0 - 1e-9 and p.segments[0]["x_end_um"] > 700.0


@pytest.mark.parametrize("seg, msg", [
    ("{kind: sine_sweep, f0_hz: 1, f1_hz: 100, amplitude_um: 2, duration_s: 10}", r"speed 1\d\d\d.* maximum 1000"),
    ("{kind: square, amplitude_um: 300, frequency_hz: 2, cycles: 1}", "edge"),
    ("{kind: square, amplitude_um: 50, frequency_hz: 1, cycles: 1, velocity_um_s: 900}", "maximum 1000"),
    ("{kind: square, amplitude_um: 600, frequency_hz: 0.1, cycles: 1}", "outside the stroke"),
])
def test_tuning_segments_are_checked_before_anything_moves(seg, msg):
    with pytest.raises(PlanError, match=msg):
        compile_recipe(rec(f"  - {seg}\n"), limits=LIM)


def test_tuning_segments_need_the_loop_rate_log_and_a_rising_sweep():
    with pytest.raises(PlanError, match="log.raw_rate_hz 500 Hz must be 1000"):
        compile_recipe(rec("  - {kind: square, amplitude_um: 1, frequency_hz: 1}\n",
                           "log: {raw_rate_hz: 500}\n"), limits=LIM)
    with pytest.raises(RecipeError, match="f1_hz .* must exceed f0_hz"):
        rec("  - {kind: sine_sweep, f0_hz: 10, f1_hz: 5, amplitude_um: 1, duration_s: 3}\n")


def test_h1_recovers_a_known_filter_through_output_noise_and_skips_stalls():
    from scipy.signal import lfilter

    rng = np.random.default_rng(1)
    fs, n = 1000.0, 40_000
    r = rng.normal(0, 1, n)
    a = math.exp(-2 * math.pi * 20 / fs)                     # first order, 20 Hz
    y = lfilter([1 - a], [1, -a], r) + rng.normal(0, 0.05, n)
    keep = np.ones(n, bool)
    keep[10_000:10_100] = False
    f, H, coh, used, n_bin = h1_estimate(r, y, fs, 1024, keep)
    z = np.exp(-2j * np.pi * f / fs)
    true = (1 - a) / (1 - a * z)
    sel = (f > 1) & (f < 50)
    assert np.abs(20 * np.log10(np.abs(H[sel] / true[sel]))).max() < 0.5
    assert np.abs(np.degrees(np.angle(H[sel] / true[sel]))).max() < 4.0
    assert coh[(f > 1) & (f < 10)].min() > 0.8
    assert used == 2 * n // 1024 - 1 - 2                        # the two segments over the stall left out
    assert (n_bin == used).all()


def test_margins_of_a_known_loop():
    f = np.geomspace(0.1, 1000, 20000)
    s = 2j * np.pi * f
    L = 100.0 / (s * (s / 50 + 1) * (s / 500 + 1))             # integrator with two lags
    m = margins(f, L)
    wc = m["crossover_hz"] * 2 * np.pi
    assert abs(abs(100.0 / (1j * wc * (1j * wc / 50 + 1) * (1j * wc / 500 + 1))) - 1) < 1e-3
    pm = 180 - 90 - math.degrees(math.atan(wc / 50) + math.atan(wc / 500))
    assert m["phase_margin_deg"] == pytest.approx(pm, abs=0.1)
    w180 = math.sqrt(50 * 500)                                # phase -180 where atan sum = 90 deg
    gm = -20 * math.log10(100.0 / (w180 * math.hypot(1, w180 / 50) * math.hypot(1, w180 / 500)))
    assert m["gain_margin_db"] == pytest.approx(gm, abs=0.05)


def test_frf_matches_the_loop_model_on_the_simulated_rig(sweep_log):
    res = CliRunner().invoke(app, ["tune", "frf", str(sweep_log / "tune.mcap"), "--json", str(sweep_log / "frf.json"),
                                   "--plot", str(sweep_log / "frf.png")])
    assert res.exit_code == 0, res.output
    doc = json.loads((sweep_log / "frf.json").read_text())
    n = len(doc["frequency_hz"])
    assert n > 20 and all(len(doc[k]) == n for k in ("gain_db", "phase_deg", "coherence"))
    c = doc["compare"]
    assert c["n"] >= 15 and c["gain_db_rms"] < 0.8 and c["phase_deg_rms"] < 6.0
    assert 50 < doc["phase_margin_deg"] < 90 and doc["crossover_hz"] > 0
    assert (sweep_log / "frf.png").stat().st_size > 20_000


def test_step_metrics_on_the_square(sweep_log):
    res = CliRunner().invoke(app, ["tune", "step", str(sweep_log / "tune.mcap"), "--json", "-"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    ups = [e for e in doc["edges"] if e["delta_um"] > 0 and e["rise_s"] is not None]
    assert ups and all(0 < e["rise_s"] < 0.05 for e in ups)       # 10 µm at 500 µm/s: a 20 ms edge
    downs = [e for e in doc["edges"] if e["delta_um"] < 0]
    assert downs and all(e["reverses"] for e in downs)           # 500 µm/s against a 50 µm/s slide
    assert not set(doc["edges_in_means"]) & {e["edge"] for e in downs}
    assert doc["following_error_max_um"] < 20.0
