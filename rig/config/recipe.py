"""Trial recipes: YAML files validated by pydantic.

A recipe says what one trial does, in the paper's terms (Dupont & Dunlap 1995,
sections 3-4): which lubricant, which normal force (100 N in the paper), and a
list of segments the reference trajectory goes through:

``run_in``
    pull then push the test piece through 4 mm at 20 µm/s (section 4, after
    lubrication).
``stepped_pass``
    one 3.5 mm tensile pass with the velocity stepped every 250 µm, from the
    lowest velocity up to the maximum midway and back down, finishing at the
    initial minimum; each level is averaged over its last 50 µm (section 4.1,
    Fig. 5). Seven velocities, each visited twice: 14 x 250 µm = 3.5 mm.
``velocity_steps``
    from steady sliding at ``v1`` to ``v2`` (section 4.2: 1->2, 1->5, 1->10
    µm/s), with enough slip after the step for the f_2 windows 50, 100 and
    250 µm after it plus 200 points at 25 Hz (eqs. 10-12). The run-up at v1 is
    6 L of the friction model in use unless given; the planner refuses one
    shorter than 5 L (:data:`trajectories.MIN_RUN_UP_L`).
``slide_hold_slide``
    the healing protocol: slide at ``velocity_um_s`` (run-up >= 5 L), then for each of
    ``hold_times_s`` stop, rest, and re-slide ``reslide_um`` (>= 5 L, the next hold's
    run-up); ``rig heal`` reduces it (docs/identification.md).
``square``, ``sine_sweep``
    loop-tuning tests about the current position: a square wave (``amplitude_um``,
    ``frequency_hz``, ``cycles``) and a logarithmic chirp (``f0_hz``, ``f1_hz``,
    ``amplitude_um``, ``duration_s``), logged at the loop rate; ``rig tune`` reduces them
    (docs/hardware.md).
``hold``
    stand still for a duration.
``move``
    go to a position at a speed.

:func:`load_recipe` reads the file with the one loader (:mod:`rig.config.loader`)
and turns any fault into ONE :class:`RecipeError` whose message names the file,
the field path (``segments[2].slip_after_um``) and the line of the YAML node, so
that nothing runs from a broken recipe. :func:`compile_recipe` turns a validated
recipe into the planner's plain :class:`trajectories.PlanSpec` and compiles it
for a rig profile.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Annotated, Literal, Union

import yaml
from pydantic import Field, PrivateAttr, field_validator, model_validator

import trajectories as tj
from rig.config.loader import ConfigError, StrictModel, expect_kind, parse_yaml, read_yaml, validate
from rig.config.profile import MAX_NORMAL_FORCE_N, RigProfile

LUBRICANTS = ("dry", "paraffin", "boundary")

# The paper's 7 velocities of the stepped pass, 1..200 µm/s: 7 log-spaced values
# (geomspace(1, 200, 7) = 1, 2.4, 5.8, 14, 34, 83, 200) rounded to the nearest
# 1-2-5 value in log.
DEFAULT_PASS_VELOCITIES_UM_S = (1.0, 2.0, 5.0, 10.0, 50.0, 100.0, 200.0)


class RecipeError(ConfigError):
    """A recipe cannot be used. ``str()`` names the file, the field and the line."""


# Bounds of what a recipe may ask for; the planner then checks the rig's own stroke,
# speed and acceleration. Generous: they catch typos of orders of magnitude (1e12 N).
MAX_SPEED_UM_S = 1e5          # 0.1 m/s
MAX_DISTANCE_UM = 1e6         # 1 m
MAX_DURATION_S = 8 * 3600.0   # the planner's limit of one plan
MAX_ACCEL_UM_S2 = 1e8
MAX_RATE_HZ = 1e5
SEED_MAX = 2**32 - 1          # numpy's legacy seeds; seed + trial - 1 must stay below
SAFE_NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$"  # a file stem: out/<name>/...mcap
#: a lubricant's name: free text of a lab (printable, one line, no leading blank), up to 100 characters
LUBRICANT_NAME = r"^[^\s\x00-\x1f][^\x00-\x1f]{0,99}$"
#: a metadata key (recipe ``metadata:``, ``rig run --md KEY=VALUE``): a CSV ``# KEY: value`` line must read back
METADATA_KEY = r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$"
#: keys the trial log writes itself: a recipe or --md cannot set them
RESERVED_METADATA = ("trial_uid", "recipe", "recipe_file", "lubricant", "normal_force_N", "seed", "trial", "trials",
                     "profile", "profile_name", "backend", "friction_model", "plan_duration_s", "git_commit",
                     "software_version", "started_utc", "start_time_ns", "log_time", "loop_rate_hz", "raw_rate_hz",
                     "decimated_rate_hz", "clock", "status", "rig-trial-csv")
MetadataValue = Annotated[str, Field(max_length=2000, pattern=r"^[^\r\n]*$")] | int | float | bool

Speed = Annotated[float, Field(gt=0, le=MAX_SPEED_UM_S)]
Distance = Annotated[float, Field(gt=0, le=MAX_DISTANCE_UM)]
Position = Annotated[float, Field(ge=-MAX_DISTANCE_UM, le=MAX_DISTANCE_UM)]
Duration = Annotated[float, Field(gt=0, le=MAX_DURATION_S)]
Rate = Annotated[float, Field(gt=0, le=MAX_RATE_HZ)]


class _SegmentBase(StrictModel):
    label: str | None = Field(None, description="Free name of the segment, shown in progress and events.")
    accel_um_s2: Annotated[float, Field(gt=0, le=MAX_ACCEL_UM_S2)] | None = Field(
        None, description="Acceleration bound of this segment's velocity transitions (µm/s²); "
                          "default: the recipe's accel_um_s2.")


class RunIn(_SegmentBase):
    """Pull then push through ``distance_um`` at ``speed_um_s`` (paper section 4: 4 mm at 20 µm/s)."""

    kind: Literal["run_in"]
    distance_um: Distance = 4000.0
    speed_um_s: Speed = 20.0


class SteppedPass(_SegmentBase):
    """Section 4.1: velocity stepped every ``level_um`` along a ``pass_um`` tensile pass.

    The levels go up through ``velocities_um_s`` (sorted ascending) and back
    down, each velocity twice, so ``pass_um == 2 * len(velocities) * level_um``
    (3.5 mm = 14 x 250 µm for 7 velocities). Friction is averaged over the last
    ``window_um`` of each level.
    """

    kind: Literal["stepped_pass"]
    velocities_um_s: list[Speed] = Field(default_factory=lambda: list(DEFAULT_PASS_VELOCITIES_UM_S),
                                         min_length=1, max_length=100)
    level_um: Distance = 250.0
    pass_um: Distance | None = Field(None, description="Length of the pass (µm); default and required value: "
                                                        "2 x len(velocities) x level_um (3.5 mm for 7).")
    window_um: Distance = 50.0

    @field_validator("velocities_um_s")
    @classmethod
    def _ascending(cls, v: list[float]) -> list[float]:
        if any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError("velocities must be strictly increasing (the pass goes up, then back down)")
        return v

    @model_validator(mode="after")
    def _geometry(self):
        n_levels = 2 * len(self.velocities_um_s)
        if self.pass_um is None:
            self.__dict__["pass_um"] = n_levels * self.level_um  # no re-validation (validate_assignment)
        elif abs(n_levels * self.level_um - self.pass_um) > 1e-6:
            raise ValueError(
                f"pass_um ({self.pass_um:g}) must equal 2 x {len(self.velocities_um_s)} velocities x "
                f"level_um ({self.level_um:g}) = {n_levels * self.level_um:g} µm")
        if self.window_um >= self.level_um:
            raise ValueError(f"window_um ({self.window_um:g}) must be shorter than level_um ({self.level_um:g})")
        return self

    def levels_um_s(self) -> list[float]:
        """Velocity of each level in pass order: up, then down (the max twice midway)."""
        v = list(self.velocities_um_s)
        return v + v[::-1]


class VelocityStep(StrictModel):
    """One step v1 -> v2 from steady sliding at v1."""

    v1_um_s: Speed
    v2_um_s: Speed
    slip_before_um: Distance | None = Field(None, description="Slip from rest to the step, the ramp to v1 "
                                                              "included; default: the segment's.")
    slip_after_um: Distance | None = Field(None, description="Slip at v2 after the step; default: the segment's.")

    @model_validator(mode="after")
    def _different(self):
        if self.v1_um_s == self.v2_um_s:
            raise ValueError("v1_um_s and v2_um_s are equal: that is no velocity step")
        return self


class VelocitySteps(_SegmentBase):
    """Section 4.2: steps in velocity from steady sliding, each in a fresh stretch of slip.

    For each step: accelerate to v1, slide ``slip_before_um`` (default: the ramp
    plus 6 L of the friction model in use, so the state variable is at steady
    state; the planner refuses less than 5 L at v1 unless
    ``require_steady_state: false``), step to v2, slide ``slip_after_um`` (past
    the f_2 windows at 50, 100 and 250 µm plus 200 points at the log rate), stop,
    hold ``hold_s``, and return to the segment's start position at
    ``return_speed_um_s`` (``null``: do not return).
    """

    kind: Literal["velocity_steps"]
    steps: list[VelocityStep] = Field(min_length=1, max_length=1000)
    slip_before_um: Distance | None = Field(None, description="Slip from rest to each step (µm), the ramp to v1 "
                                                              "included; default: the ramp + 6 L.")
    slip_after_um: Distance = 300.0
    return_speed_um_s: Speed | None = 100.0
    hold_s: Annotated[float, Field(ge=0, le=MAX_DURATION_S)] = 1.0
    require_steady_state: bool = Field(True, description="Refuse a step with less than 5 L of slip at v1 before "
                                                         "it (false: short tests, transient-start experiments).")


class SlideHoldSlide(_SegmentBase):
    """Slide-hold-slide (healing): slide ``run_up_um`` at ``velocity_um_s``, then for each hold
    time stop, rest, re-slide ``reslide_um``. Defaults: the ramp + 6 L of the friction model in
    use; the planner refuses less than 5 L at v for either (each re-slide is the next hold's
    run-up, so every hold starts from steady sliding)."""

    kind: Literal["slide_hold_slide"]
    velocity_um_s: Speed = 10.0
    hold_times_s: list[Duration] = Field(default_factory=lambda: [1.0, 3.0, 10.0, 30.0, 100.0], min_length=1,
                                         max_length=1000, description="Rest of each hold (s), ramps excluded.")
    reslide_um: Distance | None = Field(None, description="Slip after each hold (µm), the ramp included; "
                                                          "default: the ramp + 6 L.")
    run_up_um: Distance | None = Field(None, description="Slip before the first hold (µm), the ramp included; "
                                                         "default: the ramp + 6 L.")


class Square(_SegmentBase):
    """Square wave about the current position (loop tuning, ``rig tune step``)."""

    kind: Literal["square"]
    amplitude_um: Annotated[float, Field(gt=0, le=1000.0)]
    frequency_hz: Annotated[float, Field(gt=0, le=500.0)]
    cycles: Annotated[int, Field(ge=1, le=100_000)] = 5
    edge_speed_um_s: Speed | None = Field(None, description="Speed of each edge (µm/s); default: the rig's "
                                                            "maximum speed (less velocity_um_s).")
    velocity_um_s: Annotated[float, Field(ge=0, le=MAX_SPEED_UM_S)] = Field(
        0.0, description="Slide beneath the wave (µm/s); 0: about the current position.")


class SineSweep(_SegmentBase):
    """Logarithmic chirp about the current position (loop tuning, ``rig tune frf``)."""

    kind: Literal["sine_sweep"]
    f0_hz: Annotated[float, Field(gt=0, le=500.0)]
    f1_hz: Annotated[float, Field(gt=0, le=500.0)]
    amplitude_um: Annotated[float, Field(gt=0, le=1000.0)]
    duration_s: Duration
    taper_s: Annotated[float, Field(ge=0, le=MAX_DURATION_S)] | None = Field(
        None, description="Raised-cosine fade at both ends (s); default: one period of f0, at most 10 %.")
    velocity_um_s: Annotated[float, Field(ge=0, le=MAX_SPEED_UM_S)] = Field(
        0.0, description="Slide beneath the sweep (µm/s); above 2 pi f1 amplitude_um the velocity never "
                         "reverses and friction stays linear about steady sliding. 0: about the current position.")

    @model_validator(mode="after")
    def _rising(self):
        if self.f1_hz <= self.f0_hz:
            raise ValueError(f"f1_hz ({self.f1_hz:g}) must exceed f0_hz ({self.f0_hz:g}): the sweep rises")
        return self


class Hold(_SegmentBase):
    kind: Literal["hold"]
    duration_s: Duration


class Move(_SegmentBase):
    kind: Literal["move"]
    position_um: Position
    speed_um_s: Speed


Segment = Annotated[Union[RunIn, SteppedPass, VelocitySteps, SlideHoldSlide, Square, SineSweep, Hold, Move],
                    Field(discriminator="kind")]


class LogRates(StrictModel):
    """What the log keeps: raw loop data (blocks) and a decimated per-sample channel."""

    raw_rate_hz: Rate = Field(1000.0, description="Rate of the raw channel; must divide the loop rate "
                                                  "(the loop rate itself keeps every tick).")
    decimated_rate_hz: Rate = Field(25.0, description="Rate of the per-sample channel (the paper logged at 25 Hz).")
    block_s: Annotated[float, Field(gt=0, le=60.0)] = Field(
        1.0, description="Duration covered by one raw block message (s).")
    raw_encoding: Literal["binary", "base64", "json"] = Field(
        "binary", description="Arrays of a raw block: binary little-endian float columns (rig.columns.v1, "
                              "fastest), base64 of them in JSON, or JSON number lists (docs/trial.md).")
    raw_dtype: Literal["float64", "float32"] = Field(
        "float64", description="Precision of the raw arrays (t_s is always float64); float32 halves "
                               "the raw data.")
    raw_format: Literal["protobuf", "v2"] = Field(
        "protobuf", description="Layout of the 1 kHz /raw channel: protobuf rig.LoopBlock (any MCAP tool and "
                                "Foxglove plot it) or rig.columns.v2 (rig's own binary: about 0.6x the size "
                                "and less CPU; docs/trial.md).")


class ControllerSwitches(StrictModel):
    """The recipe's feed-forward switches (``controller:`` in the YAML; ``on``/``off`` or
    true/false). The gains stay the rig profile's (``controller.ff1_N_s_per_um``)."""

    ff1: bool = Field(True, description="Velocity feed-forward (LinuxCNC FF1) at the profile's "
                                        "controller.ff1_N_s_per_um; off: FF1 = 0 for this trial.")
    friction_ff: bool = Field(False, description="Friction feed-forward: the friction force the friction "
                                                  "model's rate-and-state terms predict along the reference "
                                                  "(eqs. 5-6), added to the PID output (docs/paper.md row 8); "
                                                  "on in every shipped recipe. Simulated rig only.")


