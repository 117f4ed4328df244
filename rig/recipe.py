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
    from steady sliding at ``v1`` (several L of slip) to ``v2`` (section 4.2:
    1->2, 1->5, 1->10 µm/s), with enough slip after the step for the f_2
    windows 50, 100 and 250 µm after it plus 200 points at 25 Hz (eqs. 10-12).
``hold``
    stand still for a duration.
``move``
    go to a position at a speed.

:func:`load_recipe` turns any fault into ONE :class:`RecipeError` whose message
names the file, the field path (``segments[2].slip_after_um``) and the line of
the YAML node, so that nothing runs from a broken recipe.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

LUBRICANTS = ("dry", "paraffin", "boundary")

# The paper's 7 velocities of the stepped pass, 1..200 µm/s: 7 log-spaced values
# (geomspace(1, 200, 7) = 1, 2.4, 5.8, 14, 34, 83, 200) rounded to the nearest
# 1-2-5 value in log.
DEFAULT_PASS_VELOCITIES_UM_S = (1.0, 2.0, 5.0, 10.0, 50.0, 100.0, 200.0)


class RecipeError(ValueError):
    """A recipe cannot be used. ``str()`` names the file, the field and the line."""

    def __init__(self, path: str | os.PathLike, message: str, field: str | None = None,
                 line: int | None = None):
        self.path = str(path)
        self.field = field
        self.line = line
        self.message = message
        where = self.path
        if line is not None:
            where += f", line {line}"
        if field:
            where += f", field '{field}'"
        super().__init__(f"{where}: {message}")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=False)


Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _SegmentBase(_Strict):
    label: str | None = Field(None, description="Free name of the segment, shown in progress and events.")
    accel_um_s2: Positive | None = Field(
        None, description="Acceleration bound of this segment's velocity transitions (µm/s²); "
                          "default: the recipe's accel_um_s2.")


class RunIn(_SegmentBase):
    """Pull then push through ``distance_um`` at ``speed_um_s`` (paper section 4: 4 mm at 20 µm/s)."""

    kind: Literal["run_in"]
    distance_um: Positive = 4000.0
    speed_um_s: Positive = 20.0


class SteppedPass(_SegmentBase):
    """Section 4.1: velocity stepped every ``level_um`` along a ``pass_um`` tensile pass.

    The levels go up through ``velocities_um_s`` (sorted ascending) and back
    down, each velocity twice, so ``pass_um == 2 * len(velocities) * level_um``
    (3.5 mm = 14 x 250 µm for 7 velocities). Friction is averaged over the last
    ``window_um`` of each level.
    """

    kind: Literal["stepped_pass"]
    velocities_um_s: list[Positive] = Field(default_factory=lambda: list(DEFAULT_PASS_VELOCITIES_UM_S),
                                            min_length=1)
    level_um: Positive = 250.0
    pass_um: Positive | None = Field(None, description="Length of the pass (µm); default and required value: "
                                                        "2 x len(velocities) x level_um (3.5 mm for 7).")
    window_um: Positive = 50.0

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
            self.pass_um = n_levels * self.level_um
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


class VelocityStep(_Strict):
    """One step v1 -> v2 from steady sliding at v1."""

    v1_um_s: Positive
    v2_um_s: Positive
    slip_before_um: Positive | None = Field(None, description="Slip at v1 before the step; default: the segment's.")
    slip_after_um: Positive | None = Field(None, description="Slip at v2 after the step; default: the segment's.")

    @model_validator(mode="after")
    def _different(self):
        if self.v1_um_s == self.v2_um_s:
            raise ValueError("v1_um_s and v2_um_s are equal: that is no velocity step")
        return self


class VelocitySteps(_SegmentBase):
    """Section 4.2: steps in velocity from steady sliding, each in a fresh stretch of slip.

    For each step: accelerate to v1, slide ``slip_before_um`` (several L, so
    the state variable is at steady state), step to v2, slide
    ``slip_after_um`` (past the f_2 windows at 50, 100 and 250 µm plus 200
    points at the log rate), stop, hold ``hold_s``, and return to the segment's
    start position at ``return_speed_um_s`` (``null``: do not return).
    """

    kind: Literal["velocity_steps"]
    steps: list[VelocityStep] = Field(min_length=1)
    slip_before_um: Positive = 120.0
    slip_after_um: Positive = 300.0
    return_speed_um_s: Positive | None = 100.0
    hold_s: NonNeg = 1.0


class Hold(_SegmentBase):
    kind: Literal["hold"]
    duration_s: Positive


class Move(_SegmentBase):
    kind: Literal["move"]
    position_um: Finite
    speed_um_s: Positive


Segment = Annotated[Union[RunIn, SteppedPass, VelocitySteps, Hold, Move], Field(discriminator="kind")]


class LogRates(_Strict):
    """What the log keeps: raw loop data (blocks) and a decimated per-sample channel."""

    raw_rate_hz: Positive = Field(1000.0, description="Rate of the raw channel; must divide the loop rate "
                                                      "(the loop rate itself keeps every tick).")
    decimated_rate_hz: Positive = Field(25.0, description="Rate of the per-sample channel (the paper logged at 25 Hz).")
    block_s: Positive = Field(1.0, description="Duration covered by one raw block message (s).")
    raw_encoding: Literal["binary", "base64", "json"] = Field(
        "binary", description="Arrays of a raw block: binary little-endian float columns (rig.columns.v1, "
                              "fastest), base64 of them in JSON, or JSON number lists (docs/trial.md).")
    raw_dtype: Literal["float64", "float32"] = Field(
        "float64", description="Precision of the raw arrays (t_s is always float64); float32 halves "
                               "the raw data.")


