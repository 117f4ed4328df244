"""One trial session over a Backend protocol (docs/architecture.md).

* :mod:`rig.session.core`: :class:`TrialSession` (plan scheduling, events and
  blocks to the log, statistics every second, the stop state machine), the
  :class:`Backend` protocol and what a backend sends (:class:`Block`,
  :class:`Event`, :class:`Ending`);
* :mod:`rig.session.sim`: :class:`SimBackend` (the simulated rig) and
  :func:`simulate` (a recipe or plan on the simulated rig, in memory);
* :mod:`rig.session.hardware`: :class:`HardwareBackend` (the 1 kHz loop process of
  :mod:`rig.hardware`, the emulated rig when the profile asks for it);
* :mod:`rig.session.memory`: :class:`MemoryLog`, a writer in memory;
* :mod:`rig.session.logfile`: :func:`run_to_log`, one trial to one MCAP.
"""

from rig.session.core import (
    Backend, BackendError, Block, BlockFigures, Cause, Ending, Event, Phase, StopMachine, TrialResult,
    TrialSession, run_trial,
)
from rig.session.memory import MemoryLog

__all__ = ["Backend", "BackendError", "Block", "BlockFigures", "Cause", "Ending", "Event", "MemoryLog", "Phase",
           "StopMachine", "TrialResult", "TrialSession", "run_trial"]
