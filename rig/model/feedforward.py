"""The friction a model predicts along a planned reference: the controller's friction
feed-forward (rig.control, ``ff_N``), computed once before a run from the plan alone, so the
simulated rig (rig.sim) and the hardware loop (rig.hardware) feed the same force per tick.
The recipe's ``controller: {ff1, friction_ff}`` switches are applied by
:func:`rig.control.apply_switches` and :func:`friction_feedforward_for_plan`."""
from __future__ import annotations

import numpy as np

from rig.model.friction import mu_series
from rig.model.spec import FrictionModel, model_params


def friction_feedforward_N(x_ref_um, dt_s: float, model: FrictionModel, total_normal_N: float,
                           v_init_um_s: float) -> np.ndarray:
    """The friction force (N) that ``model``'s rate-and-state terms predict along the
    reference: the friction feed-forward of the controller (rig.control, G_n), one value
    per tick.

    F_ff,n = (N_1 + N_2) (mu(v_ref,n, theta_n) - sign(v_ref,n) mu0), v_ref the reference's
    backward difference (the planner's piecewise-linear/ramped reference: exact), theta
    integrated along the reference's slip from steady state at ``v_init_um_s``
    (rig.model.friction.mu_series: eqs. 5-6 and whatever extensions ``model`` has). The
    constant level mu0 (2N mu0, about 20 N; Table 2 does not give it) is left to the
    integral term, which carries it without feed-forward too: the chain loads at the start
    and after each reversal as before. On a velocity step 1 -> v2 the feed-forward is the
    paper's Fig. 9: the jump 2N A ln(v2/v1), the decay over L to 2N (A - B) ln(v2/v1), so
    the position loop has no friction transient left to follow (docs/paper.md row 8).
    While the reference is at rest the last sliding value is held (the stuck interface
    keeps the load the chain had); 0 before the reference first moves."""
    x = np.ascontiguousarray(x_ref_um, dtype=np.float64)
    v = np.empty_like(x)
    v[1:] = np.diff(x) / dt_s
    v[0] = v[1] if x.size > 1 else 0.0
    t = np.arange(x.size) * dt_s
    mu = mu_series(model.to_array(), t, v, x, float(v_init_um_s))
    # the rate-and-state part only: the constant level mu0 (which Table 2 does not give) stays
    # with the integral term, as without feed-forward
    f = float(total_normal_N) * (mu - np.sign(v) * model.get("mu0"))
    # at rest the last sliding value is held (0 before the first motion)
    moving = v != 0.0
    last = np.where(moving, np.arange(x.size), -1)
    np.maximum.accumulate(last, out=last)
    return np.where(last >= 0, f[np.maximum(last, 0)], 0.0)


def feedforward_model(model: FrictionModel) -> FrictionModel:
    """The law the friction feed-forward knows: the model's baseline with its parameters
    (the paper's eqs. 5-6 for rate_state; ``frictional_memory`` kept, it makes a steady_state
    baseline rate-and-state), without the other extensions (second state, aging, wear,
    position-periodic, and the sensor/fixture ones). A real rig feeds forward what it has
    identified, the single-state law; what `rig diagnose` finds beyond it stays in the
    record (a feed-forward of the simulated truth would cancel it)."""
    keep = [e for e in model.extensions if e == "frictional_memory"]
    names = model_params(model.baseline, keep)
    return FrictionModel(baseline=model.baseline, extensions=keep,
                         params={k: v for k, v in model.params.items() if k in names},
                         V0_um_s=model.V0_um_s, v_reg_um_s=model.v_reg_um_s)


def initial_velocity_um_s(x_ref_um, rate_hz: float, creep_um_s: float) -> float:
    """Speed for the initial friction state of a run: the reference's mean speed over its
    first 0.1 s, or ``creep_um_s`` if that is slower (a run starting with a hold)."""
    x = np.asarray(x_ref_um, dtype=float)
    k = min(x.size - 1, int(round(0.1 * rate_hz)))
    v0 = abs(x[k] - x[0]) * rate_hz / k if k > 0 else 0.0
    return v0 if v0 > creep_um_s else creep_um_s


def friction_feedforward_for_plan(switches: dict | None, x_ref_um, dt_s: float, model: FrictionModel,
                                  total_normal_N: float, v_init_um_s: float) -> np.ndarray:
    """Per-tick friction feed-forward (N) for a run, or an empty array when the recipe's
    ``friction_ff`` switch is off (the default): :func:`friction_feedforward_N` of
    :func:`feedforward_model` (``model``'s single-state law) at ``total_normal_N`` (2 N)."""
    if not (switches or {}).get("friction_ff", False):
        return np.empty(0)
    return friction_feedforward_N(x_ref_um, dt_s, feedforward_model(model), total_normal_N, v_init_um_s)
