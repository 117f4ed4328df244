"""Stability of steady sliding (Dupont & Dunlap 1995, eqs. 8 and 13) and PD gain advice.

The sliding system of Fig. 1: a mass ``m`` driven through a spring ``kp`` and a
dashpot ``kv`` (the PD gains) by a velocity source ``V0``, with rate-and-state
friction. Linearised about steady sliding (Laplace variable s),

    m s^3 + (kv + A/V0 + m V0/L) s^2 + (kp + (kv V0 + A - B)/L) s + kp V0/L = 0

(A, B in force units), and Routh-Hurwitz gives eq. (8):

    k_cr = (B - (A + kv V0)) / L * [1 + m V0^2 / ((A + kv V0) L)].

**Force units and the double-shear fixture.** The moving test piece carries the
friction of both interfaces, ``F = 2 N mu``; in force units its coefficients are
``A = 2 N A_mu`` and ``B = 2 N B_mu``. Eq. (8) here uses those (the stiffness the
controller must provide). The paper's Table 2 and eq. (13) use ``N`` (one
interface): ``k_cr,13 = (B_mu - A_mu) N / L``, half the fixture's quasi-static
value. Both are reported.

**Paraffin (A = 0).** With ``A + kv V0 = 0`` eq. (8) has no finite critical
stiffness: the Routh-Hurwitz condition reduces to ``0 > m kp V0^2/L^2``: with
neither a direct effect nor damping, steady sliding is never asymptotically
stable. Any positive ``A + kv V0`` restores a finite k_cr, and because
``m V0^2 / L`` is tiny at µm/s (1e-6 N for 10 kg at 1 µm/s and L = 20 µm), even a
minute one makes the mass term negligible: k_cr -> (B - A - kv V0)/L. The
rig's derivative gain supplies ``kv V0``; the regularised law of
:mod:`rig.model.friction` (a smooth sign of width ``v_reg`` when A = 0) supplies an
effective ``A_eff = V0 dmu/dv = mu v_reg^2 / V0^2`` (about 1e-5 for paraffin).
The check by simulation uses the law's own slope ``V0 dmu/dv`` at V0
(:func:`effective_A_mu`), i.e. exactly the linearisation that eq. (8) assumes.

The check by simulation (:func:`find_boundary`): closed-loop runs of the
system of Fig. 1 (:func:`simulate_fig1`; mass, spring, dashpot, velocity source,
friction from :mod:`rig.model.friction`), started with a small velocity perturbation
at V0; the growth or decay of the velocity oscillation envelope classifies each
kp; bisection finds the boundary. :func:`full_rig_boundary` does the same with
the full simulated rig (:class:`rig.sim.SimRig`: PID, servovalve, actuator
with oil compliance and leakage, fixture compliance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from rig.model.spec import FrictionModel
from rig.model.friction import N_STATE, P_A, P_MU0, P_V0, P_VREG, advance_state, dmu_dv, init_state, mu_of, S_THETA, S_THETA2
from rig.model.paper import k_cr_eq8, k_cr_eq13_N_per_um

DEFAULT_MASS_KG = 10.0
DEFAULT_KD_N_S_PER_UM = 0.003


def effective_A_mu(model: FrictionModel, v_um_s: float) -> float:
    """``v dmu/dv`` of the (regularised) law at steady sliding at ``v``: the direct effect
    that the linearisation sees (equals A_mu while sliding when A_mu > 0)."""
    p = model.to_array()
    s = np.zeros(N_STATE)
    init_state(p, s, v_um_s)
    th = s[S_THETA] + s[S_THETA2]
    return float(v_um_s * dmu_dv(v_um_s, th, p[P_MU0], p[P_A], p[P_V0], p[P_VREG]))


@dataclass
class StabilityInputs:
    A_mu: float
    B_mu: float
    L_um: float
    normal_force_N: float = 100.0
    mass_kg: float = DEFAULT_MASS_KG
    kd_N_s_per_um: float = DEFAULT_KD_N_S_PER_UM
    V0_um_s: float = 1.0


def k_cr_eq8_N_per_um(A_mu, B_mu, L_um, N_N, m_kg, kd_N_s_per_um, V0_um_s) -> float:
    """Eq. (8) for the moving test piece of the double-shear fixture (A = 2 N A_mu,
    B = 2 N B_mu), in N/µm. ``inf`` when A + kv V0 <= 0 (no finite critical stiffness)."""
    A_N, B_N = 2 * N_N * A_mu, 2 * N_N * B_mu
    kv = kd_N_s_per_um * 1e6
    V0 = V0_um_s * 1e-6
    if A_N + kv * V0 <= 0:
        return math.inf
    return k_cr_eq8(A_N, B_N, L_um * 1e-6, m_kg, kv, V0) * 1e-6


def analyse(inp: StabilityInputs, margin: float = 2.0) -> dict:
    """Eq. (8) (fixture force units), eq. (13) both ways, the mass term, and PD advice."""
    N = inp.normal_force_N
    k8 = k_cr_eq8_N_per_um(inp.A_mu, inp.B_mu, inp.L_um, N, inp.mass_kg, inp.kd_N_s_per_um, inp.V0_um_s)
    k8_no_kd = k_cr_eq8_N_per_um(inp.A_mu, inp.B_mu, inp.L_um, N, inp.mass_kg, 0.0, inp.V0_um_s)
    k13 = k_cr_eq13_N_per_um(inp.A_mu, inp.B_mu, inp.L_um, N)
    a_eff_N = 2 * N * inp.A_mu + inp.kd_N_s_per_um * inp.V0_um_s
    mass_term = (inp.mass_kg * (inp.V0_um_s * 1e-6) ** 2 / (a_eff_N * inp.L_um * 1e-6)) if a_eff_N > 0 else math.inf
    # least kd that keeps a finite k_cr when A = 0 is any kd > 0; report kp advice
    kp_min = margin * max(k8, 0.0) if math.isfinite(k8) else math.inf
    return {
        "inputs": {"A_mu": inp.A_mu, "B_mu": inp.B_mu, "L_um": inp.L_um, "normal_force_N": N,
                   "mass_kg": inp.mass_kg, "kd_N_s_per_um": inp.kd_N_s_per_um, "V0_um_s": inp.V0_um_s},
        "k_cr_eq8_N_per_um": _fin(k8),
        "k_cr_eq8_kN_per_m": _fin(k8 * 1e3),
        "k_cr_eq8_kd0_kN_per_m": _fin(k8_no_kd * 1e3),
        "k_cr_eq13_kN_per_m": k13 * 1e3,
        "k_cr_eq13_fixture_kN_per_m": 2 * k13 * 1e3,
        "mass_term": _fin(mass_term),
        "A_plus_kvV0_N": a_eff_N,
        "margin": margin,
        "kp_min_N_per_um": _fin(kp_min),
        "advice": (f"kp >= {kp_min:.4g} N/µm ({kp_min * 1e3:.4g} kN/m) = {margin:g} x k_cr (eq. 8, fixture force "
                   f"units, kd = {inp.kd_N_s_per_um:g} N s/µm, m = {inp.mass_kg:g} kg, V0 = {inp.V0_um_s:g} µm/s)"
                   if math.isfinite(kp_min) else
                   "no finite critical stiffness: A + kv V0 = 0; add derivative gain (kd > 0) first"),
        "units_note": "eq. (8) uses the fixture's total friction 2 N mu (A = 2 N A_mu); eq. (13)/Table 2 use N "
                      "(one interface), half the fixture's quasi-static k_cr",
    }


def _fin(x):
    return float(x) if x is not None and math.isfinite(x) else None


# ---------------------------------------------------------------------------
# The system of Fig. 1, simulated
# ---------------------------------------------------------------------------
@njit(cache=True)
def _fig1_run(p, m_kg, kp, kv, two_n, v0, dt, n_steps, dv0, rec_every):
    """Mass m (kg), spring kp (N/µm), dashpot kv (N s/µm) to a velocity source V0 (µm/s);
    friction 2 N mu (rig.model.friction). Implicit (Newton) in the new velocity, trapezoidal
    position, exact state update in slip at the mid-step velocity. Returns v samples."""
    s = np.zeros(3)
    init_state(p, s, v0)
    mu_ss = mu_of(p, s, v0, 0.0)
    f_ss = two_n * mu_ss
    # spring pre-load carries the steady friction: x_in - x = f_ss / kp at t = 0
    x = 0.0
    xin = f_ss / kp
    v = v0 + dv0
    nrec = n_steps // rec_every + 1
    out = np.empty(nrec)
    out[0] = v
    k = 1
    minv = 1e-9
    s_new = np.zeros(3)
    for i in range(1, n_steps + 1):
        xin_n = xin + v0 * dt
        vn = v
        for it in range(30):
            vm = 0.5 * (v + vn)
            s_new[0] = s[0]
            s_new[1] = s[1]
            s_new[2] = s[2]
            advance_state(p, s_new, vm, dt)
            mu = mu_of(p, s_new, vn, 0.0)
            xn = x + 0.5 * dt * (v + vn)
            g = m_kg * 1e-6 * (vn - v) / dt - (kp * (xin_n - xn) + kv * (v0 - vn) - two_n * mu)
            th = s_new[0] + s_new[1]
            dg = m_kg * 1e-6 / dt + 0.5 * kp * dt + kv + two_n * dmu_dv(vn, th, p[0], p[1], p[4], p[12])
            step = g / dg
            vn_new = vn - step
            if vn_new < minv:
                vn_new = 0.5 * (vn + minv)
            if abs(vn_new - vn) < 1e-12 * (1.0 + abs(vn)):
                vn = vn_new
                break
            vn = vn_new
        vm = 0.5 * (v + vn)
        advance_state(p, s, vm, dt)
        x = x + 0.5 * dt * (v + vn)
        xin = xin_n
        v = vn
        if i % rec_every == 0 and k < nrec:
            out[k] = v
            k += 1
    return out[:k]


def linear_roots(A_N, B_N, L_um, m_kg, kp_N_per_um, kv_N_s_per_um, V0_um_s):
    """Roots of the linearised characteristic cubic (µm, N, s units)."""
    m = m_kg * 1e-6  # N s^2/µm
    a = kv_N_s_per_um + A_N / V0_um_s
    return np.roots([m, a + m * V0_um_s / L_um, kp_N_per_um + (kv_N_s_per_um * V0_um_s + A_N - B_N) / L_um,
                     kp_N_per_um * V0_um_s / L_um])


def growth_rate(v: np.ndarray, dt_rec: float, V0: float, dv0: float | None = None) -> float:
    """Growth rate (1/s) of the oscillation envelope of ``v - V0``: log ratio of the late
    amplitude (last fifth of the run) to the early one (after the first tenth, when the
    fast, strongly damped mode has gone), over the time between them. Positive: growing
    (unstable), including growth that saturates in a stick-slip limit cycle."""
    d = np.abs(v - V0)
    n = d.size
    e0, e1 = n // 10, n // 5
    l0 = n - n // 5
    a_early = float(d[e0:e1].max()) if e1 > e0 else float(d[0])
    a_late = float(d[l0:].max())
    span = ((l0 + n) / 2 - (e0 + e1) / 2) * dt_rec
    if a_late > 0.5 * V0:
        # stick-slip (or a large limit cycle): unstable whatever the early amplitude
        return math.log(a_late / max(a_early, 1e-300)) / span if a_late > a_early else 1.0 / span
    if dv0:
        # growth that has already saturated (stick-slip) before the early window
        if a_late > 2.0 * dv0:
            return math.log(a_late / dv0) / (n * dt_rec)
        # decayed to the round-off floor
        if a_late < 1e-7 * dv0:
            return -math.log(dv0 / max(a_late, 1e-300)) / (n * dt_rec)
    if a_early <= 0 or a_late <= 0:
        return -math.inf if a_late <= 0 else math.inf
    return math.log(a_late / a_early) / span


def simulate_fig1(model: FrictionModel, *, kp_N_per_um: float, kd_N_s_per_um: float, mass_kg: float,
                  normal_force_N: float, V0_um_s: float = 1.0, periods: float = 30.0,
                  dv_frac: float = 0.01, steps_per_period: int = 400) -> tuple[np.ndarray, float]:
    """Run Fig. 1's system; returns (velocity record, sample interval)."""
    p = model.to_array()
    two_n = 2.0 * normal_force_N
    A_N = two_n * effective_A_mu(model, V0_um_s)
    B_N = two_n * model.get("B_mu")
    roots = linear_roots(A_N, B_N, model.get("L_um", 20.0), mass_kg, kp_N_per_um, kd_N_s_per_um, V0_um_s)
    # time scale of the critical (least damped) mode; the fast mass mode is heavily damped
    # and handled by the implicit step
    crit = max(roots, key=lambda r: r.real)
    w = abs(crit.imag) if abs(crit.imag) > 1e-9 else abs(crit)
    w = min(max(w, 1e-6), 1e3)
    T = 2 * math.pi / w
    dt = T / steps_per_period
    n = int(periods * steps_per_period)
    rec = 4
    v = _fig1_run(p, mass_kg, kp_N_per_um, kd_N_s_per_um, two_n, V0_um_s, dt, n, dv_frac * V0_um_s, rec)
    return v, dt * rec, dv_frac * V0_um_s


