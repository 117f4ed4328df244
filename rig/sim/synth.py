"""The one synthetic-record generator (open loop: prescribed kinematics, no controller).

Kinematics are prescribed at the loop rate (1 kHz): either constant-velocity segments of
given slip joined by raised-cosine ramps of a 10-90 % rise time (:func:`generate`, the
paper's step and Stribeck protocols, with step events), or a commanded staircase of
velocities followed by a critically damped second-order servo (:func:`make_record`, the
diagnosis protocols, known catalogue effects). The force comes from the one forward model
(:func:`rig.model.forward.predict_force`, any catalogue extension) with the true
kinematics and normal forces, and the sensors from the rig profile (:class:`SensorChain`,
default config/rigs/sim.yaml): white noise of the profile's sigma (the paper's ± figures
read as 2 sigma) enters BEFORE each transducer's first-order analog filter (100 Hz LVDT
and friction, 10 Hz normals), then the record is sampled at ``rate_hz`` (optionally
jittered, with gaps) and the LVDT quantized (rig.model.sensors, the hardware's order).

``python -m rig.sim.synth OUT.csv --effect sensor_lag --seed 3`` writes one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.data import TrialData, write_csv
from rig.model import sensors
from rig.model.forward import as_model, predict_force
from rig.model.spec import FrictionModel
from rig.config.profile import RigProfile, default_profile_path, load_profile

N_NOM_N = 100.0
LOOP_DT_S = 1e-3

# baseline truth (boundary lubricant, Table 2)
BASE_TRUTH = {"mu0": 0.11, "A_mu": 0.0011, "B_mu": 0.0040, "L_um": 19.2}


@dataclass
class SensorChain:
    """Noise sigma of each reading (after its filter), analog cutoffs and LVDT quantization."""

    friction_sigma_N: float
    lvdt_sigma_um: float
    normal_sigma_N: float
    lvdt_quantization_um: float
    friction_cutoff_hz: float
    lvdt_cutoff_hz: float
    normal_cutoff_hz: float

    @classmethod
    def from_profile(cls, profile: RigProfile | str | Path | None = None, noise_scale: float = 1.0) -> "SensorChain":
        """The sensors of a rig profile (default: config/rigs/sim.yaml), noise times ``noise_scale``."""
        if profile is None:
            profile = default_profile_path()
        if not isinstance(profile, RigProfile):
            profile = load_profile(profile)
        s = profile.sensors
        return cls(s.friction_load_cell.noise_sigma_N * noise_scale, s.lvdt.noise_sigma_um * noise_scale,
                   s.normal_load_cells.noise_sigma_N * noise_scale, s.lvdt.quantization_um,
                   s.friction_load_cell.cutoff_hz, s.lvdt.cutoff_hz, s.normal_load_cells.cutoff_hz)

    def noiseless(self) -> "SensorChain":
        """The same filters without noise or quantization."""
        return SensorChain(0.0, 0.0, 0.0, 0.0, self.friction_cutoff_hz, self.lvdt_cutoff_hz, self.normal_cutoff_hz)


def measure(t_loop: np.ndarray, x_um: np.ndarray, F_N: np.ndarray, N1_N: np.ndarray, N2_N: np.ndarray,
            t_sample: np.ndarray, chain: SensorChain, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Sensor readings at ``t_sample`` of true signals on the loop grid ``t_loop``: noise, then
    the analog filter (on the loop grid), then sampling, then the LVDT's quantization.
    Returns (position_um, friction_N, normal_1_N, normal_2_N)."""
    dt = float(np.median(np.diff(t_loop))) if t_loop.size > 1 else LOOP_DT_S
    out = []
    for y, sig, fc in ((x_um, chain.lvdt_sigma_um, chain.lvdt_cutoff_hz),
                       (F_N, chain.friction_sigma_N, chain.friction_cutoff_hz),
                       (N1_N, chain.normal_sigma_N, chain.normal_cutoff_hz),
                       (N2_N, chain.normal_sigma_N, chain.normal_cutoff_hz)):
        a = sensors.noisy_filtered(t_loop, y, sensors.cutoff_tau_s(fc), sig, rng, dt)
        out.append(np.interp(t_sample, t_loop, a))
    q = chain.lvdt_quantization_um
    if q > 0:
        out[0] = np.round(out[0] / q) * q
    return tuple(out)


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


