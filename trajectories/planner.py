"""Compile a :class:`~trajectories.segments.PlanSpec` into a reference trajectory at the loop rate.

The reference velocity is piecewise: constant, or a raised-cosine transition
between two velocities,

    v(tau) = va + (vb - va) (1 - cos(pi tau / T)) / 2,   0 <= tau <= T,

whose peak acceleration is ``|vb - va| pi / (2 T)``; ``T`` is chosen so that
this equals the acceleration bound (recipe ``accel_um_s2`` or the segment's).
Velocity and acceleration are continuous at every joint (the paper's actuator
produced velocity steps with a 10-90 % rise time under 0.5 s, section 4.2).
The position is integrated in closed form,

    x(tau) = x0 + va tau + (vb - va)/2 (tau - T/pi sin(pi tau / T)),

and sampled at the loop rate with vectorised numpy, so a 1 h plan (3.6 M
ticks) compiles in well under a second.

Everything is checked against the rig's :class:`RigLimits` BEFORE anything
moves: every phase's end position against the stroke (5 mm, the LVDT's range,
section 3), every phase's speed against the actuator's maximum, the log rates
against the loop rate, and the run-up before each velocity step against the
slip length L of the friction model in use (at least ``MIN_RUN_UP_L`` L of
slip at v1, so the step starts from steady sliding, section 4.2). A violation
raises :class:`PlanError` naming the segment and the limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
import numpy as np

from trajectories.segments import (DEFAULT_RUN_UP_L, MIN_RUN_UP_L, Hold, Move, PlanSpec, RigLimits, RunIn,
                                   SineSweep, SlideHoldSlide, Square, SteppedPass, VelocitySteps)

MAX_PLAN_DURATION_S = 8 * 3600.0
WAVE_LEAD_IN_S = 1.0  # a square or sweep on a slide starts this long after the slide reaches its speed
_EPS_UM = 1e-9


class PlanError(ValueError):
    """The recipe cannot run on this rig (stroke, speed, rates). Names the segment and the limit."""

    def __init__(self, message: str, segment: int | None = None, kind: str | None = None,
                 label: str | None = None):
        self.segment = segment
        self.kind = kind
        self.message = message
        where = ""
        if segment is not None:
            where = f"segment {segment + 1} ({kind}{' ' + repr(label) if label else ''}): "
        super().__init__(where + message)


# ---------------------------------------------------------------------------
# The plan
# ---------------------------------------------------------------------------

@dataclass
class Plan:
    """A compiled trial: the reference at the loop rate, its events and its segment table.

    ``x_ref_um[k]`` is the reference position at ``t = k / loop_rate_hz``.
    ``events`` are dicts ``{"t_s", "kind", ...}`` sorted by time: ``segment_start``,
    ``segment_end`` (``segment``, ``segment_kind``, ``label``), ``velocity_step``
    (``v1_um_s``, ``v2_um_s``, ``x_um``, ``ramp_end_s``, ``step``), ``level`` (a
    stepped-pass level: ``level``, ``v_um_s``, ``x_start_um``, ``x_end_um``,
    ``t_end_s``, ``window_t_start_s``, ``window_t_end_s``, ``window_x_start_um``,
    ``window_x_end_um``, ``direction`` up/down), ``hold`` (a slide-hold-slide rest: ``hold``,
    ``hold_s`` at rest, ``v_um_s`` before and after, ``x_um``, ``t_end_s``, ``reslide_um``),
    ``square`` (``amplitude_um``, ``frequency_hz``, ``cycles``, ``x_um`` centre, ``edge_s``,
    ``edges_t_s``, ``velocity_um_s``, ``t_end_s``), ``sine_sweep`` (``f0_hz``, ``f1_hz``,
    ``amplitude_um``, ``duration_s``, ``taper_s``, ``x_um`` centre at the start,
    ``velocity_um_s`` of the slide beneath, ``t_end_s``).
    ``segments`` rows: ``index, kind, label, t_start_s, t_end_s, x_start_um, x_end_um,
    x_min_um, x_max_um, v_max_um_s, i_start, i_end`` (tick indices, end exclusive).
    """

    loop_rate_hz: float
    x_ref_um: np.ndarray
    events: list[dict]
    segments: list[dict]
    limits: RigLimits
    phases: np.ndarray = field(repr=False)  # columns: t0, T, x0, va, vb
    # the recipe's controller switches for this trial ({"ff1": bool, "friction_ff": bool}; empty:
    # the rig profile's settings); plain data, applied by the backend that runs the plan
    controller: dict = field(default_factory=dict)
    # waveforms added to the phases' reference (square, sine sweep): (t0_s, T_s, segment, edge_speed_um_s)
    overlays: list = field(default_factory=list, repr=False)

    @property
    def n_ticks(self) -> int:
        return int(self.x_ref_um.size)

    @property
    def duration_s(self) -> float:
        return (self.n_ticks - 1) / self.loop_rate_hz

    @property
    def dt_s(self) -> float:
        return 1.0 / self.loop_rate_hz

    @cached_property
    def t_s(self) -> np.ndarray:
        return np.arange(self.n_ticks) / self.loop_rate_hz

    @cached_property
    def v_ref_um_s(self) -> np.ndarray:
        """Reference velocity at every tick (closed form, not a finite difference)."""
        x, v = _sample(self.phases, self.t_s)
        _apply_overlays(self.overlays, self.t_s, x, v)
        return v

    def segment_at(self, t_s: float) -> dict:
        """The segment row running at time ``t_s``."""
        for seg in self.segments:
            if t_s < seg["t_end_s"]:
                return seg
        return self.segments[-1]

    def events_of(self, kind: str) -> list[dict]:
        return [e for e in self.events if e["kind"] == kind]

    def summary(self) -> str:
        lines = [f"{self.n_ticks} ticks at {self.loop_rate_hz:g} Hz, {self.duration_s:.1f} s"]
        for s in self.segments:
            lines.append(f"  {s['index'] + 1:2d} {s['kind']:<15} {s['label'] or '':<20} "
                         f"{s['t_start_s']:9.2f}-{s['t_end_s']:9.2f} s  x {s['x_start_um']:8.1f} -> "
                         f"{s['x_end_um']:8.1f} µm  |v|max {s['v_max_um_s']:g} µm/s")
        return "\n".join(lines)


class _Builder:
    """Accumulates velocity phases (constant or raised-cosine) in closed form."""

    def __init__(self, x0: float):
        self.rows: list[tuple[float, float, float, float, float]] = []
        self.t = 0.0
        self.x = float(x0)
        self.v = 0.0

    def _add(self, T: float, vb: float) -> None:
        if T <= 0:
            self.v = vb
            return
        va = self.v
        self.rows.append((self.t, T, self.x, va, vb))
        self.x += 0.5 * (va + vb) * T
        self.t += T
        self.v = vb

    def ramp_time(self, vb: float, accel: float) -> float:
        return math.pi * abs(vb - self.v) / (2.0 * accel)

    def ramp(self, vb: float, accel: float) -> float:
        """Raised-cosine transition to ``vb``; returns its distance (signed)."""
        if vb == self.v:
            return 0.0
        T = self.ramp_time(vb, accel)
        x_before = self.x
        self._add(T, vb)
        return self.x - x_before

    def cruise_time(self, T: float) -> None:
        if T > 0:
            self._add(T, self.v)

    def cruise_to(self, x_target: float) -> None:
        """Constant velocity until ``x_target`` (must lie ahead in the direction of motion)."""
        d = x_target - self.x
        if abs(d) < _EPS_UM:
            return
        if self.v == 0 or d * self.v < 0:
            raise ValueError(f"cannot cruise to {x_target:.3f} µm from {self.x:.3f} at {self.v:g} µm/s")
        self._add(d / self.v, self.v)

    def move_to(self, x_target: float, speed: float, accel: float) -> None:
        """Rest-to-rest move: raised-cosine up to ``speed`` (or less if short), cruise, down to 0."""
        if self.v != 0:
            self.ramp(0.0, accel)
        d = x_target - self.x
        if abs(d) < _EPS_UM:
            return
        s = 1.0 if d > 0 else -1.0
        # two ramps 0<->v cover v*T = pi v^2 / (2 a)
        v_pk = min(speed, math.sqrt(2.0 * accel * abs(d) / math.pi))
        self.ramp(s * v_pk, accel)
        ramps = math.pi * v_pk * v_pk / (2.0 * accel)
        rest = abs(d) - ramps
        if rest > _EPS_UM:
            self._add(rest / v_pk, s * v_pk)
        self.ramp(0.0, accel)
        self.x = x_target  # remove rounding drift

    def time_at_x_in_last_cruise(self, x: float) -> float:
        t0, T, x0, va, vb = self.rows[-1]
        return t0 + (x - x0) / va


def _sample(phases: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity of the phase table at sorted times ``t``.

    Vectorised per phase (a plan has tens to hundreds of phases, millions of ticks).
    Times before the first phase take its start, after the last its end.
    """
    x = np.empty_like(t, dtype=float)
    v = np.empty_like(t, dtype=float)
    if phases.shape[0] == 0:
        x[:] = 0.0
        v[:] = 0.0
        return x, v
    starts = np.searchsorted(t, phases[:, 0], side="left")
    starts[0] = 0
    ends = np.append(starts[1:], t.size)
    for (t0, T, x0, va, vb), i0, i1 in zip(phases, starts, ends):
        if i1 <= i0:
            continue
        tau = t[i0:i1] - t0
        np.clip(tau, 0.0, T, out=tau)
        if va == vb:
            x[i0:i1] = x0 + va * tau
            v[i0:i1] = va
        else:
            w = np.pi / T
            dv = vb - va
            x[i0:i1] = x0 + va * tau + 0.5 * dv * (tau - np.sin(w * tau) / w)
            v[i0:i1] = va + 0.5 * dv * (1.0 - np.cos(w * tau))
    return x, v


