"""Reference trajectories: compile plain segment descriptions into the loop-rate reference.

``compile_plan(PlanSpec, RigLimits) -> Plan`` (``Plan.x_ref_um``, ``Plan.events``,
``Plan.segments``); ``PlanError`` when the plan breaks a limit of the rig or would start
a velocity step out of steady state. Imports nothing from ``rig``: a recipe becomes a
:class:`PlanSpec` in :mod:`rig.config.recipe` (``compile_recipe``).
"""

from trajectories.planner import MAX_PLAN_DURATION_S, Plan, PlanError, compile_plan
from trajectories.segments import (DEFAULT_MAX_SPEED_UM_S, DEFAULT_RUN_UP_L, MIN_RUN_UP_L, Hold, Move, PlanSpec,
                                   RigLimits, RunIn, SineSweep, SlideHoldSlide, Square, SteppedPass, VelocityStep,
                                   VelocitySteps)

__all__ = ["Plan", "PlanError", "compile_plan", "PlanSpec", "RigLimits", "RunIn", "Hold", "Move", "SteppedPass",
           "VelocityStep", "VelocitySteps", "SlideHoldSlide", "Square", "SineSweep", "MIN_RUN_UP_L", "DEFAULT_RUN_UP_L", "DEFAULT_MAX_SPEED_UM_S",
           "MAX_PLAN_DURATION_S"]