def protocol_paper(n_cycles: int = 2, hold_s: float = 60.0) -> list[tuple[float, float]]:
    """The paper's velocity steps 1 -> 2, 1 -> 5, 1 -> 10 µm/s: [(duration_s, v_um_s), ...]."""
    seg = []
    for _ in range(n_cycles):
        for v2 in (2.0, 5.0, 10.0):
            seg.append((hold_s, 1.0))
            seg.append((max(hold_s / v2 * 3.0, 15.0), v2))
    seg.append((hold_s, 1.0))
    return seg


def protocol_varied(rng: np.random.Generator, duration_s: float = 600.0, v_lo: float = 0.5,
                    v_hi: float = 20.0) -> list[tuple[float, float]]:
    """A staircase of random velocities (log-uniform) with holds long enough for ~100 µm of slip."""
    seg = []
    tot = 0.0
    v = 1.0
    while tot < duration_s:
        v = float(math.exp(rng.uniform(math.log(v_lo), math.log(v_hi))))
        d = float(np.clip(120.0 / v, 8.0, 90.0))
        seg.append((d, v))
        tot += d
    return seg


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
             chain: SensorChain | None = None, seed: int = 0, jitter: float = 0.0,
             gaps: int = 0, with_events: bool = True, lubricant: str = "") -> SynthRecord:
    """A record of the segments' kinematics. ``jitter`` (fraction of the sample interval) and
    ``gaps`` (number of dropped stretches of 5-20 samples) make the sampling uneven;
    ``chain`` defaults to the sim profile's sensors."""
    chain = SensorChain.from_profile() if chain is None else chain
    rng = np.random.default_rng(seed)
    dt = 1.0 / loop_hz
    t, v, events = _velocity_history(segments, rise_time_s, dt)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    # rider normal forces: slow +-0.5 % wander; friction always scales with them
    n = t.size
    wander = 0.005 * normal_force_N * np.sin(2 * math.pi * t / max(t[-1], 1.0) * 1.3 + rng.uniform(0, 6))
    n1 = normal_force_N + wander
    n2 = normal_force_N - 0.5 * wander
    ext = [e for e in model.extensions if e != "normal_force_variation"] + ["normal_force_variation"]
    fm = as_model(model.baseline, ext, model.params)
    friction = predict_force(fm, t, x, v, n1 + n2, normal_force_N, float(v[0]))
    mu = friction / (n1 + n2)
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
    x_meas, f_meas, n1_meas, n2_meas = measure(t, x, friction, n1, n2, t[idx], chain, rng)
    trial = TrialData(
        time_s=t[idx].copy(), position_um=x_meas, friction_N=f_meas, normal_1_N=n1_meas,
        normal_2_N=n2_meas, position_ref_um=x[idx].copy(),
        metadata={"normal_force_N": f"{normal_force_N:g}", "lubricant": lubricant,
                  "generator": "rig.sim.synth"},
        events=events if with_events else [], source="synth",
    )
    truth = {"params": dict(model.params), "true_v_um_s": v[idx].copy(), "true_mu": mu[idx].copy(),
             "true_x_um": x[idx].copy(), "events": events}
    return SynthRecord(trial=trial, truth=truth)


def _servo(t, xr, tau):
    """Critically damped 2nd-order follower of ``xr`` (exact for piecewise-linear input)."""
    if tau <= 0:
        return xr.copy()
    return sensors.lowpass_uneven(t, sensors.lowpass_uneven(t, xr, tau), tau)


@dataclass
class SynthSpec:
    protocol: str | list = "paper"
    duration_s: float = 600.0
    rate_hz: float = 25.0
    baseline: str = "rate_state"
    params: dict = field(default_factory=lambda: dict(BASE_TRUTH))
    effects: dict = field(default_factory=dict)  # extension -> its params
    with_ref: bool = True
    servo_tau_s: float = 0.05
    jitter: float = 0.0        # fraction of the sample interval
    gaps: int = 0              # number of 1-3 s gaps
    noise_scale: float = 1.0   # times the profile's sensor noise
    profile: str | None = None  # rig profile of the sensors (None: config/rigs/sim.yaml)
    normal_variation: dict = field(default_factory=dict)  # {"amp_frac": .03, "period_s": 40}
    seed: int = 0


