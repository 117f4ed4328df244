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

**The rig's loop** (:func:`closed_loop_matrix`, :func:`k_cr_loop`): eq. (8)'s linearisation
extended to the PID as rig.control runs it (1 kHz, zero-order hold, integral of prior
errors, backward-difference D) on Fig. 1's plant or on the simulated rig's (spool,
actuator with oil compliance and leakage, moving mass, test-piece and fixture compliance,
LVDT filter); k_cr from the roots of the characteristic polynomial det(z I - M).

**The check by simulation** (:func:`scan_boundary`, :func:`sliding_run`): a kp scan of the
full simulated rig (:class:`rig.sim.SimRig`) started in steady sliding, with a stated
criterion: stick-slip if more than 1 % of 0.1 s blocks have mean slip velocity below
0.1 V0, or the block means' sd exceeds 0.3 V0 (second half of the run). No growth rates.

**The sensor noise** (:func:`noise_spread`, :func:`k_noise_criterion`): the LVDT's noise
through the same linear discrete loop gives the spread of the 0.1 s block means that the
criterion sees on a stable rig; with the PID it stays above 0.3 V0 well beyond k_cr (the
lightly damped I-friction mode), so a noisy scan's crossing is a noise threshold, and the
PID's stability boundary is judged noise-free. docs/paper.md has the figures.

**Velocity steps** (:func:`step_response_metrics`, :func:`step_velocity_traces`): overshoot,
noise floor and rise time as the paper's Fig. 8 shows a step (docs/paper.md row 8).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.model.friction import N_STATE, P_A, P_MU0, P_V0, P_VREG, S_THETA, S_THETA2, dmu_dv, init_state
from rig.model.paper import k_cr_eq8, k_cr_eq13_N_per_um
from rig.model.spec import FrictionModel

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
# Eq. (8) extended: the rig's discrete PID (1 kHz, zero-order hold) on the rig's plant
# ---------------------------------------------------------------------------
@dataclass
class LoopModel:
    """What the linear analysis of the closed loop needs (units: N, µm, s).

    ``plant``: ``"fig1"`` (the paper's Fig. 1: the controller force acts on the mass m
    directly, position measured exactly) or ``"rig"`` (the simulated rig of rig.sim.plant:
    first-order spool, actuator with oil compliance and leakage, moving mass, series
    compliance test piece + fixture, the interface, the LVDT's 100 Hz first-order filter).
    ``dt_s = 0``: continuous-time PID (the paper's analysis); > 0: the loop as rig.control
    runs it: I_n = ki dt sum_{k<n} e_k, D_n = kd (e_n - e_{n-1})/dt, output held (ZOH)."""
    A_N: float
    B_N: float
    L_um: float
    V0_um_s: float = 1.0
    mass_kg: float = DEFAULT_MASS_KG
    kd_N_s_per_um: float = DEFAULT_KD_N_S_PER_UM
    ki_N_per_um_s: float = 0.0
    dt_s: float = 1e-3
    plant: str = "fig1"
    tau_valve_s: float = 1e-3
    tau_leak_s: float = 2e-3
    k_h_N_per_um: float = 10.0
    c_a_N_s_per_um: float = 0.0
    k_tp_N_per_um: float = 1.0
    k_fx_N_per_um: float = 10.0
    tau_lvdt_s: float = 1.0 / (2 * math.pi * 100.0)

    @classmethod
    def from_profile(cls, prof, model: FrictionModel, *, ki_N_per_um_s: float | None = None,
                     kd_N_s_per_um: float | None = None, V0_um_s: float = 1.0, plant: str = "rig",
                     dt_s: float | None = None) -> "LoopModel":
        """The simulated rig's loop (a :class:`rig.profile.RigProfile`) at V0; the friction's
        A is the law's own slope at V0 (:func:`effective_A_mu`), in the fixture's force
        units (2 N)."""
        two_n = 2.0 * prof.normal.nominal_force_N
        c, act = prof.controller, prof.actuator
        return cls(A_N=two_n * effective_A_mu(model, V0_um_s), B_N=two_n * model.get("B_mu"),
                   L_um=model.get("L_um"), V0_um_s=V0_um_s, mass_kg=act.moving_mass_kg,
                   kd_N_s_per_um=c.kd_N_s_per_um if kd_N_s_per_um is None else kd_N_s_per_um,
                   ki_N_per_um_s=c.ki_N_per_um_s if ki_N_per_um_s is None else ki_N_per_um_s,
                   dt_s=prof.dt_s if dt_s is None else dt_s, plant=plant,
                   tau_valve_s=prof.servovalve.time_constant_s, tau_leak_s=act.leakage_time_constant_s,
                   k_h_N_per_um=act.hydraulic_stiffness_N_per_um, c_a_N_s_per_um=act.viscous_damping_N_s_per_um,
                   k_tp_N_per_um=prof.fixture.test_piece_stiffness_N_per_um,
                   k_fx_N_per_um=prof.fixture.fixture_stiffness_N_per_um,
                   tau_lvdt_s=1.0 / (2 * math.pi * prof.sensors.lvdt.cutoff_hz))


