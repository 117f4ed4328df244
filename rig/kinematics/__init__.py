"""Kinematics of a quantized, noisy LVDT position record (µm, s): two topics.

* :mod:`rig.kinematics.velocity` - velocity estimators (the paper's, local polynomial,
  slip-windowed), velocity changes, the edge-preserving line.
* :mod:`rig.kinematics.steps` - velocity steps (from events or the data), the operator's
  pause intervals.

The names the code uses are importable from ``rig.kinematics`` itself.
"""

from rig.kinematics.steps import (
    VELOCITY_KEYS,
    Step,
    clip_steps_to_pauses,
    detect_steps,
    line_fit,
    pause_intervals,
)
from rig.kinematics.velocity import (
    edge_preserving_line,
    estimate_velocity,
    median_dt,
    velocity_changes,
    velocity_for_steps,
    velocity_local_poly,
    velocity_paper,
)

__all__ = [
    "VELOCITY_KEYS", "Step", "clip_steps_to_pauses", "detect_steps", "line_fit", "pause_intervals",
    "edge_preserving_line", "estimate_velocity", "median_dt", "velocity_changes",
    "velocity_for_steps", "velocity_local_poly", "velocity_paper",
]
