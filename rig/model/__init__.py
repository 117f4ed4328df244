"""One model of the rig's physics: friction laws, loading system, sensor chain, forward model.

friction.py (rate-and-state pieces), loading.py (stiffness between the position sensor and
the interface), sensors.py (lag, delay, drift, normal-force variation, analog filters,
noise, quantization), forward.py (kinematic record -> reported force), spec.py (the model
description and the catalogue), paper.py (Table 2, eqs. 8 and 13).
"""

from rig.model.paper import TABLE2, k_cr_eq8, k_cr_eq13_N_per_um
from rig.model.spec import CATALOGUE, PARAMS, FrictionModel, model_params

__all__ = ["CATALOGUE", "PARAMS", "TABLE2", "FrictionModel", "k_cr_eq8", "k_cr_eq13_N_per_um", "model_params"]