def plant_matrices(lm: LoopModel):
    """Continuous-time linearised plant about steady sliding at V0: (A, b, c) with
    dx/dt = A x + b u (u: controller force, N) and the measured position y = c x (µm).

    Friction (eqs. 5-6 linearised, force units): F = (A_N/V0) dv_s + theta_N,
    dtheta_N/dt = -(V0/L) theta_N - (B_N/L) dv_s."""
    m = lm.mass_kg * 1e-6  # N s^2/µm
    a_v = lm.A_N / lm.V0_um_s
    g = lm.V0_um_s / lm.L_um
    if lm.plant == "fig1":
        # x, v, theta
        if a_v <= 0:
            raise ValueError("fig1 plant needs A > 0 (no direct effect: no finite k_cr, eq. 8)")
        A = np.array([[0.0, 1.0, 0.0],
                      [0.0, -a_v / m, -1.0 / m],
                      [0.0, -lm.B_N / lm.L_um, -g]])
        b = np.array([0.0, 1.0 / m, 0.0])
        c = np.array([1.0, 0.0, 0.0])
        return A, b, c
    if lm.plant != "rig":
        raise ValueError(f"plant must be 'fig1' or 'rig', not {lm.plant!r}")
    if a_v <= 0:
        raise ValueError("rig plant needs A > 0 (a massless interface without direct effect)")
    # states: spool force S, actuator force Fa, x_a, v_a, chain force Fs, theta_N, LVDT filter xf
    km = 1.0 / (1.0 / lm.k_tp_N_per_um + 1.0 / lm.k_fx_N_per_um)
    # slip velocity of the massless interface: Fs = a_v v_s + theta -> v_s = (Fs - theta)/a_v
    A = np.zeros((7, 7))
    A[0, 0] = -1.0 / lm.tau_valve_s
    A[1, 0] = 1.0 / lm.tau_leak_s
    A[1, 1] = -1.0 / lm.tau_leak_s
    A[1, 3] = -lm.k_h_N_per_um
    A[2, 3] = 1.0
    A[3, 1] = 1.0 / m
    A[3, 3] = -lm.c_a_N_s_per_um / m
    A[3, 4] = -1.0 / m
    A[4, 3] = km
    A[4, 4] = -km / a_v
    A[4, 5] = km / a_v
    A[5, 4] = -lm.B_N / lm.L_um / a_v
    A[5, 5] = -g + lm.B_N / lm.L_um / a_v
    tf = lm.tau_lvdt_s
    A[6, 2] = 1.0 / tf
    A[6, 4] = -1.0 / (tf * lm.k_tp_N_per_um)
    A[6, 6] = -1.0 / tf
    b = np.zeros(7)
    b[0] = 1.0 / lm.tau_valve_s
    c = np.zeros(7)
    c[6] = 1.0
    return A, b, c


def discrete_plant(lm: LoopModel):
    """(Phi, Gamma, c): the plant of :func:`plant_matrices` discretised exactly under a
    zero-order hold of ``lm.dt_s``, Phi = e^{A dt}, Gamma = int_0^dt e^{A t} dt b."""
    from scipy.linalg import expm

    A, b, c = plant_matrices(lm)
    n = A.shape[0]
    E = np.zeros((n + 1, n + 1))
    E[:n, :n] = A * lm.dt_s
    E[:n, n] = b * lm.dt_s
    Ed = expm(E)
    return Ed[:n, :n], Ed[:n, n], c


def closed_loop_matrix(lm: LoopModel, kp_N_per_um: float) -> np.ndarray:
    """Closed-loop matrix of the linearised loop. Discrete (dt > 0): state [x_n, s_n, e_{n-1}]
    with the plant discretised exactly under a zero-order hold (Phi = e^{A dt},
    Gamma = int_0^dt e^{A t} dt b), e_n = -c x_n (deviations; the reference ramp cancels),

        u_n = kp e_n + ki s_n + kd (e_n - e_{n-1}) / dt,  s_{n+1} = s_n + dt e_n,

    the PID of rig.control (integral of prior errors, backward-difference D). The
    characteristic polynomial is det(z I - M). Continuous (dt = 0): PID u = kp e + ki
    int e + kd de/dt (eq. 8's setting with ki = 0, kd = kv)."""
    A, b, c = plant_matrices(lm)
    n = A.shape[0]
    kp, ki, kd = kp_N_per_um, lm.ki_N_per_um_s, lm.kd_N_s_per_um
    use_i = ki != 0.0
    if lm.dt_s <= 0:
        # e = -c x, de/dt = -c A x (u has no direct feedthrough to y in either plant)
        ca = c @ A
        if abs(c @ b) > 0.0:
            raise ValueError("continuous D term needs a plant without feedthrough from u to y")
        K = -(kp * c + kd * ca)
        M = np.zeros((n + use_i, n + use_i))
        M[:n, :n] = A + np.outer(b, K)
        if use_i:
            M[:n, n] = b * ki
            M[n, :n] = -c
        return M
    dt = lm.dt_s
    Phi, Gam, _ = discrete_plant(lm)
    m = n + 1 + use_i
    M = np.zeros((m, m))
    M[:n, :n] = Phi - np.outer(Gam, (kp + kd / dt) * c)
    M[:n, n] = -Gam * kd / dt          # e_{n-1}
    M[n, :n] = -c                      # e_{n-1} <- e_n
    if use_i:
        M[:n, n + 1] = Gam * ki
        M[n + 1, :n] = -dt * c
        M[n + 1, n + 1] = 1.0
    return M


