"""The plan's reference tick by tick, with operator pauses that keep the physics.

A pause asked for while the plan runs takes effect at the next *safe point*
(a segment or velocity-step boundary of the plan, where the reference is about to
change anyway): from that tick the reference holds the position. On resume it
first *runs up* at the velocity of the segment that ran before the pause, over at
least ``runup_um`` (the rig: 5 L, so that the friction's state is back in steady
sliding after the hold, which healed it: Dupont & Dunlap 1995, eq. 6, relaxes as
exp(-d / L), 0.7 % left after 5 L); then the plan goes on where it paused, shifted
by the run-up distance. Before a hold segment, or at rest, there is nothing to run
up. A pause whose run-up would leave the stroke is refused (``pause_refused``).

:class:`PausableReference` is used by the hardware loop (``next()``, one tick) and
by the simulated rig's backend (``take(n)``); it knows nothing of either. Its
``events`` (``pause``, ``resume``, ``pause_refused``, ``runup_done``: trial tick,
kind, data) are for the caller to log. Plain data in, plain data out.
"""

from __future__ import annotations

import numpy as np

RUN, PENDING, HOLD, RUNUP = "run", "pending", "hold", "runup"


# the plan's event fields that are times (s) and positions (µm): after a pause they move with the plan
EVENT_TIME_KEYS = ("t_s", "ramp_end_s", "t_start_s", "t_end_s", "window_t_start_s", "window_t_end_s")
EVENT_POSITION_KEYS = ("x_um", "x_start_um", "x_end_um", "x_min_um", "x_max_um", "window_x_start_um",
                       "window_x_end_um")


def shift_event(event: dict, dt_s: float, dx_um: float) -> dict:
    """A plan event as it happens after pauses that delayed the plan by ``dt_s`` and moved it by ``dx_um``."""
    out = dict(event)
    for k in EVENT_TIME_KEYS:
        if isinstance(out.get(k), (int, float)):
            out[k] = out[k] + dt_s
    for k in EVENT_POSITION_KEYS:
        if isinstance(out.get(k), (int, float)):
            out[k] = out[k] + dx_um
    return out


def safe_ticks_of(events: list[dict], rate_hz: float) -> list[int]:
    """The plan's safe points (ticks) from its events: segment starts and velocity steps."""
    ks = {int(round(e["t_s"] * rate_hz)) for e in events if e.get("kind") in ("segment_start", "velocity_step")}
    return sorted(k for k in ks if k > 0)


