"""Analysis of friction trials: identification (Dupont & Dunlap 1995, eqs. 10-14),
the Stribeck curve (eq. 7), stability (eqs. 8 and 13) and the Table-2 reproduction.

Modules: :mod:`rig.analysis.identify`, :mod:`rig.analysis.stribeck`,
:mod:`rig.analysis.stability`, :mod:`rig.analysis.reproduce`, and
:mod:`rig.sim.synth` (the synthetic-record generator).
"""