def growth_rate_linear(lm: LoopModel, kp_N_per_um: float) -> float:
    """Largest growth rate (1/s) of the linearised closed loop: max Re(s), with s = ln(z)/dt
    for the discrete loop. Negative: steady sliding is asymptotically stable."""
    M = closed_loop_matrix(lm, kp_N_per_um)
    ev = np.linalg.eigvals(M)
    if lm.dt_s <= 0:
        return float(ev.real.max())
    return float(np.log(np.maximum(np.abs(ev), 1e-300)).max() / lm.dt_s)


def characteristic_polynomial(lm: LoopModel, kp_N_per_um: float) -> np.ndarray:
    """Coefficients (highest power first) of det(z I - M) (discrete) or det(s I - M)."""
    return np.real(np.poly(closed_loop_matrix(lm, kp_N_per_um)))


def k_cr_loop(lm: LoopModel, k_hi_N_per_um: float | None = None, rtol: float = 1e-4) -> float | None:
    """Critical stiffness (N/µm) of the linearised loop: the least kp above which steady
    sliding is asymptotically stable, found on the eigenvalues (deterministic, no
    simulation noise). ``None`` if the loop is not stable at ``k_hi`` (default: 8 x the
    quasi-static (B_N - A_N)/L); 0.0 if it is stable at every kp down to 2 % of that (the
    integral term can stabilise the slow friction mode: no finite k_cr)."""
    k_qs = max((lm.B_N - lm.A_N) / lm.L_um, 1e-6)
    hi = k_hi_N_per_um or 8.0 * k_qs
    if growth_rate_linear(lm, hi) >= 0:
        return None
    lo = 0.02 * k_qs
    if growth_rate_linear(lm, lo) < 0:
        return 0.0
    while hi / lo > 1 + rtol:
        mid = math.sqrt(lo * hi)
        if growth_rate_linear(lm, mid) < 0:
            hi = mid
        else:
            lo = mid
    return math.sqrt(lo * hi)


def noise_spread(lm: LoopModel, kp_N_per_um: float, lvdt_sigma_um: float, lvdt_quantization_um: float = 0.0,
                 block_s: float = 0.1) -> float:
    """The spread (sd of the ``block_s`` block means of the slip velocity, / V0) that the
    LVDT's noise drives in the linearised discrete loop at ``kp`` (stable side: finite; inf
    at or below k_cr): what the scan's spread criterion measures on a stable rig.

    The noise as rig.sim has it (rig.sim.plant.plant_sample): white noise held over each tick
    enters the 100 Hz first-order filter, so the reading carries an AR(1) noise
    eps_{n+1} = a eps_n + sigma sqrt(1 - a^2) w_n (a = exp(-dt/tau), stationary sd
    ``lvdt_sigma_um``), then the ADC's quantisation (white, step^2/12). Both enter the PID
    as a measurement error: e_n = -(c x_n + eps_n + q_n), through P, I and the D term's
    backward difference. The state covariance P solves the discrete Lyapunov equation
    P = M P M^T + Q of the loop augmented with eps; the block mean's variance is
    (1/n^2) sum_{i,j} C(i - j), C(k) = h M^k P h^T, h the slip velocity
    v_s = (F_s - theta)/(A/V0)."""
    if lm.dt_s <= 0:
        raise ValueError("noise_spread needs the discrete loop (dt_s > 0)")
    M = closed_loop_matrix(lm, kp_N_per_um)
    if np.abs(np.linalg.eigvals(M)).max() >= 1.0:
        return math.inf
    _, gam, _ = discrete_plant(lm)
    n = gam.size
    m = M.shape[0]
    dt = lm.dt_s
    # response of the loop's state to a unit measurement error at this tick
    gw = np.zeros(m)
    gw[:n] = -gam * (kp_N_per_um + lm.kd_N_s_per_um / dt)
    gw[n] = -1.0
    if m > n + 1:
        gw[n + 1] = -dt
    a = math.exp(-dt / lm.tau_lvdt_s) if lm.tau_lvdt_s > 0 else 0.0
    Ma = np.zeros((m + 1, m + 1))
    Ma[:m, :m] = M
    Ma[:m, m] = gw
    Ma[m, m] = a
    Q = np.zeros((m + 1, m + 1))
    Q[m, m] = lvdt_sigma_um ** 2 * (1.0 - a * a)
    g = np.r_[gw, 0.0]
    Q += (lvdt_quantization_um ** 2 / 12.0) * np.outer(g, g)
    # P = sum_k Ma^k Q Ma^kT by doubling (Smith): well conditioned for the slow modes
    # (|z| within 1e-6 of 1 near k_cr), where a direct Kronecker solve is not
    P, Ak = Q.copy(), Ma.copy()
    for _ in range(80):
        dP = Ak @ P @ Ak.T
        P = P + dP
        if np.abs(dP).max() <= 1e-15 * np.abs(P).max():
            break
        Ak = Ak @ Ak
    h = np.zeros(m + 1)
    if lm.plant == "rig":
        a_v = lm.A_N / lm.V0_um_s
        h[4], h[5] = 1.0 / a_v, -1.0 / a_v
    else:
        h[1] = 1.0
    nb = max(1, int(round(block_s / dt)))
    Ph = P @ h
    gk = h.copy()
    acc = 0.0
    for k in range(nb):
        ck = float(gk @ Ph)
        acc += (nb if k == 0 else 2.0 * (nb - k)) * ck
        gk = gk @ Ma
    return math.sqrt(max(acc, 0.0)) / nb / lm.V0_um_s


