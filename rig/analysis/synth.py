"""A light kinematic generator of trial records (no controller, no valve).

The velocity history is prescribed (constant levels joined by raised-cosine
ramps of a given 10-90 % rise time); position is its integral; the friction
coefficient comes from the shared model (:func:`rig.model.friction.mu_series`,
eqs. 5-6) evaluated at the 1 kHz loop rate; the sensors then add what the
paper describes (section 3): the friction load cell low-pass filtered at
100 Hz with +-0.25 N noise, the LVDT filtered at 100 Hz with +-0.25 µm noise
and a 0.076 µm quantization step, rider load cells filtered at 10 Hz with
+-0.6 N noise; the record is logged at ``rate_hz`` (25 Hz by default, like
the paper's Fig. 8). The ``+-`` figures are used as one standard deviation
(pessimistic).

It is used by the tests (known truth) and, until the full simulated rig
(:mod:`rig.sim`) is available, by the Table-2 reproduction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.data import TrialData
from rig.model.spec import FrictionModel
from rig.model.sensors import lowpass_uneven
from rig.model.friction import mu_series


@dataclass
class SensorNoise:
    """Sensor noise (standard deviations) and quantization, paper section 3."""

    friction_sd_N: float = 0.25
    lvdt_sd_um: float = 0.25
    lvdt_quant_um: float = 0.076
    normal_sd_N: float = 0.6
    friction_filter_hz: float = 100.0
    lvdt_filter_hz: float = 100.0
    normal_filter_hz: float = 10.0

    @classmethod
    def none(cls) -> "SensorNoise":
        return cls(0.0, 0.0, 0.0, 0.0)


@dataclass
class Segment:
    """Slide at ``v_um_s`` for ``slip_um`` of displacement."""

    v_um_s: float
    slip_um: float


def paper_step_protocol(v_low: float = 1.0, highs=(2.0, 5.0, 10.0), pre_um: float = 300.0,
                        post_um: float = 350.0, back_um: float = 300.0) -> list[Segment]:
    """The paper's step protocol: steady sliding at ``v_low``, then for each ``v_high``
    a step up (held ``post_um``, enough for the 250 µm window plus 200 points) and a
    step back down (held ``back_um``, long enough to return to steady state)."""
    segs = [Segment(v_low, pre_um)]
    for vh in highs:
        segs.append(Segment(vh, post_um))
        segs.append(Segment(v_low, back_um))
    return segs


def stribeck_protocol(velocities=(1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0), seg_um: float = 250.0,
                      up_and_down: bool = True) -> list[Segment]:
    """The paper's Stribeck pass (section 4.1, Fig. 5): a step every 250 µm, lowest
    velocity first, up to the highest and back down."""
    vs = list(velocities)
    if up_and_down:
        vs = vs + vs[-2::-1]
    return [Segment(v, seg_um) for v in vs]


@dataclass
class SynthRecord:
    trial: TrialData
    truth: dict = field(default_factory=dict)


def _velocity_history(segments: list[Segment], rise_time_s: float, dt: float):
    """Velocity at the loop rate and the step events (raised-cosine ramps centred on the
    nominal switch; 10-90 % rise of a raised cosine of duration T is 0.59 T)."""
    ramp_T = rise_time_s / 0.5903 if rise_time_s > 0 else 0.0
    t_switch = []
    t = 0.0
    for seg in segments:
        t += seg.slip_um / seg.v_um_s
        t_switch.append(t)
    total = t_switch[-1]
    n = int(math.ceil(total / dt)) + 1
    tt = np.arange(n) * dt
    v = np.full(n, segments[0].v_um_s)
    events = []
    for k in range(1, len(segments)):
        ts = t_switch[k - 1]
        v1, v2 = segments[k - 1].v_um_s, segments[k].v_um_s
        if ramp_T > 0:
            u = np.clip((tt - (ts - ramp_T / 2)) / ramp_T, 0.0, 1.0)
            w = 0.5 - 0.5 * np.cos(math.pi * u)
        else:
            w = (tt >= ts).astype(float)
        mask = tt >= ts - ramp_T / 2
        v[mask] = v1 + (v2 - v1) * w[mask]
        events.append({"t_s": float(ts), "kind": "velocity_step", "v1_um_s": float(v1), "v2_um_s": float(v2)})
    return tt, v, events


def generate(model: FrictionModel, segments: list[Segment], *, normal_force_N: float = 100.0,
             rate_hz: float = 25.0, loop_hz: float = 1000.0, rise_time_s: float = 0.3,
             noise: SensorNoise | None = None, seed: int = 0, jitter: float = 0.0,
             gaps: int = 0, with_events: bool = True, lubricant: str = "") -> SynthRecord:
    """Generate one record. ``jitter`` (fraction of the sample interval) and ``gaps``
    (number of dropped stretches of 5-20 samples) make the sampling uneven."""
    noise = SensorNoise() if noise is None else noise
    rng = np.random.default_rng(seed)
    dt = 1.0 / loop_hz
    t, v, events = _velocity_history(segments, rise_time_s, dt)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    p = model.to_array()
    mu = mu_series(p, t, v, x, float(v[0]))
    # rider normal forces: slow +-0.5 % wander plus noise, 10 Hz filter
    n = t.size
    wander = 0.005 * normal_force_N * np.sin(2 * math.pi * t / max(t[-1], 1.0) * 1.3 + rng.uniform(0, 6))
    n1 = normal_force_N + wander
    n2 = normal_force_N - 0.5 * wander
    friction = mu * (n1 + n2)
    tau_f = 1.0 / (2 * math.pi * noise.friction_filter_hz)
    tau_x = 1.0 / (2 * math.pi * noise.lvdt_filter_hz)
    tau_n = 1.0 / (2 * math.pi * noise.normal_filter_hz)
    # logged samples (possibly uneven)
    step = max(1, int(round(loop_hz / rate_hz)))
    idx = np.arange(0, n, step)
    if jitter > 0:
        off = np.round(rng.uniform(-jitter / 2, jitter / 2, idx.size) * step).astype(int)
        idx = np.clip(idx + off, 0, n - 1)
        idx = np.unique(idx)
    if gaps > 0:
        keep = np.ones(idx.size, bool)
        for _ in range(gaps):
            j = rng.integers(10, max(11, idx.size - 30))
            keep[j:j + rng.integers(5, 21)] = False
        idx = idx[keep]
    # filters act at the loop rate on clean signals; noise is white at the sample
    f_meas = lowpass_uneven(t, friction, tau_f)[idx]
    x_meas = lowpass_uneven(t, x, tau_x)[idx]
    n1_meas = lowpass_uneven(t, n1, tau_n)[idx]
    n2_meas = lowpass_uneven(t, n2, tau_n)[idx]
    m = idx.size
    f_meas = f_meas + noise.friction_sd_N * rng.standard_normal(m)
    x_meas = x_meas + noise.lvdt_sd_um * rng.standard_normal(m)
    if noise.lvdt_quant_um > 0:
        x_meas = np.round(x_meas / noise.lvdt_quant_um) * noise.lvdt_quant_um
    n1_meas = n1_meas + noise.normal_sd_N * rng.standard_normal(m)
    n2_meas = n2_meas + noise.normal_sd_N * rng.standard_normal(m)
    trial = TrialData(
        time_s=t[idx].copy(), position_um=x_meas, friction_N=f_meas, normal_1_N=n1_meas,
        normal_2_N=n2_meas, position_ref_um=x[idx].copy(),
        metadata={"normal_force_N": f"{normal_force_N:g}", "lubricant": lubricant,
                  "generator": "rig.analysis.synth"},
        events=events if with_events else [], source="synth",
    )
    truth = {"params": dict(model.params), "true_v_um_s": v[idx].copy(), "true_mu": mu[idx].copy(),
             "true_x_um": x[idx].copy(), "events": events}
    return SynthRecord(trial=trial, truth=truth)
