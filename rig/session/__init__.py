"""One trial session over a Backend protocol (docs/architecture.md).

* :mod:`rig.session.core`: :class:`TrialSession` (plan scheduling, events and
  blocks to the log, statistics every second, the stop state machine), the
  :class:`Backend` protocol and what a backend sends (:class:`Block`,
  :class:`Event`, :class:`Ending`, its :class:`Outcome`), the :class:`TrialWriter`
  protocol and the small capability protocols of a backend or a writer;
* :mod:`rig.session.sim`: :class:`SimBackend` (the simulated rig) and
  :func:`simulate` (a recipe or plan on the simulated rig, in memory);
* :mod:`rig.session.hardware`: :class:`HardwareBackend` (the 1 kHz loop process of
  :mod:`rig.hardware`, the emulated rig when the profile asks for it);
* :mod:`rig.session.memory`: :class:`MemoryLog`, a writer in memory;
* :mod:`rig.session.logfile`: :func:`run_to_log`, one trial to one MCAP.
"""

from rig.session.core import (
    Anchored, Backend, BackendError, Block, BlockFigures, Ending, Event, FailStoppable, FlushPaced, LoggerWatched,
    Outcome, Pausable, Phase, StopMachine, TrialResult, TrialSession, TrialWriter, run_trial,
)
from rig.session.memory import MemoryLog

__all__ = ["Anchored", "Backend", "BackendError", "Block", "BlockFigures", "Ending", "Event", "FailStoppable",
           "FlushPaced", "LoggerWatched", "MemoryLog", "Outcome", "Pausable", "Phase", "StopMachine", "TrialResult",
           "TrialSession", "TrialWriter", "run_trial"]