def k_noise_criterion(lm: LoopModel, lvdt_sigma_um: float, lvdt_quantization_um: float = 0.0,
                      spread_max: float | None = None, rtol: float = 1e-3) -> float | None:
    """The kp (N/µm) above the loop's k_cr at which the noise-driven spread
    (:func:`noise_spread`) falls to the scan's criterion ``spread_max`` (default SPREAD_MAX):
    where the noisy scan calls the rig steady although it is linearly stable above k_cr
    already. None without a finite k_cr, or if the spread stays above ``spread_max`` up to
    20 k_cr (the noise alone then drives the criterion's spread at every kp)."""
    k_cr = k_cr_loop(lm)
    if not k_cr:
        return None
    smax = SPREAD_MAX if spread_max is None else spread_max
    # not monotonic in kp: the spread falls above k_cr, then rises again as a stiff P passes
    # more of the noise on; the first crossing on a geometric grid, then bisection
    grid = k_cr * np.geomspace(1.0 + 1e-4, 20.0, 60)
    prev = grid[0]
    for k in grid[1:]:
        if noise_spread(lm, k, lvdt_sigma_um, lvdt_quantization_um) <= smax:
            lo, hi = prev, k
            break
        prev = k
    else:
        return None
    while hi / lo > 1 + rtol:
        mid = math.sqrt(lo * hi)
        if noise_spread(lm, mid, lvdt_sigma_um, lvdt_quantization_um) > smax:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def fixture_statement(A_mu: float, B_mu: float, L_um: float, N_N: float = 100.0) -> str:
    """The one statement on the moving test piece of the double-shear fixture: its k_cr, twice eq. (13)
    per rider interface (Table 2's convention) of these same values (not Table 2's printed k_cr, which is
    not eq. (13) of its printed means: boundary 15.1 against 14.8)."""
    k1 = (B_mu - A_mu) * N_N / L_um * 1e3
    return (f"moving test piece (double shear: friction 2 N mu, so A = 2 N A_mu = {2 * N_N * A_mu:.3g} N, "
            f"B = 2 N B_mu = {2 * N_N * B_mu:.3g} N): quasi-static k_cr = 2 N (B_mu - A_mu)/L = {2 * k1:.4g} kN/m, "
            f"twice eq. (13) per rider interface, (B_mu - A_mu) N / L with N = {N_N:g} N (Table 2's convention), "
            f"= {k1:.4g} kN/m")


def per_interface_statement(A_mu: float, B_mu: float, L_um: float, N_N: float = 100.0) -> str:
    """Eq. (13) of identified values, said as the paper uses it: ``(B_mu - A_mu) N / L`` with ``N`` the normal
    force on one interface (Table 2's convention, N = 100 N: section 4.2.1), and the moving test piece's
    quasi-static k_cr, twice that, because it carries the friction of both interfaces (2 N mu, section 3)."""
    k1 = (B_mu - A_mu) * N_N / L_um * 1e3
    return (f"eq. (13) on these means, (B_mu - A_mu) N / L with N = {N_N:g} N on one interface (Table 2's "
            f"convention) = {k1:.4g} kN/m; the moving test piece carries the friction of both interfaces "
            f"(2 N mu), so its quasi-static k_cr is twice that, {2 * k1:.4g} kN/m")


# ---------------------------------------------------------------------------
# The stability report of `rig stability`: eqs. (8) and (13), the rig's loop, the advice
# ---------------------------------------------------------------------------
@dataclass
class StabilityReport:
    """What ``rig stability`` found (``rig.stability/2``): the set-up, one analysis per parameter set
    (:func:`analyse` with the rig loop's k_cr and advice, :func:`analyse_set`) and the simulated
    checks (:func:`scan_boundary`). Numbers unrounded; :meth:`report` is the JSON."""
    V0_um_s: float
    mass_kg: float
    kd_N_s_per_um: float
    ki_N_per_um_s: float
    normal_force_N: float
    analyses: dict
    checks: list

    def report(self) -> dict:
        return {"schema": "rig.stability/2", "V0_um_s": self.V0_um_s, "mass_kg": self.mass_kg,
                "kd_N_s_per_um": self.kd_N_s_per_um, "ki_N_per_um_s": self.ki_N_per_um_s,
                "normal_force_N": self.normal_force_N, "analyses": self.analyses, "checks": self.checks}


