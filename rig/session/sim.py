"""The simulated rig as a session backend, and the one way to simulate a plan.

:class:`SimBackend` runs the closed loop (:class:`rig.sim.SimRig`) block by
block as the session asks; a stop request ends it after the block in progress
(a simulation has no actuator to make safe). :func:`simulate` runs a recipe or
a compiled plan through the same :class:`rig.session.TrialSession` into memory
and returns the blocks and the logged events (the 25 Hz
:class:`rig.data.TrialData` with :meth:`MemoryLog.trial_data`).
"""

from __future__ import annotations

import math
import time

from rig.session.core import Block, Ending, TrialResult, run_trial
from rig.session.memory import MemoryLog
from rig.sim import SimRig


class SimBackend:
    """``SimRig(profile, friction_model, normal_force_N, seed)`` as a :class:`rig.session.Backend`.

    ``block_ticks``: ticks per block sent to the log (``rig run``: the recipe's
    ``log.block_s`` at the loop rate).

    ``pace``: trial seconds per wall-clock second (``rig run --pace``, so a
    person can watch a simulated trial with ``--live``): 1 = real time, 10 = ten
    times faster, 0 = as fast as the machine goes (default). A block is handed
    over when the wall clock reaches its end's trial time / pace (counted from
    :meth:`start`), as the hardware loop hands over a block once it has
    happened; a paced run hands over blocks of at most ``PACED_BLOCK_WALL_S``
    of wall time (0.1 s, ten updates a second for a live view). The simulated
    data do not depend on the pace or the block size. A machine too slow for
    the pace just runs behind it.

    The log's clock (:class:`rig.session.core.Block` ``wall_ns``): trial time 0 is
    the wall-clock time the run starts; a paced run re-anchors it on every block
    (the wall-clock time it is handed over), as the hardware's loop does. A paced
    run's log is flushed every 0.5 s (``log_flush_interval_s``), as the hardware's.
    """

    PACED_BLOCK_WALL_S = 0.1

    name = "sim"

    def __init__(self, profile, friction_model, normal_force_N: float | None = None, seed: int = 0,
                 block_ticks: int = 1000, pace: float = 0.0):
        pace = float(pace)
        if not (math.isfinite(pace) and pace >= 0.0):
            raise ValueError(f"pace must be a finite number >= 0 (0 = as fast as possible), not {pace!r}")
        self.pace = pace
        self.rig = SimRig(profile, friction_model, normal_force_N, seed)
        self.seed = seed
        self.block_ticks = max(1, int(block_ticks))
        self._blocks = None
        self._stop: str | None = None
        self._ended = False

    def describe(self) -> dict:
        d = {"normal_force_N": self.rig.normal_force_N, "seed": self.seed}
        if self.pace > 0:
            d["pace"] = self.pace
        return d

    def start(self, plan) -> None:
        rate = float(plan.loop_rate_hz)
        self._dt_s = 1.0 / rate
        ticks = self.block_ticks
        if self.pace > 0:
            ticks = min(ticks, max(1, int(round(self.PACED_BLOCK_WALL_S * self.pace * rate))))
        self._blocks = self.rig.run_blocks(plan.x_ref_um, block_ticks=ticks,
                                           controller=getattr(plan, "controller", None) or None)
        self._wall0 = time.monotonic()
        self._wall0_ns = time.time_ns()
        self._first = True

    @property
    def log_flush_interval_s(self) -> float:
        """How often the log is flushed and fsync'd (wall time): 0.5 s when paced (a person watches a
        trial in real time: kill -9 loses at most about that), else every second."""
        return 0.5 if self.pace > 0 else 1.0

    def _wait_for(self, t_end_s: float) -> None:
        """Sleep until the wall clock reaches trial time ``t_end_s`` at the pace (from :meth:`start`)."""
        due = self._wall0 + t_end_s / self.pace
        while self._stop is None:
            left = due - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def receive(self) -> Block | None:
        if self._stop is not None or self._ended:
            return None
        blk = next(self._blocks, None)
        if blk is None:
            self._ended = True
            return None
        t = blk["t_s"]
        wall_ns = None
        if self.pace > 0 and t.size:
            self._wait_for(float(t[-1]) + self._dt_s)
            wall_ns = time.time_ns() - int(self._dt_s * 1e9)  # handed over one tick after its last sample
        elif self._first and t.size:
            wall_ns = self._wall0_ns + int(round(float(t[-1]) * 1e9))  # unpaced: trial time 0 is the start
        self._first = False
        return Block(blk, wall_ns)

    def request_stop(self, reason: str, insist: bool = False) -> None:
        self._stop = reason

    def stats_window(self) -> dict:
        return {}

    def finish(self) -> Ending:
        if self._stop is not None:
            return Ending("stopped", self._stop)
        return Ending("completed")

    def close(self) -> None:
        self._blocks = None


def simulate(recipe_or_plan, profile, friction_model=None, *, recipe=None, seed: int | None = None,
             normal_force_N: float | None = None, keep_blocks: bool = True,
             block_ticks: int = 20000) -> tuple[MemoryLog, TrialResult]:
    """Run a recipe (or a compiled plan with its ``recipe``) on the simulated rig, in memory.

    ``friction_model``: a :class:`rig.model.spec.FrictionModel`, or None for the
    profile's model of the recipe's lubricant. ``seed`` / ``normal_force_N``
    default to the recipe's. Returns ``(log, result)``: ``log.blocks`` (with
    ``keep_blocks``), ``log.events`` (planned events reached, session events),
    ``log.trial_data(rate_hz)``; ``result`` the session's :class:`TrialResult`.
    """
    from rig.config.recipe import compile_recipe
    from trajectories import Plan

    if isinstance(recipe_or_plan, Plan):
        plan = recipe_or_plan
        if recipe is None:
            raise ValueError("simulate(plan, ...) needs recipe= (lubricant, normal force, seed)")
    else:
        recipe = recipe_or_plan
        fm0 = friction_model if friction_model is not None else profile.friction_model(recipe.lubricant)
        plan = compile_recipe(recipe, profile, friction_model=fm0)
    fm = friction_model if friction_model is not None else profile.friction_model(recipe.lubricant)
    nf = float(normal_force_N if normal_force_N is not None else recipe.normal_force_N)
    sd = int(recipe.seed if seed is None else seed)
    backend = SimBackend(profile, fm, nf, sd, block_ticks=block_ticks)
    log = MemoryLog(keep_blocks=keep_blocks, rate_hz=plan.loop_rate_hz,
                    metadata={"normal_force_N": f"{nf:g}", "lubricant": recipe.lubricant, "seed": str(sd),
                              "recipe": recipe.name, "generator": "rig.session.simulate"})
    result = run_trial(plan, backend, log, handle_signals=False,
                       trial_fields={"recipe": recipe.name, "lubricant": recipe.lubricant})
    return log, result