def find_boundary(model: FrictionModel, *, kd_N_s_per_um: float, mass_kg: float, normal_force_N: float,
                  V0_um_s: float = 1.0, k_guess: float | None = None, iters: int = 12, periods: float = 30.0,
                  simulate=None) -> dict:
    """Bisection on kp (N/µm) between decaying and growing oscillation."""
    sim = simulate or (lambda kp: simulate_fig1(model, kp_N_per_um=kp, kd_N_s_per_um=kd_N_s_per_um, mass_kg=mass_kg,
                                                normal_force_N=normal_force_N, V0_um_s=V0_um_s, periods=periods))
    if k_guess is None or not math.isfinite(k_guess) or k_guess <= 0:
        k_guess = k_cr_eq13_N_per_um(model.get("A_mu"), model.get("B_mu"), model.get("L_um"), 2 * normal_force_N)
    lo, hi = 0.5 * k_guess, 2.0 * k_guess
    runs = []

    def rate(kp):
        out = sim(kp)
        v, dtr = out[0], out[1]
        g = growth_rate(v, dtr, V0_um_s, out[2] if len(out) > 2 else None)
        g = float(min(max(g, -1e6), 1e6)) if g == g else 0.0  # finite for the JSON report
        runs.append({"kp_N_per_um": kp, "growth_rate_per_s": g})
        return g

    g_lo, g_hi = rate(lo), rate(hi)
    for _ in range(6):
        if g_lo > 0:
            break
        lo *= 0.5
        g_lo = rate(lo)
    for _ in range(6):
        if g_hi < 0:
            break
        hi *= 2.0
        g_hi = rate(hi)
    if not (g_lo > 0 and g_hi < 0):
        return {"k_boundary_N_per_um": None, "runs": runs, "bracketed": False}
    for _ in range(iters):
        mid = math.sqrt(lo * hi)
        if rate(mid) > 0:
            lo = mid
        else:
            hi = mid
    return {"k_boundary_N_per_um": math.sqrt(lo * hi), "bracket_N_per_um": [lo, hi], "runs": runs,
            "bracketed": True}