def params_from_report(doc, N_default_N: float) -> tuple[dict, float]:
    """(A_mu, B_mu, L_um) and the normal force of a ``rig identify`` JSON report (its mean); a
    ValueError saying what is missing or unusable."""
    try:
        m = doc["mean"]
        p = {"A_mu": float(m["A_mu"]), "B_mu": float(m["B_mu"]), "L_um": float(m["L_um"])}
        N = float(doc.get("normal_force_N", N_default_N))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"not a rig identify report with mean A_mu, B_mu, L_um ({type(exc).__name__}: {exc})")
    bad = [k for k, v in p.items() if not math.isfinite(v)] + ([] if N > 0 else ["normal_force_N"])
    if bad or not p["L_um"] > 0:
        raise ValueError(f"mean {', '.join(bad) or 'L_um'} is not a usable number (L_um must be positive, "
                         "all finite)")
    return p, N


def _loop_k_cr(prof, model: FrictionModel, ki: float, v0: float) -> dict:
    """k_cr of the rig's loop (N/µm) with the I term off (PD) and on (PID); None where the analysis cannot."""
    loop = {}
    for label, k_i in (("PD", 0.0), ("PID", ki)):
        try:
            loop[label] = k_cr_loop(LoopModel.from_profile(prof, model, ki_N_per_um_s=k_i, V0_um_s=v0))
        except ValueError:
            loop[label] = None
    return loop


def loop_advice(prof, model: FrictionModel, margin: float, v0: float) -> dict:
    """The rig loop's k_cr (PD and PID, kN/m) and the gain advice ``kp >= margin x k_cr`` of the loop the
    profile runs (PID when it has an integral gain): the keys :func:`analyse_set` adds to :func:`analyse`'s."""
    from rig.analysis.report import fmt

    ki = prof.controller.ki_N_per_um_s
    loop = _loop_k_cr(prof, model, ki, v0)
    out = {"k_cr_loop_PD_kN_per_m": loop["PD"] * 1e3 if loop["PD"] is not None else None,
           "k_cr_loop_PID_kN_per_m": loop["PID"] * 1e3 if loop["PID"] is not None else None}
    k_use = loop["PID"] if ki > 0 else loop["PD"]
    if k_use == 0.0:
        kp_min = margin * loop["PD"] if loop["PD"] else None
        out["kp_min_N_per_um"] = kp_min
        out["advice"] = ("the rig's PID loop has no finite k_cr (the integral term holds the slow friction "
                         f"mode); without the I term (PD) kp >= {fmt(kp_min * 1e3 if kp_min else None)} kN/m "
                         f"= {margin:g} x k_cr")
    elif k_use is not None:
        out["kp_min_N_per_um"] = margin * k_use
        out["advice"] = (f"kp >= {margin * k_use * 1e3:.4g} kN/m = {margin:g} x k_cr of the rig's loop "
                         f"({'PID' if ki > 0 else 'PD'}, 1 kHz)")
    return out


def analyse_set(name: str, p: dict, inp: StabilityInputs, margin: float, prof=None, from_table2: bool = True) -> dict:
    """One parameter set's analysis: :func:`analyse` (eqs. 8, 13), with a profile the rig loop's k_cr
    and advice (:func:`loop_advice`; the profile's own law of a lubricant it knows), and the statement
    on the moving test piece (:func:`fixture_statement`)."""
    a = analyse(inp, margin)
    if prof is not None:
        model = (prof.friction_model(name) if from_table2 and name in getattr(prof, "lubricants", {})
                 else FrictionModel(params={"mu0": 0.12, **p}))
        a.update(loop_advice(prof, model, margin, inp.V0_um_s))
    a["statement"] = fixture_statement(p["A_mu"], p["B_mu"], p["L_um"], inp.normal_force_N)
    return a


def simulated_checks(analyses: dict, prof, profile_path, v0: float, map_fn, say, bar=None,
                     from_table2: bool = True) -> list[dict]:
    """The kp scans (:func:`scan_boundary`) of the profile's lubricants among the analysed sets, PD and
    (when the profile has an integral gain) PID, each next to the rig loop's k_cr; ``say(text)`` reports
    each. A set from an identify report is no lubricant of the profile: not simulated."""
    from rig.analysis.report import fmt

    ki = prof.controller.ki_N_per_um_s
    checks = []
    for nm in analyses:
        if not from_table2 or nm not in prof.lubricants:
            say(f"{nm}: not a lubricant of the profile; simulation skipped")
            continue
        for k_i in (0.0, ki) if ki > 0 else (0.0,):
            ctl = "PID" if k_i else "PD"
            k_lin = k_cr_loop(LoopModel.from_profile(prof, prof.friction_model(nm), ki_N_per_um_s=k_i, V0_um_s=v0))
            if not k_lin:
                say(f"{nm} ({ctl}): no finite k_cr in the analysis; scan skipped")
                continue
            if bar is not None:
                bar.update(description=f"{nm} ({ctl}): kp scan")
            r = scan_boundary(nm, profile=profile_path, ki_N_per_um_s=k_i, V0_um_s=v0,
                              factors=(0.8, 0.9, 0.95, 1.05, 1.1, 1.25), map_fn=map_fn)
            r["k_cr_eq8_N_per_um"] = analyses[nm]["k_cr_eq8_N_per_um"]
            checks.append(r)
            lo, hi = r["bracket_N_per_um"]
            inside = r["analysis_in_bracket"]
            say(f"{nm} ({ctl}): simulated boundary in [{fmt(lo * 1e3 if lo else None)}, "
                f"{fmt(hi * 1e3 if hi else None)}] kN/m (stick-slip at the low end, steady at the high end) vs the "
                f"rig loop's {fmt(k_lin * 1e3)} kN/m"
                + ("" if inside is None else " (inside the bracket)" if inside else " (OUTSIDE the bracket)"))
    return checks