class Recipe(StrictModel):
    """One trial's procedure (what ``rig run`` executes)."""

    name: str = Field(pattern=SAFE_NAME, description="Names the trial and its default log out/<name>.mcap: "
                                                      "letters, digits, '.', '_', '-' (no path).")
    description: str | None = None
    lubricant: str = Field(pattern=LUBRICANT_NAME, description="The lubricant: a free name the rig profile maps to "
                                                            "a friction model (lubricants, lubricant_map); the "
                                                            "paper's dry, paraffin, boundary by default.")
    normal_force_N: Annotated[float, Field(gt=0, le=MAX_NORMAL_FORCE_N)] = Field(
        100.0, description="Nominal per-rider normal force (N); 100 N in the paper.")
    segments: list[Segment] = Field(min_length=1, max_length=10_000)
    log: LogRates = Field(default_factory=LogRates)
    seed: int = Field(0, ge=0, le=SEED_MAX - 1000, description="Random seed of trial 1 (trial k: seed + k - 1).")
    trials: int = Field(1, ge=1, le=1000, description="Number of trials; one MCAP each, numbered.")
    accel_um_s2: Annotated[float, Field(gt=0, le=MAX_ACCEL_UM_S2)] = Field(
        500.0, description="Default acceleration bound of velocity transitions (µm/s²).")
    start_position_um: Position | None = Field(
        None, description="Where the reference starts (µm); default: the rig profile's initial position.")
    profile: str | None = Field(None, description="Rig profile YAML (relative to the current directory, "
                                                  "else to the recipe file).")
    controller: ControllerSwitches = Field(default_factory=ControllerSwitches,
                                           description="Feed-forward switches: ff1, friction_ff (on/off).")
    metadata: dict[Annotated[str, Field(pattern=METADATA_KEY)], MetadataValue] = Field(
        default_factory=dict, description="Who and what: specimen, operator, note and any KEY: value of the lab "
                                          "(into the trial log's 'trial' record, rig info, the CSV export, the "
                                          "catalogue); `rig run --specimen/--operator/--note/--md` override it.")

    # filled by load_recipe, not part of the YAML
    _source_path: str | None = PrivateAttr(None)
    _source_text: str | None = PrivateAttr(None)

    @field_validator("metadata")
    @classmethod
    def _not_reserved(cls, v: dict) -> dict:
        bad = sorted(set(v) & set(RESERVED_METADATA))
        if bad:
            raise ValueError(f"{', '.join(bad)}: set by rig itself, not by a recipe's metadata")
        return v

    @property
    def source_path(self) -> str | None:
        """The file the recipe was loaded from (None when built in code)."""
        return self._source_path

    @property
    def source_text(self) -> str | None:
        """The recipe file's text as loaded (attached to the trial log)."""
        return self._source_text

    def profile_path(self) -> Path | None:
        """The rig profile named by the recipe, resolved (cwd first, then the recipe's folder)."""
        if not self.profile:
            return None
        p = Path(self.profile)
        if p.is_absolute() or p.exists() or not self.source_path:
            return p
        alt = Path(self.source_path).parent / p
        return alt if alt.exists() else p

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json", exclude_none=True), sort_keys=False)

    def with_lubricant(self, lubricant: str) -> "Recipe":
        """A copy of this recipe on another lubricant (``rig run --lubricant``). The recipe's own
        lubricant named as a word in its ``description`` or a segment's ``label`` (``boundary
        steps``) becomes the lubricant actually used, so that the progress bar, the events and the
        log's recipe say what runs. ValueError: not a lubricant name."""
        out = self.model_copy(deep=True)
        old = self.lubricant
        out.lubricant = lubricant  # validated (validate_assignment)
        if lubricant == old:
            return out
        word = re.compile(rf"(?<![\w-]){re.escape(old)}(?![\w-])")
        if out.description:
            out.description = word.sub(lubricant, out.description)
        for seg in out.segments:
            if seg.label:
                seg.label = word.sub(lubricant, seg.label)
        return out


