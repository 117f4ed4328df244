"""The hardware: the 1 kHz real-time loop in its own process (:mod:`.loop`, read -> update ->
write over the devices of :mod:`.devices`), its interlocks (:mod:`.interlocks`, on device
health), pacing and timing statistics (:mod:`.timing`), and the emulated rig
(:mod:`.emulated`: the device emulators of :mod:`drivers.emulators` around the simulated
plant). The session's backend for it is :class:`rig.session.hardware.HardwareBackend`."""
