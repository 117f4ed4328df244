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

from rig.session.core import Block, Ending, Event, Outcome, TrialResult, run_trial
from rig.session.memory import MemoryLog
from rig.session.pausing import pausable_reference
from rig.sim import SimRig

MAX_PAUSE_S = 600.0  # as the hardware's interlocks.max_pause_s default: a longer pause trips


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

    ``pause()`` / ``resume()``: the operator's pause (:mod:`rig.session.pausing`). The
    simulation runs block by block (nothing simulated ahead), so a pause takes effect at
    the plan's next safe point after the block in progress; from then on the reference
    comes from :class:`trajectories.pause.PausableReference` (hold, run-up, the plan
    shifted), simulated piece by piece from the rig's state. A hold lasts its wall time
    (``realtime``; a scripted one runs as fast as the rest), at most ``MAX_PAUSE_S``.
    The recipe's friction feed-forward is the plan's, held through the hold and the run-up.
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
        self._ref = None          # the pausable reference, from the first pause on
        self._done_ticks = 0
        self._out: list = []      # events to hand out before the next block
        self._realtime_hold = True
        self._trip: str | None = None

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
        self._plan, self._ticks = plan, ticks
        # chunk = one block: nothing simulated ahead of what was handed out (a pause can still take it)
        self._blocks = self.rig.run_blocks(plan.x_ref_um, block_ticks=ticks, chunk_ticks=ticks,
                                           controller=getattr(plan, "controller", None) or None)
        self._ff_plan = self.rig.ff_N  # the plan's friction feed-forward (empty: none), for the pieces of a pause
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

    # -- pause ------------------------------------------------------------------------------------------
    def pause(self, realtime: bool = True) -> None:
        if self._ref is None:
            self._ref = pausable_reference(self._plan, self.rig.friction_model)
            self._ref.k_plan = self._ref.k_trial = self._done_ticks  # where the plan is now
            self._blocks = None
        self._realtime_hold = realtime
        self._ref.request_pause()

    def resume(self) -> None:
        if self._ref is not None:
            self._ref.request_resume()

    def _next_paused_block(self) -> dict | None:
        ref = self._ref
        k0 = ref.k_trial
        x, kp = ref.take(self._ticks)
        for k, kind, data in ref.events:
            self._out.append(Event(k * self._dt_s, kind, data))
        ref.events.clear()
        if x.size == 0:
            return None
        ff = self._ff_plan[kp] if self._ff_plan.size else self._ff_plan  # the plan's, held through the pause
        blk = next(self.rig.run_blocks(x, block_ticks=x.size, chunk_ticks=x.size, reset=False,
                                       controller=getattr(self._plan, "controller", None) or None, ff_N=ff))
        if ref.hold_s > MAX_PAUSE_S and self._trip is None:
            self._trip = f"paused for {ref.hold_s:.1f} s (limit {MAX_PAUSE_S:g} s)"
            self._out.append(Event(k0 * self._dt_s, "interlock", {"name": "pause_timeout", "message": self._trip}))
        if ref.state == "hold" and self._realtime_hold:  # the hold lasts as long as the operator holds it
            time.sleep(x.size * self._dt_s)
        return blk

    def receive(self) -> Block | Event | None:
        if self._out:
            return self._out.pop(0)
        if self._stop is not None or self._ended or self._trip is not None:
            return None
        blk = next(self._blocks, None) if self._ref is None else self._next_paused_block()
        if self._out:  # the pause's events go before the block that holds them
            self._out.append(Block(blk, frozen=True) if blk is not None else None)
            return self._out.pop(0)
        if blk is None:
            self._ended = True
            return None
        self._done_ticks += int(blk["t_s"].size)
        t = blk["t_s"]
        wall_ns = None
        if self.pace > 0 and t.size:
            self._wait_for(float(t[-1]) + self._dt_s)
            wall_ns = time.time_ns() - int(self._dt_s * 1e9)  # handed over one tick after its last sample
        elif self._first and t.size:
            wall_ns = self._wall0_ns + int(round(float(t[-1]) * 1e9))  # unpaced: trial time 0 is the start
        self._first = False
        return Block(blk, wall_ns, frozen=True)  # rig.sim.rig.Rig._blocks: fresh arrays for every chunk

    def request_stop(self, reason: str, insist: bool = False) -> None:
        self._stop = reason

    def stats_window(self) -> dict:
        return {}

    def finish(self) -> Ending:
        if self._trip is not None:
            return Ending(Outcome.TRIPPED, f"INTERLOCK pause_timeout: {self._trip}")
        if self._stop is not None:
            return Ending(Outcome.STOPPED, self._stop)
        return Ending(Outcome.COMPLETED)

    def close(self) -> None:
        self._blocks = None


def simulate(recipe_or_plan, profile, friction_model=None, *, recipe=None, seed: int | None = None,
             normal_force_N: float | None = None, keep_blocks: bool = True,
             block_ticks: int = 20000, pause_script=None) -> tuple[MemoryLog, TrialResult]:
    """Run a recipe (or a compiled plan with its ``recipe``) on the simulated rig, in memory.

    ``friction_model``: a :class:`rig.model.spec.FrictionModel`, or None for the
    profile's model of the recipe's lubricant. ``seed`` / ``normal_force_N``
    default to the recipe's. Returns ``(log, result)``: ``log.blocks`` (with
    ``keep_blocks``), ``log.events`` (planned events reached, session events),
    ``log.trial_data(rate_hz)``; ``result`` the session's :class:`TrialResult`.
    ``pause_script``: ``[(t_s, hold_s), ...]``, operator pauses to simulate (:class:`PauseControl`).
    """
    from rig.session.pausing import PauseControl

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
    pause = PauseControl(pause_script, listen=False, signals=False) if pause_script else None
    result = run_trial(plan, backend, log, handle_signals=False, pause=pause,
                       trial_fields={"recipe": recipe.name, "lubricant": recipe.lubricant})
    return log, result