# ---------------------------------------------------------------------------
# Loading: the one loader, errors with file, field and line
# ---------------------------------------------------------------------------

_WHAT = "a recipe (a mapping with name, lubricant, segments)"


def parse_recipe(text: str, path: str | os.PathLike = "<recipe>") -> Recipe:
    """Validate recipe YAML ``text``; ``path`` is only used in messages."""
    recipe = validate(Recipe, parse_yaml(text, path, error=RecipeError, what=_WHAT), error=RecipeError)
    recipe._source_path = str(path)
    recipe._source_text = text
    return recipe


def load_recipe(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file. Raises :class:`RecipeError` (file, field, line) on any fault."""
    doc = read_yaml(path, error=RecipeError, what=_WHAT)
    expect_kind(doc, Recipe, "a recipe", RecipeError)
    recipe = validate(Recipe, doc, error=RecipeError)
    recipe._source_path = str(path)
    recipe._source_text = doc.text
    return recipe


# ---------------------------------------------------------------------------
# Recipe -> the planner's plain description
# ---------------------------------------------------------------------------

def _plain(seg) -> "tj.Segment":
    common = {"label": seg.label, "accel_um_s2": seg.accel_um_s2}
    if isinstance(seg, RunIn):
        return tj.RunIn(distance_um=seg.distance_um, speed_um_s=seg.speed_um_s, **common)
    if isinstance(seg, Hold):
        return tj.Hold(duration_s=seg.duration_s, **common)
    if isinstance(seg, Move):
        return tj.Move(position_um=seg.position_um, speed_um_s=seg.speed_um_s, **common)
    if isinstance(seg, SteppedPass):
        return tj.SteppedPass(velocities_um_s=tuple(seg.velocities_um_s), level_um=seg.level_um,
                              window_um=seg.window_um, **common)
    if isinstance(seg, VelocitySteps):
        steps = tuple(tj.VelocityStep(v1_um_s=st.v1_um_s, v2_um_s=st.v2_um_s,
                                      slip_before_um=st.slip_before_um or seg.slip_before_um,
                                      slip_after_um=st.slip_after_um or seg.slip_after_um) for st in seg.steps)
        return tj.VelocitySteps(steps=steps, return_speed_um_s=seg.return_speed_um_s, hold_s=seg.hold_s,
                                require_steady_state=seg.require_steady_state, **common)
    if isinstance(seg, SlideHoldSlide):
        return tj.SlideHoldSlide(velocity_um_s=seg.velocity_um_s, hold_times_s=tuple(seg.hold_times_s),
                                 reslide_um=seg.reslide_um, run_up_um=seg.run_up_um, **common)
    if isinstance(seg, Square):
        return tj.Square(amplitude_um=seg.amplitude_um, frequency_hz=seg.frequency_hz, cycles=seg.cycles,
                         edge_speed_um_s=seg.edge_speed_um_s, velocity_um_s=seg.velocity_um_s, **common)
    if isinstance(seg, SineSweep):
        return tj.SineSweep(f0_hz=seg.f0_hz, f1_hz=seg.f1_hz, amplitude_um=seg.amplitude_um,
                            duration_s=seg.duration_s, taper_s=seg.taper_s, velocity_um_s=seg.velocity_um_s,
                            **common)
    raise TypeError(f"not a recipe segment: {seg!r}")  # pragma: no cover - the union is closed


def state_length(recipe: Recipe, profile, friction_model=None) -> tuple[float, str]:
    """L (µm) of the friction model in use and where it comes from.

    ``friction_model`` (e.g. ``rig run --friction-model``) when it has a state variable
    (its ``L_um``; a second state's ``L2_um`` is not counted), else the profile's
    lubricant (what a real rig is expected to have)."""
    if friction_model is not None and getattr(friction_model, "has_state", False):
        return float(friction_model.get("L_um")), "the friction model given"
    prof = profile if profile is not None else RigProfile()
    key = prof.lubricant_key(recipe.lubricant)
    lp = prof.lubricants.get(key) if key is not None else None
    if lp is None:
        raise tj.PlanError(f"lubricant {recipe.lubricant!r} is not in profile {prof.name} (it has: "
                           f"{', '.join(prof.lubricant_names())}): no slip length L for the run-up before a step")
    return lp.L_um, f"{recipe.lubricant} in profile {prof.name}"


def plan_spec(recipe: Recipe, profile=None, friction_model=None) -> tj.PlanSpec:
    """The planner's plain description of ``recipe`` (L from the model in use, see :func:`state_length`)."""
    L, src = state_length(recipe, profile, friction_model)
    return tj.PlanSpec(segments=tuple(_plain(s) for s in recipe.segments), accel_um_s2=recipe.accel_um_s2,
                       start_position_um=recipe.start_position_um, state_length_um=L, state_length_source=src,
                       log_rates_hz=(("log.raw_rate_hz", recipe.log.raw_rate_hz),
                                     ("log.decimated_rate_hz", recipe.log.decimated_rate_hz)))


def compile_recipe(recipe: Recipe, profile=None, friction_model=None, limits: tj.RigLimits | None = None
                   ) -> tj.Plan:
    """Compile ``recipe`` for the rig ``profile`` (a :class:`RigProfile`; None: the default limits).

    ``friction_model``: the model the run uses instead of the profile's lubricant, for the
    run-up rule. ``limits`` overrides the profile's :meth:`RigProfile.plan_limits`.
    Raises :class:`trajectories.PlanError` (naming the segment) before anything moves.
    """
    if limits is None:
        limits = profile.plan_limits(str(getattr(profile, "name", "profile"))) if profile is not None else None
    plan = tj.compile_plan(plan_spec(recipe, profile, friction_model), limits)
    plan.controller = recipe.controller.model_dump()
    return plan


__all__ = [
    "Recipe", "RecipeError", "ControllerSwitches", "RunIn", "SteppedPass", "VelocitySteps", "VelocityStep", "Hold", "Move",
    "SlideHoldSlide", "Square", "SineSweep",
    "LogRates", "load_recipe", "parse_recipe", "compile_recipe", "plan_spec", "state_length", "LUBRICANTS",
    "DEFAULT_PASS_VELOCITIES_UM_S",
]
