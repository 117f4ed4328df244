"""The running figures of the logged samples: one accumulator for the session's summary and loop statistics.

:class:`BlockFigures` sums, block by block, what ``rig run`` prints and the
``trial_end`` record keeps: the tracking error (``position_ref_um - position_um``:
RMS and maximum, µm), the friction (mean and mean absolute, N), the friction
coefficient ``mu = friction_N / (normal_1_N + normal_2_N)`` (mean over the samples
where it is defined: finite, the normal forces' sum not 0) and the ticks with the
valve saturated (``|valve_cmd| >= 1``). Non-finite samples are skipped, each
figure counting its own samples. One numba pass per block (:func:`_block_stats`,
compiled on first use and cached beside the source; ``warm_up`` loads it before a
real-time loop starts). The session (:class:`rig.session.TrialSession`) owns one per
trial; the log writer keeps none of its own.
"""

from __future__ import annotations

import math
import time

import numpy as np

#: the accumulator's slots
SUM_E2, MAX_E, N_E, SUM_F, SUM_ABS_F, N_F, SUM_MU, N_SAT, N_MU = range(9)


def _block_stats_py(ref, pos, f, n1, n2, valve, acc):  # pragma: no cover - compiled
    """Accumulate a block's figures into ``acc`` (the slots above; non-finite samples skipped)."""
    if ref.size == pos.size:
        for i in range(ref.size):
            e = ref[i] - pos[i]
            if math.isfinite(e):
                acc[0] += e * e
                ae = abs(e)
                if ae > acc[1]:
                    acc[1] = ae
                acc[2] += 1.0
    with_n = n1.size == f.size and n2.size == f.size
    for i in range(f.size):
        fi = f[i]
        if math.isfinite(fi):
            acc[3] += fi
            acc[4] += abs(fi)
            acc[5] += 1.0
            if with_n:
                nn = n1[i] + n2[i]
                if nn != 0.0:
                    mu = fi / nn
                    if math.isfinite(mu):
                        acc[6] += mu
                        acc[8] += 1.0
    for i in range(valve.size):
        if abs(valve[i]) >= 1.0:
            acc[7] += 1.0


_JIT: dict = {}
_EMPTY = np.zeros(0)


def _block_stats(ref, pos, f, n1, n2, valve, acc) -> None:
    """numba-compiled :func:`_block_stats_py` (compiled on first use, so reading a log needs no numba)."""
    fn = _JIT.get("stats")
    if fn is None:
        from rig.jitstart import kernel

        fn = _JIT["stats"] = kernel(_block_stats_py)
    fn(ref, pos, f, n1, n2, valve, acc)


def warm_up() -> None:
    """Compile (or load from numba's cache) the accumulator's kernel now."""
    _block_stats(_EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY, np.zeros(9))


def _f64(b: dict, key: str) -> np.ndarray:
    v = b.get(key)
    if v is None:
        return _EMPTY
    return v if type(v) is np.ndarray and v.dtype == np.float64 else np.asarray(v, dtype=np.float64)


class BlockFigures:
    """Running sums over the blocks: tracking error, friction, mu, valve saturation.

    ``window()`` gives the figures since the previous call; the properties the
    whole trial's. Non-finite samples are skipped.
    """

    def __init__(self):
        self.ticks = 0
        self.last_t_s = 0.0
        self.acc = np.zeros(9)
        self._w_acc = self.acc.copy()
        self._w_ticks = 0
        self._w_wall = time.perf_counter()

    warm_up = staticmethod(warm_up)

    def add(self, b: dict) -> None:
        t = b["t_s"]
        n = len(t)
        if n == 0:
            return
        _block_stats(_f64(b, "position_ref_um"), _f64(b, "position_um"), _f64(b, "friction_N"),
                     _f64(b, "normal_1_N"), _f64(b, "normal_2_N"), _f64(b, "valve_cmd"), self.acc)
        self.ticks += n
        self.last_t_s = float(t[-1])

    def window(self, rate_hz: float) -> dict:
        now = time.perf_counter()
        dw = now - self._w_wall
        d = self.acc - self._w_acc
        ticks = self.ticks - self._w_ticks
        out = {"ticks": ticks, "wall_s": dw,
               "ticks_per_s": ticks / dw if dw > 0 else None,
               "realtime_factor": (ticks / rate_hz) / dw if dw > 0 else None,
               "tracking_error_rms_um": math.sqrt(d[SUM_E2] / d[N_E]) if d[N_E] else None,
               "valve_saturated_fraction": d[N_SAT] / ticks if ticks else None}
        self._w_acc = self.acc.copy()
        self._w_ticks = self.ticks
        self._w_wall = now
        return out

    @property
    def tracking_error_rms_um(self) -> float:
        """RMS of position_ref_um - position_um over everything logged (µm)."""
        return math.sqrt(self.acc[SUM_E2] / self.acc[N_E]) if self.acc[N_E] else float("nan")

    @property
    def max_abs_err_um(self) -> float:
        return float(self.acc[MAX_E]) if self.acc[N_E] else float("nan")

    @property
    def mean_friction_N(self) -> float:
        return float(self.acc[SUM_F] / self.acc[N_F]) if self.acc[N_F] else float("nan")

    @property
    def mean_abs_friction_N(self) -> float:
        """Mean |friction| (N): the sliding friction level whatever the direction."""
        return float(self.acc[SUM_ABS_F] / self.acc[N_F]) if self.acc[N_F] else float("nan")

    @property
    def mean_mu(self) -> float:
        """Mean friction / (normal_1 + normal_2) over the samples where it is defined (NaN if none)."""
        return float(self.acc[SUM_MU] / self.acc[N_MU]) if self.acc[N_MU] else float("nan")

    @property
    def n_valve_saturated(self) -> int:
        return int(self.acc[N_SAT])


__all__ = ["BlockFigures", "warm_up"]
