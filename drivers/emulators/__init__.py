"""Device emulators over real transports, driven by the simulated plant.

* :mod:`.modbus_conditioner`: the load-cell conditioner, a pymodbus server on
  TCP (127.0.0.1) or RTU over a pty pair bridged in Python (:mod:`.pty`);
* :mod:`.lvdt_streamer`: the LVDT conditioner streaming frames on a pty;
* :mod:`.valve_controller`: the servovalve controller on a python-can bus
  (``udp_multicast`` across processes, ``virtual`` inside one), with a watchdog
  that nulls the output when setpoints stop;
* :mod:`.rig`: :class:`EmulatedRig`, all three around one plant
  (``rig.sim.SimRig.plant_step``), stepped once per received setpoint (lock
  step with the controller) or free-running at 1 kHz with the valve nulled,
  in its own process (:func:`start_emulator_process`).

Fault injection (``EmulatedRig.inject(device, fault, value)``): dropped or
corrupted LVDT frames, garbage bytes, silent or vanished devices, slow Modbus
answers, Modbus exception responses, a frozen sample counter, the valve fault
bit, a silent valve controller (missing heartbeat).
"""
