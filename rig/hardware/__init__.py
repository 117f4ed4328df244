"""The hardware backend: a 1 kHz real-time loop in its own process, its interlocks,
timing statistics and the trial runner (``rig run --hardware``)."""
