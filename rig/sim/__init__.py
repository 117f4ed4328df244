"""The simulated rig (closed loop: servovalve, actuator, fixture + rig.model) and synthetic records.

plant.py: the numba plant and closed-loop kernels; rig.py: :class:`SimRig`.
"""

from rig.model.feedforward import initial_velocity_um_s
from rig.sim.rig import BLOCK_KEYS, SimRig, build_plant_params

__all__ = ["BLOCK_KEYS", "SimRig", "build_plant_params", "initial_velocity_um_s"]