class Recipe(_Strict):
    """One trial's procedure (what ``rig run`` executes)."""

    name: str = Field(min_length=1)
    description: str | None = None
    lubricant: Literal["dry", "paraffin", "boundary"]
    normal_force_N: Positive = Field(100.0, description="Nominal per-rider normal force (N); 100 N in the paper.")
    segments: list[Segment] = Field(min_length=1)
    log: LogRates = Field(default_factory=LogRates)
    seed: int = 0
    trials: int = Field(1, ge=1, le=1000, description="Number of trials; one MCAP each, numbered.")
    accel_um_s2: Positive = Field(500.0, description="Default acceleration bound of velocity transitions (µm/s²).")
    start_position_um: Finite | None = Field(
        None, description="Where the reference starts (µm); default: the rig profile's initial position.")
    profile: str | None = Field(None, description="Rig profile YAML (relative to the current directory, "
                                                  "else to the recipe file).")

    # filled by load_recipe, not part of the YAML
    _source_path: str | None = PrivateAttr(None)
    _source_text: str | None = PrivateAttr(None)

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


# ---------------------------------------------------------------------------
# Loading with errors mapped back to YAML lines
# ---------------------------------------------------------------------------

def _fmt_loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _locate(root: yaml.Node | None, loc: tuple) -> tuple[tuple, int | None]:
    """Walk the composed YAML tree along a pydantic error ``loc``.

    Returns the cleaned field path (union tags such as ``'velocity_steps'``
    dropped) and the 1-based line of the deepest node reached (for a missing
    field: the mapping that should hold it).
    """
    node = root
    path: list = []
    line = None if node is None else node.start_mark.line + 1
    for part in loc:
        if node is None:
            path.append(part)
            continue
        if isinstance(node, yaml.MappingNode) and isinstance(part, str):
            found = None
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == part:
                    found = (k, v)
                    break
            if found is None:
                # a discriminator tag of a union, or a missing field
                if part in _SEGMENT_KINDS or part.startswith("function-"):
                    continue
                path.append(part)
                node = None
                continue
            path.append(part)
            node = found[1]
            line = found[0].start_mark.line + 1 if not isinstance(node, yaml.ScalarNode) else node.start_mark.line + 1
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int):
            path.append(part)
            if 0 <= part < len(node.value):
                node = node.value[part]
                line = node.start_mark.line + 1
            else:
                node = None
        else:
            if isinstance(part, str) and (part in _SEGMENT_KINDS or part.startswith("function-")):
                continue
            path.append(part)
            node = None
    return tuple(path), line


_SEGMENT_KINDS = {"run_in", "stepped_pass", "velocity_steps", "hold", "move"}


def parse_recipe(text: str, path: str | os.PathLike = "<recipe>") -> Recipe:
    """Validate recipe YAML ``text``; ``path`` is only used in messages."""
    path = str(path)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = exc.problem or str(exc)
        raise RecipeError(path, f"YAML syntax error: {problem}", line=line) from None
    except yaml.YAMLError as exc:
        raise RecipeError(path, f"YAML error: {exc}") from None
    if data is None:
        raise RecipeError(path, "empty recipe (expected a mapping with name, lubricant, segments)", line=1)
    if not isinstance(data, dict):
        raise RecipeError(path, f"a recipe is a YAML mapping, found {type(data).__name__}",
                          line=root.start_mark.line + 1 if root is not None else 1)
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        first = errors[0]
        field_path, line = _locate(root, tuple(first["loc"]))
        msg = first["msg"]
        if first["type"] == "missing":
            msg = "required field is missing"
        elif first["type"] == "extra_forbidden":
            msg = "unknown field"
        elif "input" in first and first["type"] not in ("union_tag_invalid",) and not isinstance(
                first["input"], (dict, list)):
            msg += f" (got {first['input']!r})"
        if len(errors) > 1:
            others = []
            for e in errors[1:4]:
                fp, ln = _locate(root, tuple(e["loc"]))
                others.append(f"{_fmt_loc(fp) or '<root>'} (line {ln}): {e['msg']}")
            more = f"; also: {'; '.join(others)}"
            if len(errors) > 4:
                more += f"; and {len(errors) - 4} more"
            msg += more
        raise RecipeError(path, msg, field=_fmt_loc(field_path) or None, line=line) from None
    recipe._source_path = path
    recipe._source_text = text
    return recipe


def load_recipe(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file. Raises :class:`RecipeError` (file, field, line) on any fault."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecipeError(p, "no such file") from None
    except UnicodeDecodeError as exc:
        raise RecipeError(p, f"not valid UTF-8 text ({exc.reason})") from None
    except OSError as exc:
        raise RecipeError(p, f"cannot read: {exc.strerror or exc}") from None
    return parse_recipe(text, p)


__all__ = [
    "Recipe", "RecipeError", "RunIn", "SteppedPass", "VelocitySteps", "VelocityStep", "Hold", "Move",
    "LogRates", "load_recipe", "parse_recipe", "LUBRICANTS", "DEFAULT_PASS_VELOCITIES_UM_S",
]
