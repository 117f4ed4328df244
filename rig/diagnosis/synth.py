"""Synthetic measured records with known catalogue effects (a lighter model of the rig).

The trajectory is a sequence of constant-velocity segments (the paper's
velocity steps 1 -> 2, 1 -> 5, 1 -> 10 µm/s, or a random staircase of
velocities). The load point follows the commanded position through a
critically damped second-order servo (``servo_tau_s``; the paper's steps rise
in < 0.5 s). Friction comes from the shared model of :mod:`rig.model.friction`
through :func:`rig.model.forward.predict_force` evaluated on a 1 kHz
internal grid with the *true* kinematics, with any catalogue effect injected.
The record is then sampled (25 Hz to 1 kHz, optionally jittered and with
gaps) and the rig's sensor noise added: friction ±0.25 N, LVDT ±0.25 µm then
quantized to 0.076 µm, normal load cells ±0.6 N (the ± values are used as
Gaussian standard deviations: a pessimistic reading of the paper's
resolutions). With or without ``position_ref_um``.

``python -m rig.diagnosis.synth OUT.csv --effect sensor_lag --seed 3`` writes one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.data import TrialData, write_csv

from rig.model.forward import as_model, predict_force

LVDT_Q_UM = 0.076
NOISE_F_N = 0.25
NOISE_X_UM = 0.25
NOISE_N_N = 0.6
N_NOM_N = 100.0

# baseline truth (boundary lubricant, Table 2)
BASE_TRUTH = {"mu0": 0.11, "A_mu": 0.0011, "B_mu": 0.0040, "L_um": 19.2}


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


def _servo(t, xr, tau):
    """Critically damped 2nd-order follower of ``xr`` (exact for piecewise-linear input)."""
    if tau <= 0:
        return xr.copy()
    from rig.model.sensors import lowpass_uneven

    return lowpass_uneven(t, lowpass_uneven(t, xr, tau), tau)


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
    noise_scale: float = 1.0
    normal_variation: dict = field(default_factory=dict)  # {"amp_frac": .03, "period_s": 40}
    seed: int = 0


def make_record(spec: SynthSpec) -> tuple[TrialData, dict]:
    """A synthetic trial and its truth ``{"baseline", "extensions", "params"}``."""
    rng = np.random.default_rng(spec.seed)
    if isinstance(spec.protocol, str):
        if spec.protocol == "paper":
            hold = max(20.0, spec.duration_s / 13.0)
            segs = protocol_paper(1, hold)
            # repeat to fill the duration
            total = sum(d for d, _ in segs)
            reps = max(1, int(round(spec.duration_s / total)))
            segs = protocol_paper(reps, hold)
        elif spec.protocol == "varied":
            segs = protocol_varied(rng, spec.duration_s)
        else:
            raise ValueError(f"unknown protocol {spec.protocol!r} (paper, varied)")
    else:
        segs = list(spec.protocol)
    pre = 20.0  # pre-roll at the first velocity, cut off: the record starts in steady sliding
    segs = [(pre, segs[0][1])] + segs
    T = sum(d for d, _ in segs)
    dt = 1e-3
    tf = np.arange(0.0, T, dt)
    edges = np.cumsum([0.0] + [d for d, _ in segs])
    vel = np.array([v for _, v in segs])
    seg_i = np.clip(np.searchsorted(edges, tf, side="right") - 1, 0, len(segs) - 1)
    v_ref = vel[seg_i]
    x_ref = np.concatenate([[0.0], np.cumsum(0.5 * (v_ref[1:] + v_ref[:-1]) * dt)])
    x_true = _servo(tf, x_ref, spec.servo_tau_s)
    v_true = np.gradient(x_true, tf)
    # normal forces (true)
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
    exts = list(spec.effects)
    params = dict(spec.params)
    for e, pe in spec.effects.items():
        params.update(pe)
    if spec.baseline == "steady_state" and "frictional_memory" not in exts:
        params.setdefault("c_mu", params.get("A_mu", 0.0011) - params.get("B_mu", 0.004))
        for k in ("A_mu", "B_mu", "L_um"):
            params.pop(k, None)
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
    T = T - pre
    n_s = int(T * spec.rate_hz)
    ts = (np.arange(n_s) + 0.5) / spec.rate_hz
    if spec.jitter > 0:
        ts = ts + rng.uniform(-0.5, 0.5, n_s) * spec.jitter / spec.rate_hz
        ts = np.sort(ts)
    keep = np.ones(n_s, bool)
    for _ in range(spec.gaps):
        g0 = rng.uniform(0.1 * T, 0.9 * T)
        keep &= ~((ts > g0) & (ts < g0 + rng.uniform(1.0, 3.0)))
    ts = ts[keep & (ts < tf[-1])]
    ts = ts[np.concatenate([[True], np.diff(ts) > 0])]

    def at(y):
        return np.interp(ts, tf, y)

    ns = spec.noise_scale
    Fm = at(F_true) + rng.normal(0, NOISE_F_N * ns, ts.size)
    xm = at(x_true) + rng.normal(0, NOISE_X_UM * ns, ts.size)
    xm = np.round(xm / LVDT_Q_UM) * LVDT_Q_UM
    n1 = at(N1) + rng.normal(0, NOISE_N_N * ns, ts.size)
    n2 = at(N2) + rng.normal(0, NOISE_N_N * ns, ts.size)
    truth = {"baseline": spec.baseline, "extensions": [e for e in exts], "params": params}
    meta = {"normal_force_N": f"{N_NOM_N:g}", "lubricant": "boundary", "synthetic": "rig.diagnosis.synth",
            "truth": json.dumps(truth, sort_keys=True), "seed": str(spec.seed)}
    trial = TrialData(time_s=ts, position_um=xm, friction_N=Fm, normal_1_N=n1, normal_2_N=n2,
                      position_ref_um=at(x_ref) if spec.with_ref else None, metadata=meta,
                      source=f"synth(seed={spec.seed})")
    return trial, truth


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

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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