def check_lubricant(name: str, *, mass_kg: float = DEFAULT_MASS_KG, kd_N_s_per_um: float = DEFAULT_KD_N_S_PER_UM,
                    normal_force_N: float = 100.0, V0_um_s: float = 1.0, mu0: float = 0.12, iters: int = 12,
                    periods: float = 30.0, model: FrictionModel | None = None) -> dict:
    """Eq. (8) (with the law's own direct effect at V0) against the simulated boundary."""
    model = model or FrictionModel.for_lubricant(name, mu0)
    a_eff = effective_A_mu(model, V0_um_s)
    k8 = k_cr_eq8_N_per_um(a_eff, model.get("B_mu"), model.get("L_um"), normal_force_N, mass_kg,
                           kd_N_s_per_um, V0_um_s)
    res = find_boundary(model, kd_N_s_per_um=kd_N_s_per_um, mass_kg=mass_kg, normal_force_N=normal_force_N,
                        V0_um_s=V0_um_s, k_guess=k8, iters=iters, periods=periods)
    kb = res["k_boundary_N_per_um"]
    return {"lubricant": name, "A_mu": model.get("A_mu"), "A_eff_mu": a_eff, "B_mu": model.get("B_mu"),
            "L_um": model.get("L_um"), "k_cr_eq8_N_per_um": k8, "k_sim_N_per_um": kb,
            "rel_diff": (kb - k8) / k8 if kb else None, "runs": res["runs"], "model": "fig1"}


