"""The 25 Hz log's decimation: block means over each decimation interval (one function for
the MCAP writer's ``/log25`` and :meth:`rig.session.memory.MemoryLog.trial_data`).

The rig's loop samples at ``f_s`` = 1 kHz behind 100 Hz analog filters (first order); the
paper logged at 25 Hz. Taking every 40th sample would fold everything above 12.5 Hz -- the
sensor noise the 100 Hz filters pass, the 500 Hz dither, the loop's fluctuations -- into
0-12.5 Hz. Instead each logged sample is the **mean of the N = f_s / f_log ticks of its
interval** (a boxcar FIR followed by down-sampling, what a data logger's averaging input does),
time-stamped at the mean of the interval's tick times (its centre, so the boxcar's group
delay of (N - 1) / (2 f_s) = 19.5 ms is not a lag on the log's clock).

Response of the boxcar (amplitude, at frequency f):

    |H(f)| = |sin(pi f N / f_s) / (N sin(pi f / f_s))|

* 0 at every multiple of f_log = 25 Hz: exactly the frequencies that would alias onto DC
  (the 500 Hz dither is removed entirely), and the bands around them are attenuated;
* 0.90 (-0.9 dB) at 6.25 Hz, 0.64 (-3.9 dB) at the 12.5 Hz Nyquist frequency of the log;
  the 1 µm/s-10 µm/s step transients of the paper (rise 0.1-0.5 s, f < 3 Hz) pass within 2 %;
* white noise of variance sigma^2 (independent per tick) leaves with sigma^2 / N; noise
  already low-passed at 100 Hz (correlation time 1.6 ms) with about sigma^2 / 9.6.

A block is logged when its N ticks are complete (counted from the trial's first tick);
:class:`BlockMean` carries a partial block across write calls, and ``flush`` logs the last,
partial block as the mean of the ticks it has.
"""

from __future__ import annotations


import numpy as np


def boxcar_response(f_hz, n: int, rate_hz: float = 1000.0):
    """|H(f)| of the ``n``-tick block mean at loop rate ``rate_hz`` (the formula above)."""
    f = np.asarray(f_hz, dtype=float)
    x = np.pi * f / rate_hz
    with np.errstate(invalid="ignore", divide="ignore"):
        h = np.abs(np.sin(n * x) / (n * np.sin(x)))
    return np.where(np.isclose(np.sin(x), 0.0), 1.0, h)


def decimation_factor(loop_rate_hz: float, log_rate_hz: float) -> int:
    """Ticks per logged sample: ``round(loop_rate / log_rate)``, at least 1."""
    return max(1, int(round(float(loop_rate_hz) / float(log_rate_hz))))


def block_mean(columns: dict[str, np.ndarray], n: int, *, partial: bool = True) -> dict[str, np.ndarray]:
    """Block means of every column over consecutive groups of ``n`` samples from the first;
    ``t_s`` becomes the mean time of each group (its centre). ``partial``: the last,
    incomplete group is kept as the mean of what it has. A column may be a matrix: its
    samples run along the last axis (the writer stacks its columns so, one numpy pass)."""
    out = {}
    for k, v in columns.items():
        v = np.asarray(v, dtype=np.float64)
        size = v.shape[-1]
        m = size // n
        full = v[..., : m * n].reshape(v.shape[:-1] + (m, n)).mean(axis=-1)
        if partial and size > m * n:
            full = np.concatenate((full, v[..., m * n:].mean(axis=-1, keepdims=True)), axis=-1)
        out[k] = full
    return out


class BlockMean:
    """Streaming :func:`block_mean`: ``push(block)`` returns the complete groups so far (the
    remainder is carried), ``flush()`` the last partial group (or None). Samples run along the
    last axis of each column (vectors, or matrices of stacked columns)."""

    def __init__(self, n: int):
        self.n = int(n)
        self._rest: dict[str, np.ndarray] | None = None

    def push(self, block: dict[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        if self._rest is not None:
            block = {k: np.concatenate((self._rest[k], np.asarray(v, dtype=np.float64)), axis=-1)
                     for k, v in block.items()}
        size = next(iter(block.values())).shape[-1]
        m = (size // self.n) * self.n
        self._rest = {k: np.asarray(v[..., m:], dtype=np.float64).copy() for k, v in block.items()} \
            if m < size else None
        if m == 0:
            return None
        return block_mean({k: v[..., :m] for k, v in block.items()}, self.n, partial=False)

    def flush(self) -> dict[str, np.ndarray] | None:
        rest, self._rest = self._rest, None
        if rest is None or next(iter(rest.values())).shape[-1] == 0:
            return None
        return {k: v.mean(axis=-1, keepdims=True) for k, v in rest.items()}


def _kernels():
    """:mod:`rig.log.kernels`, imported on first use (reading a log needs no numba)."""
    from rig.log import kernels

    return kernels


class MatrixBlockMean:
    """:class:`BlockMean` of one matrix of stacked float64 rows (samples along axis 1), compiled: one
    pass per block without the GIL, each group's sum in numpy's own order, so the means are numpy's to
    the bit (``tests/unit/log/test_log_mcap.py``). Rows where ``grid`` is true are first put on their
    grid, ``rint((x - offset) / scale) * scale + offset`` (the device counts the /raw channel stores)."""

    def __init__(self, n: int, grid, offset, scale):
        self.n = int(n)
        self.grid = np.asarray(grid, dtype=np.bool_)
        self.offset = np.asarray(offset, dtype=np.float64)
        self.scale = np.asarray(scale, dtype=np.float64)
        self._carry = np.empty((self.grid.size, self.n))
        self._n_carry = 0

    def push(self, m: np.ndarray) -> np.ndarray | None:
        """The means of the groups completed by ``m`` (rows x samples; its grid rows are rounded in place)."""
        out = np.empty((m.shape[0], (self._n_carry + m.shape[1]) // self.n))
        k, self._n_carry = _kernels().block_means(m, self.grid, self.offset, self.scale, self._carry,
                                                  self._n_carry, self.n, out)
        return out if k else None

    def flush(self) -> np.ndarray | None:
        """The last, partial group's mean (None: nothing carried)."""
        if self._n_carry == 0:
            return None
        out = np.empty((self._carry.shape[0], 1))
        _kernels().flush_means(self._carry, self._n_carry, out)
        self._n_carry = 0
        return out


def warm_up() -> None:
    """Compile (or load from the cache) the kernels now."""
    mb = MatrixBlockMean(2, [True], [0.0], [1.0])
    mb.push(np.zeros((1, 3)))
    mb.flush()


__all__ = ["block_mean", "BlockMean", "MatrixBlockMean", "boxcar_response", "decimation_factor"]