def make_record(spec: SynthSpec) -> tuple[TrialData, dict]:
    """A synthetic trial and its truth ``{"baseline", "extensions", "params"}``."""
    rng = np.random.default_rng(spec.seed)
    pre = 20.0  # pre-roll at the first velocity, cut off: the record starts in steady sliding
    segs = _protocol_segments(spec, rng)
    segs = [(pre, segs[0][1])] + segs
    T = sum(d for d, _ in segs)
    dt = LOOP_DT_S
    tf = np.arange(0.0, T, dt)
    edges = np.cumsum([0.0] + [d for d, _ in segs])
    vel = np.array([v for _, v in segs])
    seg_i = np.clip(np.searchsorted(edges, tf, side="right") - 1, 0, len(segs) - 1)
    v_ref = vel[seg_i]
    x_ref = np.concatenate([[0.0], np.cumsum(0.5 * (v_ref[1:] + v_ref[:-1]) * dt)])
    x_true = _servo(tf, x_ref, spec.servo_tau_s)
    v_true = np.gradient(x_true, tf)
    N1, N2 = _normal_forces(spec, tf, T, rng)
    exts, params = list(spec.effects), _truth_params(spec)
    # friction always scales with the true normal force
    ext_sim = [e for e in exts if e != "normal_force_variation"] + ["normal_force_variation"]
    F_true = predict_force(as_model(spec.baseline, ext_sim, params), tf, x_true, v_true, N1 + N2, N_NOM_N,
                           v_init_um_s=segs[0][1])
    # sampling (after the pre-roll; the record's clock starts at 0)
    cut = tf >= pre
    tf, x_true, x_ref, F_true, N1, N2 = (a[cut] for a in (tf, x_true, x_ref, F_true, N1, N2))
    tf = tf - pre
    x0 = x_ref[0]
    x_true, x_ref = x_true - x0, x_ref - x0
    ts = _sample_times(spec, T - pre, float(tf[-1]), rng)
    chain = SensorChain.from_profile(spec.profile, spec.noise_scale)
    xm, Fm, n1, n2 = measure(tf, x_true, F_true, N1, N2, ts, chain, rng)
    truth = {"baseline": spec.baseline, "extensions": [e for e in exts], "params": params}
    meta = {"normal_force_N": f"{N_NOM_N:g}", "lubricant": "boundary", "synthetic": "rig.sim.synth",
            "truth": json.dumps(truth, sort_keys=True), "seed": str(spec.seed)}
    trial = TrialData(time_s=ts, position_um=xm, friction_N=Fm, normal_1_N=n1, normal_2_N=n2,
                      position_ref_um=np.interp(ts, tf, x_ref) if spec.with_ref else None, metadata=meta,
                      source=f"synth(seed={spec.seed})")
    return trial, truth


def _protocol_segments(spec: SynthSpec, rng: np.random.Generator) -> list[tuple[float, float]]:
    """The (duration s, velocity µm/s) segments of the spec's protocol: ``paper`` (repeated to fill
    the duration), ``varied`` (random) or the list given."""
    if not isinstance(spec.protocol, str):
        return list(spec.protocol)
    if spec.protocol == "paper":
        hold = max(20.0, spec.duration_s / 13.0)
        total = sum(d for d, _ in protocol_paper(1, hold))
        return protocol_paper(max(1, int(round(spec.duration_s / total))), hold)  # repeated to fill the duration
    if spec.protocol == "varied":
        return protocol_varied(rng, spec.duration_s)
    raise ValueError(f"unknown protocol {spec.protocol!r} (paper, varied)")


