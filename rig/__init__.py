"""rig: control, acquisition, identification and diagnosis for a servohydraulic
friction rig after Dupont & Dunlap (1995), "Friction Modeling and PD
Compensation at Very Low Velocities" (J. Dyn. Sys. Meas. Control)."""

__version__ = "0.1.0"
