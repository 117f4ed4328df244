"""A log writer that keeps the trial in memory (simulation for analysis, tests, loop-bench)."""

from __future__ import annotations

import numpy as np

from rig.data import TrialData
from rig.log.decimate import block_mean, decimation_factor


class MemoryLog:
    """The writer interface of :class:`rig.log.TrialLogWriter`, in memory.

    Planned events are kept once a block reaches their time, as in the MCAP
    log. ``keep_blocks=False`` keeps only events and statistics (loop-bench).
    """

    def __init__(self, keep_blocks: bool = True, rate_hz: float = 1000.0, metadata: dict | None = None):
        self.keep_blocks = keep_blocks
        self.rate_hz = float(rate_hz)
        self.metadata = dict(metadata or {})
        self.blocks: list[dict] = []
        self.events: list[dict] = []
        self.stats: list[tuple[float, dict]] = []
        self.ticks = 0
        self.last_t_s = 0.0
        self.status: str | None = None
        self.summary: dict = {}
        self._pending: list[dict] = []

    def schedule_events(self, events) -> None:
        self._pending = sorted([dict(e) for e in events] + self._pending, key=lambda e: e["t_s"])

    def event(self, t_s: float, kind: str, **data) -> None:
        self.events.append({"t_s": float(t_s), "kind": kind, **data})

    def write_block(self, block: dict, *, frozen: bool = False) -> None:  # noqa: ARG002 - stored as given
        t = block["t_s"]
        if t.size == 0:
            return
        if self.keep_blocks:
            self.blocks.append(block)
        self.ticks += t.size
        self.last_t_s = float(t[-1])
        until = self.last_t_s + 0.5 / self.rate_hz
        k = 0
        while k < len(self._pending) and self._pending[k]["t_s"] <= until:
            e = self._pending[k]
            self.event(e["t_s"], e["kind"], **{a: b for a, b in e.items() if a not in ("t_s", "kind")})
            k += 1
        del self._pending[:k]

    def loop_stats(self, t_s: float, stats: dict) -> None:
        self.stats.append((float(t_s), dict(stats)))

    def warm_up(self) -> None:
        """Nothing to load (the writer interface: :meth:`rig.log.TrialLogWriter.warm_up`)."""

    def failure(self) -> BaseException | None:
        """Memory does not fail (the writer interface: :meth:`rig.log.TrialLogWriter.failure`)."""
        return None

    def close(self, status: str = "completed", *, timeout_s: float | None = None, **summary) -> None:
        self.status = status
        self.summary = summary

    # -- reading ---------------------------------------------------------------
    def column(self, key: str) -> np.ndarray:
        return np.concatenate([b[key] for b in self.blocks]) if self.blocks else np.zeros(0)

    def columns(self) -> dict[str, np.ndarray]:
        keys = self.blocks[0].keys() if self.blocks else ()
        return {k: self.column(k) for k in keys}

    def trial_data(self, rate_hz: float | None = 25.0, extra: tuple[str, ...] = ("true_velocity_um_s", "true_mu"),
                   source: str = "") -> TrialData:
        """The samples as :class:`TrialData`: the log's 25 Hz channel (block means over each
        ``loop_rate / rate_hz`` ticks from the first, time-stamped at their centre,
        :func:`rig.log.decimate.block_mean`, the same function as the MCAP writer's ``/log25``),
        every tick with ``rate_hz=None``."""
        cols = self.columns()
        every = 1 if rate_hz is None else decimation_factor(self.rate_hz, rate_hz)
        sel = cols if every == 1 else block_mean(cols, every)
        kinds = {"trial_start", "stop_state", "log_start", "log_end"}
        return TrialData(
            time_s=sel["t_s"], position_um=sel["position_um"], friction_N=sel["friction_N"],
            normal_1_N=sel.get("normal_1_N"), normal_2_N=sel.get("normal_2_N"),
            position_ref_um=sel.get("position_ref_um"), valve_cmd=sel.get("valve_cmd"),
            extra={k: sel[k] for k in extra if k in sel}, metadata=dict(self.metadata),
            events=[e for e in self.events if e["kind"] not in kinds], source=source)
