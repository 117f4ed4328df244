"""The paper's numbers: Table 2 and the stability formulas (Dupont & Dunlap 1995).

``TABLE2``: mean ± standard deviation of the mean over velocity jumps of 1-10 µm/s at
100 N normal force; ``A_mu``, ``B_mu`` dimensionless, ``L_um`` in µm, ``k_cr_kN_per_m``.
"""

from __future__ import annotations

TABLE2 = {
    "dry": {"A_mu": (2.8e-3, 0.5e-3), "B_mu": (9.4e-3, 1.1e-3), "L_um": (64.7, 14.3), "k_cr_kN_per_m": (10.2, 2.9)},
    "paraffin": {"A_mu": (0.0, 0.0), "B_mu": (11.1e-3, 2.5e-3), "L_um": (22.4, 4.3), "k_cr_kN_per_m": (49.4, 14.5)},
    "boundary": {"A_mu": (1.1e-3, 0.1e-3), "B_mu": (4.0e-3, 0.4e-3), "L_um": (19.2, 1.4), "k_cr_kN_per_m": (14.8, 2.3)},
}
LUBRICANT_NAMES = tuple(TABLE2)


def k_cr_eq13_N_per_um(A_mu: float, B_mu: float, L_um: float, N_N: float) -> float:
    """Critical stiffness, quasi-static, k_v = 0 (eq. 13): (B_mu - A_mu) N / L, in N/µm (= MN/m).

    ``N`` is the nominal per-rider normal force, as in the paper's Table 2.
    Multiply by 1000 for kN/m.
    """
    return (B_mu - A_mu) * N_N / L_um


def k_cr_eq8(A_N: float, B_N: float, L_m: float, m_kg: float, k_v_N_s_per_m: float, V0_m_s: float) -> float:
    """Critical stiffness of the sliding system of Fig. 1 (eq. 8), SI units throughout.

    ``A_N``, ``B_N``: rate-and-state coefficients in force units (N), i.e.
    ``A_mu`` times the normal force acting on the sliding block (``2 N`` for the
    double-shear fixture's total friction force); ``L_m`` in m; returns N/m.
    """
    a_eff = A_N + k_v_N_s_per_m * V0_m_s
    return (B_N - a_eff) / L_m * (1.0 + m_kg * V0_m_s ** 2 / (a_eff * L_m))