# ---------------------------------------------------------------------------
# The full simulated rig
# ---------------------------------------------------------------------------
def full_rig_boundary(name: str, *, profile=None, ki_N_per_um_s: float | None = 0.0, V0_um_s: float = 1.0,
                      iters: int = 8, periods: float = 12.0, seed: int = 0, progress=None,
                      bump_um: float = 0.5, kd_N_s_per_um: float | None = None) -> dict:
    """Bisection on the PID's kp with the full simulated rig (rig.sim.SimRig), kd and the
    actuator as in the profile, ``ki`` as given (0: PD, the paper's analysis)."""
    from rig.config.profile import default_profile_path, load_profile
    from rig.sim import SimRig

    prof = load_profile(profile or default_profile_path())
    if kd_N_s_per_um is not None:
        prof = prof.model_copy(update={"controller": prof.controller.model_copy(
            update={"kd_N_s_per_um": float(kd_N_s_per_um)})})
    model = prof.friction_model(name)
    N = prof.normal.nominal_force_N
    kd = prof.controller.kd_N_s_per_um
    m = prof.actuator.moving_mass_kg
    # the actuator's leakage gives a force-velocity slope that acts as extra damping
    try:
        kv_leak = float(prof.actuator.hydraulic_stiffness_N_per_um * prof.actuator.leakage_time_constant_s)
    except Exception:  # noqa: BLE001
        kv_leak = 0.0
    a_eff = effective_A_mu(model, V0_um_s)
    k8 = k_cr_eq8_N_per_um(a_eff, model.get("B_mu"), model.get("L_um"), N, m, kd, V0_um_s)
    k8_leak = k_cr_eq8_N_per_um(a_eff, model.get("B_mu"), model.get("L_um"), N, m, kd + kv_leak, V0_um_s)
    A_N, B_N = 2 * N * a_eff, 2 * N * model.get("B_mu")
    roots = linear_roots(A_N, B_N, model.get("L_um"), m, k8, kd, V0_um_s)
    crit = max(roots, key=lambda r: r.real)
    w = max(abs(crit.imag), 1e-6)
    T = 2 * math.pi / w
    dur = periods * T
    rate = prof.loop.rate_hz
    f_ss = 2 * N * float(model.mu_ss(V0_um_s))

    def sim(kp):
        # the PID's constant bias carries the steady friction (Fig. 1's spring is pre-loaded)
        upd = {"kp_N_per_um": kp, "bias_N": f_ss}
        if ki_N_per_um_s is not None:
            upd["ki_N_per_um_s"] = ki_N_per_um_s
        ctrl = prof.controller.model_copy(update=upd)
        p2 = prof.model_copy(update={"controller": ctrl})
        rig = SimRig(p2, model, seed=seed)
        n = int(dur * rate)
        x0 = prof.stroke.home_um
        xref = x0 + V0_um_s * np.arange(n) / rate
        # a small perturbation: a 0.2 µm bump of the reference early on (the start from rest
        # under the bias force is another, brief one)
        xref = xref + bump_um * np.exp(-((np.arange(n) / rate - 0.1 * T) / (0.02 * T)) ** 2)
        out = rig.run(xref)
        v = out["true_velocity_um_s"]
        # block means over T/40: the oscillation stays resolved, the loop's noise-driven
        # jitter of the interface velocity (large when A is small) averages out
        every = max(1, int(T / 40 * rate))
        vv = v.reshape(-1)[: (v.size // every) * every].reshape(-1, every).mean(axis=1)
        if progress:
            progress()
        return vv, every / rate

    res = find_boundary(model, kd_N_s_per_um=kd, mass_kg=m, normal_force_N=N, V0_um_s=V0_um_s, k_guess=k8,
                        iters=iters, simulate=sim)
    kb = res["k_boundary_N_per_um"]
    return {"lubricant": name, "k_cr_eq8_N_per_um": k8, "k_cr_eq8_with_leak_N_per_um": k8_leak,
            "kv_leak_N_s_per_um": kv_leak, "ki_N_per_um_s": ki_N_per_um_s, "k_sim_N_per_um": kb,
            "rel_diff": (kb - k8) / k8 if kb else None, "runs": res["runs"], "model": "SimRig"}


# ---------------------------------------------------------------------------
# Report and map
# ---------------------------------------------------------------------------
def plot_map(checks: list[dict], analyses: dict, path) -> None:
    """Stability map: growth rate of the velocity oscillation against kp for each checked
    lubricant (simulated runs; growing = unstable), with eq. (8)'s k_cr and the simulated
    boundary; and k_cr of eq. (8) against the derivative gain (the A = 0 divergence)."""
    from rig.analysis.plots import _plt, save

    plt = _plt()
    n = max(1, len(checks))
    fig, axs = plt.subplots(1, n + 1, figsize=(4.2 * (n + 1), 4))
    axs = np.atleast_1d(axs)
    for ax, c in zip(axs, checks):
        for src, mk in (("fig1", "o"), ("SimRig", "s")):
            runs = [r for r in c.get("runs", [])] if c.get("model") == src else []
            if not runs:
                continue
            kp = np.array([r["kp_N_per_um"] for r in runs]) * 1e3
            g = np.array([r["growth_rate_per_s"] for r in runs])
            g = np.clip(g, -1e3, 1e3)
            ax.scatter(kp[g > 0], g[g > 0], marker=mk, color="C3", label=f"growing ({src})")
            ax.scatter(kp[g <= 0], g[g <= 0], marker=mk, color="C2", label=f"decaying ({src})")
        ax.axvline(c["k_cr_eq8_N_per_um"] * 1e3, color="k", ls="--", label="eq. (8)")
        if c.get("k_sim_N_per_um"):
            ax.axvline(c["k_sim_N_per_um"] * 1e3, color="C1", ls=":", label="simulated boundary")
        ax.axhline(0, color="0.6", lw=0.6)
        ax.set_xscale("log")
        ax.set_yscale("symlog", linthresh=1e-4)
        ax.set_xlabel("kp (kN/m)")
        ax.set_ylabel("envelope growth rate (1/s)")
        rd = c.get("rel_diff")
        ax.set_title(f"{c['lubricant']} ({c.get('model')}): sim/eq.8 - 1 = "
                     f"{rd * 100:.2f} %" if rd is not None else c["lubricant"], fontsize=9)
        ax.legend(fontsize=7)
    ax = axs[-1]
    kd = np.logspace(-6, -1, 200)
    for name, a in analyses.items():
        inp = a["inputs"]
        k = [k_cr_eq8_N_per_um(inp["A_mu"], inp["B_mu"], inp["L_um"], inp["normal_force_N"], inp["mass_kg"], d,
                               inp["V0_um_s"]) * 1e3 for d in kd]
        ax.loglog(kd, k, label=name)
    ax.set_xlabel("derivative gain kd (N s/µm)")
    ax.set_ylabel("k_cr, eq. (8) (kN/m)")
    ax.set_title("eq. (8) vs derivative gain (A = 0: k_cr -> inf as kd -> 0)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)