# ---------------------------------------------------------------------------
# The simulated boundary: a scan of kp with a stated criterion
# ---------------------------------------------------------------------------
STUCK_BELOW_FRAC = 0.1      # a 0.1 s block with mean slip velocity < 0.1 V0 counts as stuck
STUCK_FRACTION_MAX = 0.01   # stick-slip: more than 1 % of the judged blocks stuck ...
SPREAD_MAX = 0.3            # ... or a spread (sd of the 0.1 s block means) above 0.3 V0
BLOCK_S = 0.1
ONSET_SPREAD = 0.005        # noise-free runs: a sustained oscillation (stable runs decay below 0.001 V0)
SCAN_FACTORS = (0.80, 0.85, 0.90, 0.93, 0.96, 0.98, 1.00, 1.02, 1.04, 1.07, 1.10, 1.15, 1.25)


def sliding_run(profile_path: str | None, lubricant: str, kp_N_per_um: float, ki_N_per_um_s: float,
                kd_N_s_per_um: float, duration_s: float, V0_um_s: float = 1.0, seed: int = 0,
                bump_L: float = 0.05, sensor_noise: bool = True, valve_stiction: bool = False) -> dict:
    """One simulated run of the full rig (rig.sim.SimRig) sliding at V0 with the given PID
    gains, started in steady sliding (chain loaded with the steady friction, spool and
    actuator at their steady values; PD: the controller's bias carries the steady force,
    PID: the integral does), perturbed by a smooth step of the reference by ``bump_L`` x L
    at 1 s (a slip-velocity perturbation of about 5 % of V0 in the slow friction mode); the
    loop's sensor noise excites the rest (``sensor_noise=False``: LVDT and load-cell noise
    and quantisation off, so the spread measures the rig's own oscillation only). Judged on the second half of the run:
    ``stuck_fraction`` (0.1 s blocks of true slip velocity below 0.1 V0) and ``spread``
    (sd of the block means / V0); ``stick_slip`` by the criterion of the module constants.
    ``valve_stiction=False`` (default): the spool's stiction band is off, as in the linear
    loop analysis this scan checks (with the profile's band of 5e-4 and its full-scale
    dither, boundary PID: spread 0.85 / 0.28 / 0.18 V0 at 0.8 / 1.25 / 2 k_cr, against the
    linear valve's criterion 0.3; a band of 1e-3 gives 0.42 at 1.25 k_cr; docs/paper.md row 6). A top-level function of plain values (one trial for a parallel engine)."""
    from rig.sim import plant as pl
    from rig.control import C_BIAS, C_FF1, K_SUM
    from rig.config.profile import default_profile_path, load_profile
    from rig.sim import SimRig

    prof = load_profile(profile_path or default_profile_path())
    ctrl = prof.controller.model_copy(update={"kp_N_per_um": float(kp_N_per_um),
                                              "ki_N_per_um_s": float(ki_N_per_um_s),
                                              "kd_N_s_per_um": float(kd_N_s_per_um), "bias_N": 0.0})
    rate = prof.loop.rate_hz
    n = int(round(duration_s * rate))
    # a stability run may slide further than the 5 mm stroke: the LVDT range is widened
    # (the physics does not depend on where the piece is; the riders' taper is held flat)
    span = prof.stroke.home_um + V0_um_s * duration_s + 1000.0
    lvdt = prof.sensors.lvdt.model_copy(update={"max_um": max(prof.sensors.lvdt.max_um, span)})
    if not sensor_noise:
        lvdt = lvdt.model_copy(update={"noise_sigma_um": 0.0, "quantization_um": 0.0})
    sensors = prof.sensors.model_copy(update={"lvdt": lvdt})
    if not sensor_noise:
        sensors = sensors.model_copy(update={
            "friction_load_cell": sensors.friction_load_cell.model_copy(update={"noise_sigma_N": 0.0}),
            "normal_load_cells": sensors.normal_load_cells.model_copy(update={"noise_sigma_N": 0.0})})
    normal = prof.normal.model_copy(update={"face_taper_um_per_mm": [0.0, 0.0]})
    valve = prof.servovalve if valve_stiction else prof.servovalve.model_copy(update={"stiction_band_cmd": 0.0})
    prof = prof.model_copy(update={"controller": ctrl, "sensors": sensors, "normal": normal, "servovalve": valve})
    model = prof.friction_model(lubricant)
    rig = SimRig(prof, model, seed=seed)
    x0 = prof.stroke.home_um
    t = np.arange(n) / rate
    model_L = prof.friction_model(lubricant).get("L_um")
    xref = x0 + V0_um_s * t + bump_L * model_L * 0.5 * (1.0 + np.tanh((t - 1.0) / 0.05))
    # steady sliding at V0
    rig.reset(x0, V0_um_s)
    q, st = rig.q, rig.st
    f_ss = float(np.sum(pl.normal_forces(q, x0))) * float(model.mu_ss(V0_um_s))
    act = prof.actuator
    fa = f_ss + act.viscous_damping_N_s_per_um * V0_um_s
    s_ss = fa + act.leakage_time_constant_s * act.hydraulic_stiffness_N_per_um * V0_um_s
    st[pl.Z_FS] = f_ss
    st[pl.Z_FA] = fa
    st[pl.Z_XSP] = s_ss / act.full_scale_force_N
    st[pl.Z_VA] = V0_um_s
    st[pl.Z_VS] = V0_um_s
    st[pl.Z_XA] = x0 + f_ss * q[pl.Q_CTP]
    st[pl.Z_FLF] = f_ss
    rig.ring[:] = V0_um_s
    # the PID's share of the steady force: FF1 supplies ff1 V0 of it (rig.control)
    s_pid = s_ss - rig.c[C_FF1] * V0_um_s
    if ki_N_per_um_s > 0:
        rig.cs[K_SUM] = s_pid / ki_N_per_um_s
    else:
        rig.c[C_BIAS] = s_pid
    out = rig.run(xref, reset=False)
    v = out["true_velocity_um_s"]
    every = max(1, int(round(BLOCK_S * rate)))
    nb = v.size // every
    vb = v[: nb * every].reshape(nb, every).mean(axis=1)
    judged = vb[nb // 2:]
    stuck = float(np.mean(judged < STUCK_BELOW_FRAC * V0_um_s))
    spread = float(np.std(judged) / V0_um_s)
    return {"kp_N_per_um": float(kp_N_per_um), "ki_N_per_um_s": float(ki_N_per_um_s),
            "kd_N_s_per_um": float(kd_N_s_per_um), "duration_s": float(duration_s),
            "stuck_fraction": stuck, "spread": spread, "v_max_um_s": float(judged.max()),
            "stick_slip": bool(stuck > STUCK_FRACTION_MAX or spread > SPREAD_MAX)}


def scan_duration_s(lm: LoopModel, k_cr: float, periods: float = 40.0, lo_s: float = 300.0,
                    hi_s: float = 12000.0) -> float:
    """Run length for the scan: ``periods`` periods of the critical mode at k_cr (at least
    ``lo_s``, at most ``hi_s``)."""
    M = closed_loop_matrix(lm, k_cr)
    ev = np.linalg.eigvals(M).astype(complex)
    s = np.log(ev) / lm.dt_s if lm.dt_s > 0 else ev
    j = int(np.argmax(s.real))
    w = abs(s[j].imag)
    T = 2 * math.pi / w if w > 1e-9 else hi_s / periods
    return float(min(max(periods * T, lo_s), hi_s))


def sliding_run_task(args: tuple) -> dict:
    """:func:`sliding_run` on a tuple of its positional arguments (one task of the batch engine)."""
    return sliding_run(*args)


def scan_boundary(lubricant: str, *, profile=None, ki_N_per_um_s: float | None = None, V0_um_s: float = 1.0,
                  factors=SCAN_FACTORS, k_ref_N_per_um: float | None = None, duration_s: float | None = None,
                  seed: int = 0, run=None, bump_L: float = 0.05, sensor_noise: bool = True,
                  map_fn=None) -> dict:
    """Scan kp = factor x k_ref (default k_ref: the discrete-time analysis of the rig's loop,
    :func:`k_cr_loop`) with :func:`sliding_run`; the simulated boundary lies between the
    highest kp that stick-slips and the next one above that slides steadily: reported as that
    bracket (``bracket_N_per_um``, ``rel_bracket`` against the analysis, ``analysis_in_bracket``),
    never as a point, which the scan does not resolve.

    ``run``: a callable with :func:`sliding_run`'s signature; default: in process.
    ``map_fn(fn, items)`` (e.g. :func:`rig.catalog.batch.mapper`) runs the scan's runs on a
    parallel engine, one task per kp, by value."""
    from rig.config.profile import default_profile_path, load_profile

    ppath = str(profile or default_profile_path())
    prof = load_profile(ppath)
    model = prof.friction_model(lubricant)
    ki = prof.controller.ki_N_per_um_s if ki_N_per_um_s is None else ki_N_per_um_s
    kd = prof.controller.kd_N_s_per_um
    lm = LoopModel.from_profile(prof, model, ki_N_per_um_s=ki, V0_um_s=V0_um_s)
    k_lin = k_cr_loop(lm)
    k_ref = k_ref_N_per_um or k_lin
    if not k_ref:
        raise ValueError(f"{lubricant}: the linear analysis finds no finite k_cr; give k_ref_N_per_um")
    dur = duration_s or scan_duration_s(lm, k_ref)
    args = [(ppath, lubricant, f * k_ref, ki, kd, dur, V0_um_s, seed, bump_L, sensor_noise) for f in factors]
    if map_fn is not None and run is None:
        runs = list(map_fn(sliding_run_task, args))
    else:
        run = run or sliding_run
        runs = [run(*a) for a in args]
    runs.sort(key=lambda r: r["kp_N_per_um"])
    unstable = [r["kp_N_per_um"] for r in runs if r["stick_slip"]]
    lo = hi = None  # the boundary is resolved to a bracket, never to a point inside it
    if unstable:
        lo = max(unstable)
        above = [r["kp_N_per_um"] for r in runs if r["kp_N_per_um"] > lo]
        if above:
            hi = min(above)
    # noise-free: the onset of any sustained oscillation (for a gradual, supercritical onset
    # the stick-slip amplitude is reached below k_cr, the linear boundary is where it starts)
    k_onset = None
    if not sensor_noise:
        osc = [r["kp_N_per_um"] for r in runs if r["spread"] > ONSET_SPREAD]
        if osc:
            above = [r["kp_N_per_um"] for r in runs if r["kp_N_per_um"] > max(osc)]
            k_onset = 0.5 * (max(osc) + min(above)) if above else None
    return {"lubricant": lubricant, "ki_N_per_um_s": ki, "kd_N_s_per_um": kd, "V0_um_s": V0_um_s,
            "k_onset_N_per_um": k_onset,
            "onset_rel_diff": (k_onset / k_lin - 1) if (k_onset and k_lin) else None,
            "k_cr_loop_N_per_um": k_lin, "k_ref_N_per_um": k_ref, "duration_s": dur,
            "bracket_N_per_um": [lo, hi], "runs": runs,
            "rel_bracket": [lo / k_lin - 1, hi / k_lin - 1] if (lo and hi and k_lin) else None,
            "analysis_in_bracket": (lo <= k_lin <= hi) if (lo and hi and k_lin) else None,
            "steady_at_every_kp": not unstable, "bump_L": bump_L, "sensor_noise": sensor_noise,
            "criterion": f"stick-slip if > {STUCK_FRACTION_MAX:.0%} of {BLOCK_S:g} s blocks have mean slip velocity "
                         f"< {STUCK_BELOW_FRAC:g} V0, or their sd > {SPREAD_MAX:g} V0 (second half of the run)"}


# ---------------------------------------------------------------------------
# Report and map
# ---------------------------------------------------------------------------
def plot_map(scans: list[dict], path, title: str = "") -> None:
    """The stability map PNG (:func:`rig.analysis.plots.plot_stability_map`)."""
    from rig.analysis.plots import plot_stability_map

    plot_stability_map(scans, path, title, spread_max=SPREAD_MAX, onset_spread=ONSET_SPREAD)


# ---------------------------------------------------------------------------
# Velocity steps: overshoot and rise time as the paper's Fig. 8 shows them
# ---------------------------------------------------------------------------

def step_response_metrics(t_s, v_um_s, t_step_s: float, v1_um_s: float, v2_um_s: float,
                          after_s: float = 5.0, pre_s: tuple[float, float] = (6.0, 1.0)) -> dict:
    """Overshoot, noise floor and rise time of one velocity step v1 -> v2 in a velocity trace.

    ``v_um_s`` sampled at ``t_s`` (e.g. the paper's estimator on the 25 Hz LVDT log,
    rig.kinematics.velocity_paper, or a mean of such traces over trials); the step's ramp
    starts at ``t_step_s``. Relative to the step size v2 - v1:

    * ``overshoot`` = (max v over [t_step, t_step + after_s] - v2) / (v2 - v1);
    * ``floor`` = (max v over [t_step - pre_s[0], t_step - pre_s[1]] - v1) / (v2 - v1): the
      same statistic on steady sliding at v1, i.e. what the trace's noise alone gives;
    * ``rise_s``: 10 -> 90 % of the step (the paper: < 0.5 s); ``t90_s`` from the ramp's
      start (it includes the planner's ramp, (v2 - v1)/accel)."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(v_um_s, dtype=float)
    dv = v2_um_s - v1_um_s
    post = (t >= t_step_s) & (t <= t_step_s + after_s)
    pre = (t >= t_step_s - pre_s[0]) & (t <= t_step_s - pre_s[1])
    if not post.any() or not pre.any():
        raise ValueError(f"step at t = {t_step_s:g} s: the trace does not cover {pre_s[0]:g} s before "
                         f"and {after_s:g} s after it")
    y, ty = v[post], t[post]
    i10 = int(np.argmax(y > v1_um_s + 0.1 * dv))
    i90 = int(np.argmax(y > v1_um_s + 0.9 * dv))
    return {"v1_um_s": v1_um_s, "v2_um_s": v2_um_s, "overshoot": float((y.max() - v2_um_s) / dv),
            "floor": float((v[pre].max() - v1_um_s) / dv), "rise_s": float(ty[i90] - ty[i10]),
            "t90_s": float(ty[i90] - t_step_s)}


def step_velocity_traces(log, rate_hz: float = 25.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """(t_s, v_paper, v_true, steps) of a simulated trial's log (rig.session.MemoryLog):
    the paper's velocity (10-point moving average + central difference) of the LVDT at the
    ``rate_hz`` log rate, the true slip velocity through the same decimation and 10-point
    (0.4 s) average, and the log's ``velocity_step`` events."""
    from rig.kinematics import velocity_paper

    td = log.trial_data(rate_hz)
    v_paper = velocity_paper(td.time_s, td.position_um)
    vt = np.asarray(td.extra["true_velocity_um_s"], dtype=float)
    k = np.ones(10) / 10.0
    v_true = np.convolve(vt, k, mode="same") / np.convolve(np.ones_like(vt), k, mode="same")
    return td.time_s, v_paper, v_true, [e for e in log.events if e["kind"] == "velocity_step"]
