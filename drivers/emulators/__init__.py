"""Device emulators over real transports, driven by the simulated plant.

* :mod:`.modbus_conditioner`: the load-cell conditioner, a pymodbus server on
  TCP (127.0.0.1) or RTU over a pty pair bridged in Python (:mod:`.pty`);
* :mod:`.lvdt_streamer`: the LVDT conditioner streaming frames on a pty;
* :mod:`.valve_controller`: the servovalve controller, a CANopen LocalNode (CiA 301/408)
  on the machine-local bus (:mod:`drivers.canopen_bus`), with a set-point watchdog
  and a host-heartbeat consumer that null the output and latch until a reset;
* :mod:`.rig`: :class:`EmulatedRig`, all three around one plant
  (``rig.sim.SimRig.plant_step``), stepped once per received setpoint (lock
  step with the controller) or free-running at 1 kHz with the valve nulled,
  in its own process (:func:`start_emulator_process`).

Fault injection (``EmulatedRig.inject(device, fault, value)``): dropped or
corrupted LVDT frames, garbage bytes, silent or vanished devices, slow Modbus
answers, Modbus exception responses, a frozen sample counter, the valve fault
bit, a silent valve controller (missing heartbeat).
"""
