"""The 25 Hz log's compiled kernels (numba, cached beside the source, without the GIL: the log's writer
thread runs beside them): the block means of :class:`rig.log.decimate.MatrixBlockMean`. Imported on first
use by that class, so that reading a log needs no numba."""

from __future__ import annotations

import numpy as np
from rig.jitstart import kernel


@kernel(nogil=True)
def _leaf_sum(a, lo, n):
    """numpy's ``pairwise_sum`` for n <= 128 values: eight running sums, then the rest one by one."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    end = n - (n % 8)
    while i < end:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@kernel(nogil=True)
def pairwise_sum(a, lo, n):
    """Sum of ``a[lo:lo + n]`` in numpy's order for contiguous float64 (its ``pairwise_sum``: blocks of up
    to 128 values summed by :func:`_leaf_sum`, longer runs split in two halves whose sums are added, left
    + right), so a mean taken here has numpy's bits. numpy recurses; this walks the same tree with a
    stack (numba caches no recursive function)."""
    if n <= 128:
        return _leaf_sum(a, lo, n)
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    state = np.zeros(64, np.int64)
    vals = np.empty(64)
    sp, vp = 1, 0
    los[0], ns[0] = lo, n
    while sp > 0:
        t = sp - 1
        h = ns[t] // 2
        h -= h % 8
        if ns[t] <= 128:
            vals[vp] = _leaf_sum(a, los[t], ns[t])
            vp += 1
            sp -= 1
        elif state[t] == 0:  # the left half first
            state[t] = 1
            los[sp], ns[sp], state[sp] = los[t], h, 0
            sp += 1
        elif state[t] == 1:  # then the right
            state[t] = 2
            los[sp], ns[sp], state[sp] = los[t] + h, ns[t] - h, 0
            sp += 1
        else:  # both done: left + right
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
            sp -= 1
    return vals[0]


@kernel(nogil=True)
def block_means(m, grid, off, scale, carry, n_carry, n, out):
    """One block of :class:`MatrixBlockMean`: rows ``grid`` of ``m`` put on their grid in place
    (``rint((x - off) / scale) * scale + off``), then the means of the complete groups of ``n`` of
    ``carry[:, :n_carry]`` followed by ``m`` into ``out``; the rest goes to ``carry``.
    Returns (groups, samples carried)."""
    rows, size = m.shape
    total = n_carry + size
    k = total // n
    rest = total - k * n
    tmp = np.empty(max(n, rest))
    for r in range(rows):
        if grid[r]:
            for i in range(size):
                m[r, i] = np.rint((m[r, i] - off[r]) / scale[r]) * scale[r] + off[r]
        for j in range(k):
            for i in range(n):
                p = j * n + i
                tmp[i] = carry[r, p] if p < n_carry else m[r, p - n_carry]
            out[r, j] = pairwise_sum(tmp, 0, n) / n
        for i in range(rest):
            p = k * n + i
            tmp[i] = carry[r, p] if p < n_carry else m[r, p - n_carry]
        for i in range(rest):
            carry[r, i] = tmp[i]
    return k, rest


@kernel(nogil=True)
def flush_means(carry, n_carry, out):
    for r in range(carry.shape[0]):
        out[r, 0] = pairwise_sum(carry[r], 0, n_carry) / n_carry