def _square_points(seg: Square, edge_speed_um_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints (time from the segment's start, offset) of the speed-limited square wave:
    +a for the first half cycle, -a for the second, ..., straight edges at ``edge_speed_um_s``
    starting at each nominal edge, back to 0 after the last cycle."""
    a, h, c = seg.amplitude_um, 0.5 / seg.frequency_hz, int(seg.cycles)
    e1, e2 = a / edge_speed_um_s, 2.0 * a / edge_speed_um_s
    pts = [(0.0, 0.0), (e1, a)]
    level = a
    for k in range(1, 2 * c):
        pts += [(k * h, level), (k * h + e2, -level)]
        level = -level
    pts += [(2 * c * h, level), (2 * c * h + e1, 0.0)]
    tt, xx = np.array(pts).T
    return tt, xx


def _overlay_values(ov, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset (µm) and its velocity (µm/s) of an overlay waveform at times ``tau`` from its start."""
    _, T, seg, edge = ov
    if isinstance(seg, Square):
        tt, xx = _square_points(seg, edge)
        slopes = np.diff(xx) / np.maximum(np.diff(tt), 1e-300)
        k = np.clip(np.searchsorted(tt, tau, side="right") - 1, 0, tt.size - 2)
        return np.interp(tau, tt, xx), np.where(tau < T, slopes[k], 0.0)
    a, f0 = seg.amplitude_um, seg.f0_hz
    D, Tt = seg.duration_s, seg.taper()
    kk = math.log(seg.f1_hz / f0) / D
    phi = 2.0 * math.pi * f0 * np.expm1(kk * tau) / kk
    dphi = 2.0 * math.pi * f0 * np.exp(kk * tau)
    w, dw = np.ones_like(tau), np.zeros_like(tau)
    for edge_tau, sgn in ((tau, 1.0), (D - tau, -1.0)):
        m = edge_tau < Tt
        w[m] *= 0.5 * (1.0 - np.cos(math.pi * edge_tau[m] / Tt))
        dw[m] = sgn * 0.5 * math.pi / Tt * np.sin(math.pi * edge_tau[m] / Tt)
    return a * w * np.sin(phi), a * (dw * np.sin(phi) + w * np.cos(phi) * dphi)


def _apply_overlays(overlays: list, t: np.ndarray, x: np.ndarray, v: np.ndarray | None = None) -> None:
    """Add the overlay waveforms to the sampled reference ``x`` (and velocity ``v``) in place."""
    for ov in overlays:
        t0, T = ov[0], ov[1]
        i0, i1 = np.searchsorted(t, [t0, t0 + T], side="left")
        if i1 <= i0:
            continue
        dx, dv = _overlay_values(ov, t[i0:i1] - t0)
        x[i0:i1] += dx
        if v is not None:
            v[i0:i1] += dv


def _check_rate(limits: RigLimits, rate_hz: float, what: str) -> int:
    ratio = limits.loop_rate_hz / rate_hz
    n = int(round(ratio))
    if n < 1 or abs(ratio - n) > 1e-9:
        raise PlanError(f"{what} = {rate_hz:g} Hz does not divide the loop rate "
                        f"{limits.loop_rate_hz:g} Hz (profile {limits.source})")
    return n


def compile_plan(spec: PlanSpec, limits: RigLimits | None = None) -> Plan:
    """Compile ``spec`` for a rig with ``limits`` (default: :class:`RigLimits`'s).

    Raises :class:`PlanError` before anything moves when a segment leaves the
    stroke, exceeds the actuator's speed or acceleration, a log rate does not
    divide the loop rate, or a velocity step would start out of steady state.
    """
    lim = limits or RigLimits()
    _check_limits(spec, lim)
    b = _Builder(lim.initial_position_um)
    overlays: list = []
    events: list[dict] = []
    segments: list[dict] = []
    seg_list = _with_approach(spec, lim)
    offset = len(seg_list) - len(spec.segments)
    for k, seg in enumerate(seg_list):
        index = k - offset  # the spec's segment index (-1 for the implicit approach)
        accel = seg.accel_um_s2 or spec.accel_um_s2
        kind, label = seg.kind, seg.label

        def fail(msg: str):
            raise PlanError(msg, segment=index if index >= 0 else None, kind=kind, label=label)

        if accel > lim.max_accel_um_s2:
            fail(f"acceleration {accel:g} µm/s² exceeds the actuator's maximum {lim.max_accel_um_s2:g} µm/s²")
        # speed check before building (what the segment asks for)
        asked = _segment_speeds(seg, lim)
        if asked > lim.max_speed_um_s:
            fail(f"speed {asked:g} µm/s exceeds the actuator's maximum {lim.max_speed_um_s:g} µm/s "
                 f"(profile {lim.source}{lim.max_speed_note})")
        row0, ov0 = len(b.rows), len(overlays)
        t_start, x_start = b.t, b.x
        events.append({"t_s": t_start, "kind": "segment_start", "segment": index, "segment_kind": kind,
                       "label": label, "x_um": x_start})
        try:
            _build_segment(b, seg, accel, index, events, overlays, fail, spec, lim)
        except PlanError:
            raise
        except ValueError as exc:  # builder geometry
            fail(str(exc))
        x_min, x_max, v_max = _segment_extent(b, row0, overlays[ov0:])
        if x_max > lim.stroke_max_um + 1e-6 or x_min < lim.stroke_min_um - 1e-6:
            bad = x_max if x_max > lim.stroke_max_um + 1e-6 else x_min
            fail(f"reference reaches {bad:.1f} µm, outside the stroke [{lim.stroke_min_um:g}, "
                 f"{lim.stroke_max_um:g}] µm (profile {lim.source}); start at {x_start:.1f} µm")
        if v_max > lim.max_speed_um_s * (1 + 1e-12):
            fail(f"speed {v_max:g} µm/s exceeds the actuator's maximum {lim.max_speed_um_s:g} µm/s")
        events.append({"t_s": b.t, "kind": "segment_end", "segment": index, "segment_kind": kind,
                       "label": label, "x_um": b.x})
        segments.append({"index": index, "kind": kind, "label": label, "t_start_s": t_start, "t_end_s": b.t,
                         "x_start_um": x_start, "x_end_um": b.x, "x_min_um": x_min, "x_max_um": x_max,
                         "v_max_um_s": v_max})
        if b.t > MAX_PLAN_DURATION_S:
            fail(f"the plan lasts beyond {MAX_PLAN_DURATION_S / 3600:g} h; split it into trials")
    return _sampled_plan(b, segments, events, overlays, lim)


def _check_limits(spec: PlanSpec, lim: RigLimits) -> None:
    """The log rates divide the loop rate; the rig's initial position is inside its stroke."""
    for what, rate in spec.log_rates_hz:
        _check_rate(lim, rate, what)
    if not lim.stroke_min_um <= lim.initial_position_um <= lim.stroke_max_um:
        raise PlanError(f"the rig's initial position {lim.initial_position_um:g} µm is outside its stroke "
                        f"[{lim.stroke_min_um:g}, {lim.stroke_max_um:g}] µm")


def _with_approach(spec: PlanSpec, lim: RigLimits) -> list:
    """The spec's segments, after an implicit move to ``start_position_um`` when it is not where the rig is."""
    if spec.start_position_um is None or abs(spec.start_position_um - lim.initial_position_um) <= _EPS_UM:
        return list(spec.segments)
    speed = min(100.0, lim.max_speed_um_s)
    return [Move(position_um=spec.start_position_um, speed_um_s=speed, label="approach start_position_um"),
            *spec.segments]


def _build_segment(b: "_Builder", seg, accel: float, index: int, events: list, overlays: list, fail,
                   spec: PlanSpec, lim: RigLimits) -> None:
    """Append one segment's phases (and overlays, events) to the builder."""
    x_start = b.x
    if isinstance(seg, RunIn):
        b.move_to(x_start + seg.distance_um, seg.speed_um_s, accel)
        b.move_to(x_start, seg.speed_um_s, accel)
    elif isinstance(seg, Hold):
        if b.v != 0:
            b.ramp(0.0, accel)
        b.cruise_time(seg.duration_s)
    elif isinstance(seg, Move):
        b.move_to(seg.position_um, seg.speed_um_s, accel)
    elif isinstance(seg, SteppedPass):
        _stepped_pass(b, seg, accel, index, events, fail)
    elif isinstance(seg, VelocitySteps):
        _velocity_steps(b, seg, accel, index, events, fail, spec)
    elif isinstance(seg, SlideHoldSlide):
        _slide_hold_slide(b, seg, accel, index, events, fail, spec)
    elif isinstance(seg, (Square, SineSweep)):
        _waveform(b, seg, accel, index, events, overlays, fail, spec, lim)
    else:  # pragma: no cover - the segment union is closed
        fail("unknown segment kind")


def _segment_extent(b: "_Builder", row0: int, overlays: list) -> tuple[float, float, float]:
    """Lowest and highest position (µm) and the largest speed (µm/s) of the phases from row ``row0``
    on, the segment's ``overlays`` (square wave, sine sweep) included."""
    rows = np.asarray(b.rows[row0:], dtype=float).reshape(-1, 5)
    if rows.size:
        x_ends = np.concatenate([rows[:, 2], rows[:, 2] + 0.5 * (rows[:, 3] + rows[:, 4]) * rows[:, 1]])
        x_min, x_max = float(x_ends.min()), float(x_ends.max())
        v_max = float(np.abs(rows[:, 3:5]).max())
    else:
        x_min = x_max = b.x
        v_max = 0.0
    for ov in overlays:
        amp, base = ov[2].amplitude_um, ov[2].velocity_um_s
        x_min, x_max = x_min - amp, x_max + amp
        v_max = max(v_max, base + _overlay_peak_speed(ov))
    return x_min, x_max, v_max


def _sampled_plan(b: "_Builder", segments: list[dict], events: list[dict], overlays: list, lim: RigLimits) -> Plan:
    """The reference at the loop rate from the builder's phases and the overlays; each segment's tick range."""
    phases = np.asarray(b.rows, dtype=float).reshape(-1, 5)
    n = int(math.floor(b.t * lim.loop_rate_hz + 1e-9)) + 1
    # one extra tick so the final rest position is in the reference
    if (n - 1) / lim.loop_rate_hz < b.t - 1e-12:
        n += 1
    t = np.arange(n) / lim.loop_rate_hz
    x, _ = _sample(phases, t)
    _apply_overlays(overlays, t, x)
    for s in segments:
        s["i_start"] = int(math.ceil(s["t_start_s"] * lim.loop_rate_hz - 1e-9))
        s["i_end"] = min(n, int(math.ceil(s["t_end_s"] * lim.loop_rate_hz - 1e-9)))
    segments[-1]["i_end"] = n
    events.sort(key=lambda e: (e["t_s"], 0 if e["kind"] == "segment_end" else 1))
    return Plan(loop_rate_hz=lim.loop_rate_hz, x_ref_um=x, events=events, segments=segments, limits=lim,
                phases=phases, overlays=overlays)


def _overlay_peak_speed(ov) -> float:
    seg = ov[2]
    if isinstance(seg, Square):
        return float(ov[3])
    return 2.0 * math.pi * seg.f1_hz * seg.amplitude_um * (1.0 + 1.0 / (seg.f1_hz * seg.taper()))


def _segment_speeds(seg, lim: RigLimits) -> float:
    if isinstance(seg, RunIn):
        return seg.speed_um_s
    if isinstance(seg, Move):
        return seg.speed_um_s
    if isinstance(seg, SteppedPass):
        return max(seg.velocities_um_s)
    if isinstance(seg, SlideHoldSlide):
        return seg.velocity_um_s
    if isinstance(seg, Square):
        return seg.velocity_um_s + (seg.edge_speed_um_s or lim.max_speed_um_s)
    if isinstance(seg, SineSweep):
        return seg.velocity_um_s + _overlay_peak_speed((0.0, seg.duration_s, seg, None))
    if isinstance(seg, VelocitySteps):
        vs = [max(s.v1_um_s, s.v2_um_s) for s in seg.steps]
        if seg.return_speed_um_s:
            vs.append(seg.return_speed_um_s)
        return max(vs)
    return 0.0


def _stepped_pass(b: _Builder, seg: SteppedPass, accel: float, index: int, events: list, fail) -> None:
    """Section 4.1: levels of ``level_um`` each; transitions start at a level's beginning."""
    x_s = b.x
    if b.v != 0:
        b.ramp(0.0, accel)
    levels = seg.levels_um_s()
    n_up = len(seg.velocities_um_s)
    for i, v in enumerate(levels):
        t_lvl, x_lvl = b.t, b.x
        d = b.ramp(v, accel)
        if d > seg.level_um - seg.window_um + 1e-9:
            fail(f"level {i + 1}: the transition to {v:g} µm/s takes {d:.1f} µm at {accel:g} µm/s², more than "
                 f"level_um - window_um = {seg.level_um - seg.window_um:g} µm; raise accel_um_s2")
        x_end = x_s + (i + 1) * seg.level_um
        b.cruise_to(x_end)
        t_end = b.t
        xw0 = x_end - seg.window_um
        tw0 = b.time_at_x_in_last_cruise(xw0)
        events.append({"t_s": t_lvl, "kind": "level", "segment": index, "level": i, "v_um_s": v,
                       "direction": "up" if i < n_up else "down", "x_start_um": x_lvl, "x_end_um": x_end,
                       "t_end_s": t_end, "window_t_start_s": tw0, "window_t_end_s": t_end,
                       "window_x_start_um": xw0, "window_x_end_um": x_end})
    b.ramp(0.0, accel)


def _run_up_um(b: _Builder, st, seg: VelocitySteps, accel: float, j: int, spec: PlanSpec, fail) -> float:
    """Slip from rest to the step (ramp to v1 included), checked against L of the model in use."""
    return _run_up_check(b, st.v1_um_s, st.slip_before_um, accel, spec,
                         f"step {j + 1} ({st.v1_um_s:g} -> {st.v2_um_s:g} µm/s)", fail, "slip_before_um",
                         steady=seg.require_steady_state, hint=", or set require_steady_state: false", vname="v1",
                         noun="a step")


def _velocity_steps(b: _Builder, seg: VelocitySteps, accel: float, index: int, events: list, fail,
                    spec: PlanSpec) -> None:
    """Section 4.2: rest -> v1 for the run-up -> v2 for slip_after -> rest (-> return)."""
    if b.v != 0:
        b.ramp(0.0, accel)
    x_home = b.x
    L = spec.state_length_um
    for j, st in enumerate(seg.steps):
        before = _run_up_um(b, st, seg, accel, j, spec, fail)
        after = st.slip_after_um
        x0 = b.x
        d = b.ramp(st.v1_um_s, accel)
        b.cruise_to(x0 + before)
        t_step, x_step = b.t, b.x
        d2 = b.ramp(st.v2_um_s, accel)
        if d2 > after:
            fail(f"step {j + 1}: slip_after_um {after:g} is shorter than the transition ({d2:.2f} µm)")
        ramp_end = b.t
        b.cruise_to(x_step + after)
        events.append({"t_s": t_step, "kind": "velocity_step", "segment": index, "step": j,
                       "v1_um_s": st.v1_um_s, "v2_um_s": st.v2_um_s, "x_um": x_step, "ramp_end_s": ramp_end,
                       "slip_before_um": before, "slip_after_um": after, "t_end_s": b.t,
                       "x_end_um": b.x, "run_up_L": None if L is None else (before - d) / L})
        b.ramp(0.0, accel)
        b.cruise_time(seg.hold_s)
        if seg.return_speed_um_s:
            b.move_to(x_home, seg.return_speed_um_s, accel)
            b.cruise_time(seg.hold_s)


def _run_up_check(b: _Builder, v: float, given: float | None, accel: float, spec: PlanSpec, what: str, fail,
                  field_name: str, steady: bool = True, hint: str = "", vname: str = "v",
                  noun: str = "a hold") -> float:
    """Slip from rest (ramp to ``v`` included) before a hold or a step: ``given``, or the ramp
    plus DEFAULT_RUN_UP_L x L; refused below MIN_RUN_UP_L x L at ``v`` (exp(-5): the state
    within 0.7 % of steady state, eq. 6)."""
    d_ramp = math.pi * v * v / (4.0 * accel)
    L = spec.state_length_um
    if given is None:
        if L is None:
            fail(f"{what}: {field_name} is needed (no slip length L of a friction model was given)")
        return d_ramp + DEFAULT_RUN_UP_L * L
    if given < d_ramp:
        fail(f"{what}: {field_name} {given:g} is shorter than the run-up to {vname} ({d_ramp:.2f} µm)")
    if L is not None and steady and given - d_ramp < MIN_RUN_UP_L * L * (1 - 1e-9):
        src = f" ({spec.state_length_source})" if spec.state_length_source else ""
        fail(f"{what} would start out of steady state: {given - d_ramp:.1f} µm of slip at {vname} is "
             f"{(given - d_ramp) / L:.2f} L, with L = {L:g} µm{src}; {noun} needs at least {MIN_RUN_UP_L:g} L = "
             f"{MIN_RUN_UP_L * L:.1f} µm at {vname} (the state relaxes as exp(-slip/L), eq. 6). Set {field_name} "
             f">= {math.ceil(d_ramp + MIN_RUN_UP_L * L):g}, or leave it out ({DEFAULT_RUN_UP_L:g} L){hint}")
    return given


def _slide_hold_slide(b: _Builder, seg: SlideHoldSlide, accel: float, index: int, events: list, fail,
                      spec: PlanSpec) -> None:
    """Slide (run-up >= 5 L), then per hold: stop, rest ``t_hold``, re-slide ``reslide_um`` at v."""
    if b.v != 0:
        b.ramp(0.0, accel)
    v = seg.velocity_um_s
    vname = f"v = {v:g} µm/s"
    run_up = _run_up_check(b, v, seg.run_up_um, accel, spec, "the run-up", fail, "run_up_um", vname=vname)
    reslide = _run_up_check(b, v, seg.reslide_um, accel, spec, "the re-slide (the next hold's run-up)", fail,
                            "reslide_um", vname=vname)
    x0 = b.x
    b.ramp(v, accel)
    b.cruise_to(x0 + run_up)
    for j, t_hold in enumerate(seg.hold_times_s):
        t_stop = b.t
        b.ramp(0.0, accel)
        t_rest, x_hold = b.t, b.x
        b.cruise_time(t_hold)
        t_end = b.t
        b.ramp(v, accel)
        b.cruise_to(x_hold + reslide)
        events.append({"t_s": t_rest, "kind": "hold", "segment": index, "hold": j, "hold_s": float(t_hold),
                       "v_um_s": v, "x_um": x_hold, "t_stop_s": t_stop, "t_end_s": t_end, "reslide_um": reslide,
                       "t_reslide_end_s": b.t})
    b.ramp(0.0, accel)


def _waveform(b: _Builder, seg, accel: float, index: int, events: list, overlays: list, fail, spec: PlanSpec,
              lim: RigLimits) -> None:
    """A square wave or a sine sweep about the current position (the reference at rest beneath)."""
    raw = dict(spec.log_rates_hz).get("log.raw_rate_hz")
    if raw is not None and raw < lim.loop_rate_hz:
        fail(f"a {seg.kind} segment is a loop-tuning test and is logged at the loop rate: log.raw_rate_hz "
             f"{raw:g} Hz must be {lim.loop_rate_hz:g} Hz")
    if b.v != seg.velocity_um_s:
        b.ramp(seg.velocity_um_s, accel)
        if seg.velocity_um_s > 0:
            b.cruise_time(WAVE_LEAD_IN_S)  # the loop settles on the slide before the wave begins
    t0, xc = b.t, b.x
    if isinstance(seg, Square):
        edge = seg.edge_speed_um_s or (lim.max_speed_um_s - seg.velocity_um_s)
        half = 0.5 / seg.frequency_hz
        if 2.0 * seg.amplitude_um / edge > 0.5 * half:
            fail(f"an edge of {2 * seg.amplitude_um:g} µm at {edge:g} µm/s takes {2e3 * seg.amplitude_um / edge:.1f}"
                 f" ms, more than half of the half period ({500.0 * half:.1f} ms at {seg.frequency_hz:g} Hz): "
                 f"lower frequency_hz or amplitude_um")
        if math.isfinite(lim.max_accel_um_s2):
            fail(f"a square wave's edges are straight ramps (no acceleration bound) and the rig limits the "
                 f"acceleration to {lim.max_accel_um_s2:g} µm/s²; use a sine_sweep")
        tt, _ = _square_points(seg, edge)
        T = float(tt[-1])
        e = 2.0 * seg.amplitude_um / edge
        edges = [t0] + [t0 + k * half for k in range(1, 2 * int(seg.cycles) + 1)]
        events.append({"t_s": t0, "kind": "square", "segment": index, "amplitude_um": seg.amplitude_um,
                       "frequency_hz": seg.frequency_hz, "cycles": int(seg.cycles), "x_um": xc,
                       "velocity_um_s": seg.velocity_um_s, "edge_s": e,
                       "edge_speed_um_s": edge, "edges_t_s": edges, "t_end_s": t0 + T})
    else:
        if seg.f1_hz <= seg.f0_hz:
            fail(f"f1_hz ({seg.f1_hz:g}) must exceed f0_hz ({seg.f0_hz:g})")
        if seg.f1_hz > 0.5 * lim.loop_rate_hz:
            fail(f"f1_hz {seg.f1_hz:g} Hz is above the loop's Nyquist frequency {0.5 * lim.loop_rate_hz:g} Hz")
        if 2.0 * seg.taper() > seg.duration_s:
            fail(f"taper_s {seg.taper():g} s at both ends is longer than the sweep ({seg.duration_s:g} s)")
        a_pk = (2.0 * math.pi * seg.f1_hz) ** 2 * seg.amplitude_um
        if a_pk > lim.max_accel_um_s2:
            fail(f"the sweep's peak acceleration (2 pi f1)^2 a = {a_pk:.4g} µm/s² exceeds the actuator's maximum "
                 f"{lim.max_accel_um_s2:g} µm/s²")
        T = seg.duration_s
        edge = None
        events.append({"t_s": t0, "kind": "sine_sweep", "segment": index, "f0_hz": seg.f0_hz, "f1_hz": seg.f1_hz,
                       "amplitude_um": seg.amplitude_um, "duration_s": T, "taper_s": seg.taper(), "x_um": xc,
                       "velocity_um_s": seg.velocity_um_s, "t_end_s": t0 + T})
    overlays.append((t0, T, seg, edge))
    b.cruise_time(T)
    if b.v != 0:
        b.ramp(0.0, accel)


__all__ = ["Plan", "PlanError", "compile_plan", "MAX_PLAN_DURATION_S"]
