"""Plain descriptions of what a trial's reference does: the planner's input.

These are frozen dataclasses, already validated by whoever builds them
(:mod:`rig.config.recipe` converts a validated recipe into a :class:`PlanSpec`);
``trajectories`` imports nothing from ``rig``. Units are in every name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Union

# A velocity step must start from steady sliding (Dupont & Dunlap 1995, section 4.2): the
# state variable relaxes over the slip length L (eq. 6), as exp(-slip / L). The run-up at v1
# before a step is therefore at least MIN_RUN_UP_L x L of constant-velocity slip (exp(-5) =
# 0.7 % of the initial distance from steady state); unset, it is DEFAULT_RUN_UP_L x L.
MIN_RUN_UP_L = 5.0
DEFAULT_RUN_UP_L = 6.0

# Used when the rig gives no maximum speed: 1 mm/s, five times the paper's fastest
# velocity (200 µm/s, section 4) -- an assumption, not a property of the sim plant.
DEFAULT_MAX_SPEED_UM_S = 1000.0


@dataclass(frozen=True)
class RigLimits:
    """What the planner needs from a rig profile."""

    loop_rate_hz: float = 1000.0
    stroke_min_um: float = 0.0
    stroke_max_um: float = 5000.0
    max_speed_um_s: float = DEFAULT_MAX_SPEED_UM_S
    max_accel_um_s2: float = math.inf
    initial_position_um: float = 0.0
    source: str = "defaults"
    max_speed_note: str = ""


@dataclass(frozen=True)
class RunIn:
    """Pull then push through ``distance_um`` at ``speed_um_s`` (section 4: 4 mm at 20 µm/s)."""

    kind: ClassVar[str] = "run_in"
    distance_um: float = 4000.0
    speed_um_s: float = 20.0
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class Hold:
    kind: ClassVar[str] = "hold"
    duration_s: float = 1.0
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class Move:
    kind: ClassVar[str] = "move"
    position_um: float = 0.0
    speed_um_s: float = 100.0
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class SteppedPass:
    """Section 4.1: levels of ``level_um`` at ``velocities_um_s`` up, then the same back down;
    friction averaged over the last ``window_um`` of each level."""

    kind: ClassVar[str] = "stepped_pass"
    velocities_um_s: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0, 50.0, 100.0, 200.0)
    level_um: float = 250.0
    window_um: float = 50.0
    label: str | None = None
    accel_um_s2: float | None = None

    def levels_um_s(self) -> list[float]:
        v = list(self.velocities_um_s)
        return v + v[::-1]


@dataclass(frozen=True)
class VelocityStep:
    """One step v1 -> v2. ``slip_before_um``: slip from rest to the step, ramp to v1 included
    (None: the ramp plus DEFAULT_RUN_UP_L x L)."""

    v1_um_s: float
    v2_um_s: float
    slip_before_um: float | None = None
    slip_after_um: float = 300.0


@dataclass(frozen=True)
class VelocitySteps:
    """Section 4.2: steps from steady sliding, each from rest, then back to the start at
    ``return_speed_um_s`` (None: stay). ``require_steady_state=False`` lets a step start
    before MIN_RUN_UP_L x L of slip (short tests, transient-start experiments)."""

    kind: ClassVar[str] = "velocity_steps"
    steps: tuple[VelocityStep, ...] = ()
    return_speed_um_s: float | None = 100.0
    hold_s: float = 1.0
    require_steady_state: bool = True
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class SlideHoldSlide:
    """Slide-hold-slide (the friction lab's healing protocol, Dieterich 1972; Marone 1998):
    slide ``run_up_um`` at ``velocity_um_s`` (None: the ramp + DEFAULT_RUN_UP_L x L; at least
    MIN_RUN_UP_L x L at v), then for each of ``hold_times_s``: stop, rest that long (the
    reference at rest, ramps excluded), re-slide ``reslide_um`` at the same velocity (None:
    the ramp + DEFAULT_RUN_UP_L x L; the same 5 L rule, since it is the next hold's run-up)."""

    kind: ClassVar[str] = "slide_hold_slide"
    velocity_um_s: float = 10.0
    hold_times_s: tuple[float, ...] = (1.0, 3.0, 10.0, 30.0, 100.0)
    reslide_um: float | None = None
    run_up_um: float | None = None
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class _Wave:
    """What a loop-tuning wave has in common: its amplitude about the position where it starts
    and the slide beneath it (``velocity_um_s`` > 0: the interface slides throughout, and its
    friction is linear about steady sliding, as the loop model of ``rig stability`` assumes)."""

    amplitude_um: float = 1.0
    velocity_um_s: float = 0.0
    label: str | None = None
    accel_um_s2: float | None = None


@dataclass(frozen=True)
class Square(_Wave):
    """A square wave of ``amplitude_um``, ``cycles`` cycles at ``frequency_hz`` (first half cycle
    +amplitude), back to the start position at the end: the step test of loop tuning. Each edge
    is a straight ramp at ``edge_speed_um_s`` (None: the rig's maximum speed, less the slide),
    so the reference never asks more speed than the actuator has."""

    kind: ClassVar[str] = "square"
    frequency_hz: float = 1.0
    cycles: int = 5
    edge_speed_um_s: float | None = None


@dataclass(frozen=True)
class SineSweep(_Wave):
    """A logarithmic chirp from ``f0_hz`` to ``f1_hz`` in ``duration_s``: x = x_c + a w(t) sin(phi(t)),
    phi(t) = 2 pi f0 T / ln(f1/f0) (exp(t ln(f1/f0) / T) - 1), the instantaneous frequency
    f0 (f1/f0)^(t/T); w a raised-cosine taper over ``taper_s`` at both ends (None: one period
    of f0, at most a tenth of the sweep), so position and velocity are continuous. On a slide
    faster than the sweep's peak speed 2 pi f1 a the velocity never reverses."""

    kind: ClassVar[str] = "sine_sweep"
    f0_hz: float = 1.0
    f1_hz: float = 100.0
    duration_s: float = 30.0
    taper_s: float | None = None

    def taper(self) -> float:
        return self.taper_s if self.taper_s is not None else min(1.0 / self.f0_hz, 0.1 * self.duration_s)


Segment = Union[RunIn, Hold, Move, SteppedPass, VelocitySteps, SlideHoldSlide, Square, SineSweep]


@dataclass(frozen=True)
class PlanSpec:
    """Everything the planner compiles.

    ``state_length_um``: L of the friction model in use (eq. 6), for the run-up before
    velocity steps; ``state_length_source`` says where it came from (for messages). None:
    every velocity step must give ``slip_before_um`` and no steady-state check is made.
    ``log_rates_hz``: rates (name -> Hz) that must divide the loop rate.
    """

    segments: tuple[Segment, ...]
    accel_um_s2: float = 500.0
    start_position_um: float | None = None
    state_length_um: float | None = None
    state_length_source: str = ""
    log_rates_hz: tuple[tuple[str, float], ...] = ()


__all__ = ["RigLimits", "RunIn", "Hold", "Move", "SteppedPass", "VelocityStep", "VelocitySteps", "SlideHoldSlide",
           "Square", "SineSweep", "Segment",
           "PlanSpec", "MIN_RUN_UP_L", "DEFAULT_RUN_UP_L", "DEFAULT_MAX_SPEED_UM_S"]
