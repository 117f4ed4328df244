"""Reference trajectories: compile a recipe with a rig profile into the loop-rate reference.

``compile_recipe(recipe, profile) -> Plan`` (``Plan.x_ref_um``, ``Plan.events``,
``Plan.segments``); ``PlanError`` when the plan breaks a limit of the rig.
"""

from trajectories.planner import Plan, PlanError, RigLimits, compile_recipe, rig_limits

__all__ = ["Plan", "PlanError", "RigLimits", "compile_recipe", "rig_limits"]