def _normal_forces(spec: SynthSpec, tf: np.ndarray, T: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The true normal force on each rider (N): nominal, or varying (``normal_variation``; the
    ``normal_force_variation`` effect's default) in a sine of random phase plus a drift."""
    N1 = np.full(tf.shape, N_NOM_N)
    N2 = np.full(tf.shape, N_NOM_N)
    nv = dict(spec.normal_variation)
    if "normal_force_variation" in spec.effects and not nv:
        nv = {"amp_frac": 0.04, "period_s": 37.0, "drift_frac": 0.03}
    if nv:
        ph = rng.uniform(0, 2 * math.pi)
        a = nv.get("amp_frac", 0.03)
        P = nv.get("period_s", 40.0)
        d = nv.get("drift_frac", 0.0)
        mod = a * np.sin(2 * math.pi * tf / P + ph) + d * (tf / T)
        N1 = N1 * (1 + mod)
        N2 = N2 * (1 + 0.8 * mod)
    return N1, N2


def _truth_params(spec: SynthSpec) -> dict:
    """The true parameters: the spec's, each effect's; a steady_state baseline's slope c_mu = A - B."""
    params = dict(spec.params)
    for pe in spec.effects.values():
        params.update(pe)
    if spec.baseline == "steady_state" and "frictional_memory" not in spec.effects:
        params.setdefault("c_mu", params.get("A_mu", 0.0011) - params.get("B_mu", 0.004))
        for k in ("A_mu", "B_mu", "L_um"):
            params.pop(k, None)
    return params


def _sample_times(spec: SynthSpec, T: float, t_end_s: float, rng: np.random.Generator) -> np.ndarray:
    """The record's sample times over ``T`` seconds: the spec's rate, with jitter and gaps."""
    n_s = int(T * spec.rate_hz)
    ts = (np.arange(n_s) + 0.5) / spec.rate_hz
    if spec.jitter > 0:
        ts = ts + rng.uniform(-0.5, 0.5, n_s) * spec.jitter / spec.rate_hz
        ts = np.sort(ts)
    keep = np.ones(n_s, bool)
    for _ in range(spec.gaps):
        g0 = rng.uniform(0.1 * T, 0.9 * T)
        keep &= ~((ts > g0) & (ts < g0 + rng.uniform(1.0, 3.0)))
    ts = ts[keep & (ts < t_end_s)]
    return ts[np.concatenate([[True], np.diff(ts) > 0])]


# plausible sizes of every catalogue effect (random within these ranges)
def random_effect(name: str, rng: np.random.Generator) -> dict:
    u = rng.uniform
    if name == "second_state_variable":
        return {"B2_mu": float(u(0.0015, 0.003)), "L2_um": float(u(120.0, 300.0))}
    if name == "aging_law":
        return {"L_um": float(u(15.0, 30.0))}
    if name == "sensor_lag":
        return {"tau_s": float(u(0.3, 0.8))}
    if name == "normal_force_variation":
        return {}
    if name == "slip_wear_drift":
        return {"rate_mu_per_mm": float(u(0.6e-3, 1.2e-3)) * (1 if u() < 0.5 else -1)}
    if name == "force_offset_drift":
        return {"rate_N_per_s": float(u(0.6e-3, 1.2e-3)) * (1 if u() < 0.5 else -1)}
    if name == "position_periodic":
        return {"amplitude_mu": float(u(0.0008, 0.0015)), "wavelength_um": float(u(60.0, 300.0)),
                "phase_rad": float(u(-3.0, 3.0))}
    if name == "finite_stiffness":
        return {"stiffness_kN_per_m": float(u(150.0, 400.0))}
    if name == "time_delay":
        return {"delay_s": float(u(0.5, 1.5))}
    if name == "frictional_memory":
        return {"A_mu": 0.0011, "B_mu": 0.004, "L_um": float(u(15.0, 30.0))}
    raise ValueError(f"unknown effect {name!r}")


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="write a synthetic record with known catalogue effects")
    ap.add_argument("out")
    ap.add_argument("--effect", action="append", default=[])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate-hz", type=float, default=25.0)
    ap.add_argument("--duration-s", type=float, default=600.0)
    ap.add_argument("--protocol", default="paper")
    ap.add_argument("--no-ref", action="store_true")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    eff = {e: random_effect(e, rng) for e in a.effect}
    spec = SynthSpec(protocol=a.protocol, duration_s=a.duration_s, rate_hz=a.rate_hz, effects=eff,
                     with_ref=not a.no_ref, seed=a.seed)
    trial, truth = make_record(spec)
    write_csv(trial, Path(a.out))
    print(json.dumps(truth))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
