"""Diagnosis: what the simulation's friction model gets wrong, why, and how much a better model gains.

The contract is ../shared/specs/diagnosis.md. Entry points: :func:`diagnose`
(a :class:`rig.data.TrialData` -> :class:`Diagnosis`, whose ``.report()`` is the
JSON report and ``.model`` the extended :class:`rig.model.spec.FrictionModel`),
:mod:`rig.sim.synth` (records with known effects), :mod:`rig.diagnosis.plot`.
"""

from .core import Diagnosis, diagnose

__all__ = ["Diagnosis", "diagnose"]
