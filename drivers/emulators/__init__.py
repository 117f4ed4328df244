"""Per-device protocol emulators over real transports.

* :mod:`.modbus_conditioner`: the load-cell conditioner, a pymodbus server on
  TCP (127.0.0.1) or RTU over a pty pair bridged in Python (:mod:`.pty`);
* :mod:`.lvdt_streamer`: the LVDT conditioner streaming frames on a pty;
* :mod:`.valve_controller`: the servovalve controller, a CANopen LocalNode (CiA 301/408)
  on the machine-local bus (:mod:`drivers.canopen_bus`), with a set-point watchdog
  and a host-heartbeat consumer that null the output and latch until a reset;
Each knows its device only and gets its values through a small interface
(``send(position_um)``, ``update(forces)`` or a shared-memory sample,
``output(now)``); the emulated rig that composes them with the simulated plant
is :mod:`rig.hardware.emulated` (drivers/ imports nothing from rig/).

Fault injection (``rig.hardware.emulated.EmulatedRig.inject(device, fault, value)``): dropped or
corrupted LVDT frames, garbage bytes, silent or vanished devices, slow Modbus
answers, Modbus exception responses, a frozen sample counter, the valve fault
bit, a silent valve controller (missing heartbeat).
"""