class PausableReference:
    """``x_ref_um`` (one value per tick at ``dt_s``) with pauses at ``safe_ticks``; see the module
    docstring. ``stroke_um``: (min, max) the shifted plan and the run-up must stay within."""

    def __init__(self, x_ref_um, dt_s: float, safe_ticks, runup_um: float, stroke_um=(-np.inf, np.inf)):
        self.x = np.asarray(x_ref_um, dtype=float)
        self.dt_s = float(dt_s)
        self.safe = np.asarray(sorted(safe_ticks), dtype=np.int64)
        self.runup_um = float(runup_um)
        self.stroke = (float(stroke_um[0]), float(stroke_um[1]))
        self.n = int(self.x.size)
        self.k_plan = 0          # the plan's next tick
        self.plan_k = 0          # the plan's tick of the last value handed out (held through a pause)
        self.k_trial = 0         # ticks handed out
        self.shift_um = 0.0      # added to the plan after run-ups
        self.state = RUN
        self.resume_asked = False
        self.hold_um = 0.0
        self.hold_ticks = 0      # ticks of the current hold
        self._ru_v = 0.0         # run-up velocity (µm per tick) and what is left of it (µm)
        self._ru_left = 0.0
        self._ru_x = 0.0
        self.events: list[tuple[int, str, dict]] = []

    # -- requests -------------------------------------------------------------------------------------
    @property
    def paused(self) -> bool:
        """A pause is pending or holding (a resume has not been asked for)."""
        return self.state in (PENDING, HOLD) and not self.resume_asked

    def request_pause(self) -> None:
        if self.state == RUN and self.k_plan < self.n:
            self.state = PENDING
            self.resume_asked = False

    def request_resume(self) -> None:
        if self.state == PENDING:
            self.state = RUN  # never reached its safe point: nothing to undo
        elif self.state == HOLD:
            self.resume_asked = True

    def toggle(self) -> None:
        """SIGUSR1: pause when running, resume when paused."""
        if self.paused:
            self.request_resume()
        else:
            self.request_pause()

    @property
    def done(self) -> bool:
        """The plan's last tick is out (a pause still pending at the end never came to a safe point)."""
        return self.k_plan >= self.n and self.state in (RUN, PENDING)

    @property
    def hold_s(self) -> float:
        return self.hold_ticks * self.dt_s if self.state == HOLD else 0.0

    # -- ticks ----------------------------------------------------------------------------------------
    def _plan_value(self, k: int) -> float:
        return float(self.x[k if k < self.n else self.n - 1]) + self.shift_um

    def _at_safe_point(self) -> bool:
        k = self.k_plan
        i = int(np.searchsorted(self.safe, k))
        return i < self.safe.size and self.safe[i] == k

    def _start_hold(self) -> None:
        k = self.k_plan
        self.hold_um = self._plan_value(k - 1) if k > 0 else self._plan_value(0)
        v = (self.x[k - 1] - self.x[k - 2]) if k >= 2 else 0.0  # µm per tick of the segment before
        if k >= 3 and abs(v - (self.x[k - 2] - self.x[k - 3])) > 1e-9:
            v = 0.0  # it ended on a ramp to rest (a run-in's return): no slide to run up to (its last tick's
            #          speed, a fraction of a µm/s, would take hours over 5 L)
        dist = self.runup_um if abs(v) > 1e-12 else 0.0
        lo, hi = self.stroke
        rest = self.x[k:] + self.shift_um + np.sign(v) * dist  # the plan after the run-up
        outside = bool(rest.size) and (rest.min() < lo or rest.max() > hi)
        if dist and (outside or not lo <= self.hold_um + np.sign(v) * dist <= hi):
            self.state = RUN
            self.events.append((self.k_trial, "pause_refused", {
                "reason": f"the run-up of {dist:.1f} µm would leave the stroke [{lo:g}, {hi:g}] µm",
                "plan_t_s": k * self.dt_s}))
            return
        self.state, self.hold_ticks, self.resume_asked = HOLD, 0, False
        self._ru_v, self._ru_left = float(v), float(dist)
        self.events.append((self.k_trial, "pause", {"plan_t_s": k * self.dt_s, "hold_um": self.hold_um,
                                                    "runup_um": dist, "runup_v_um_s": v / self.dt_s}))

    def next(self) -> float:
        """This tick's reference (µm); advances one tick."""
        st = self.state
        if st == PENDING and self._at_safe_point():
            self._start_hold()
            st = self.state
        if st == HOLD:
            if not self.resume_asked:
                self.hold_ticks += 1
                self.k_trial += 1
                self.plan_k = max(0, self.k_plan - 1)
                return self.hold_um
            self.events.append((self.k_trial, "resume", {"held_s": self.hold_ticks * self.dt_s,
                                                        "runup_um": self._ru_left}))
            self.state, self._ru_x = RUNUP, self.hold_um
            st = RUNUP
        if st == RUNUP:
            if self._ru_left > 1e-9:
                step = min(abs(self._ru_v), self._ru_left)
                self._ru_left -= step
                self._ru_x += step if self._ru_v > 0 else -step
                self.k_trial += 1
                self.plan_k = max(0, self.k_plan - 1)
                return self._ru_x
            self.shift_um += self._ru_x - self.hold_um  # the plan goes on from where the run-up ended
            self.state = RUN
            self.events.append((self.k_trial, "runup_done", {"plan_t_s": self.k_plan * self.dt_s,
                                                            "shift_um": self.shift_um}))
        xr = self._plan_value(self.k_plan)
        self.plan_k = min(self.k_plan, self.n - 1)
        self.k_plan += 1
        self.k_trial += 1
        return xr

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next ``n`` ticks (fewer at the plan's end): the reference and, per tick, the plan's tick it
        stands for (a plan's per-tick inputs, e.g. the friction feed-forward, are held through a pause)."""
        out = np.empty(n)
        kp = np.empty(n, dtype=np.int64)
        i = 0
        while i < n and not self.done:
            out[i] = self.next()
            kp[i] = self.plan_k
            i += 1
        return out[:i], kp[:i]
