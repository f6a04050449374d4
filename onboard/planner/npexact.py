"""Compiled twins of the numpy routines the planner's set-up and safety check use, rounding
exactly as numpy 1.26 does, so that moving that code into numba changes no result.

Each function follows the algorithm of its numpy original (``tests/test_planner_kernels.py``
compares them bit for bit on random inputs):

- ``np_sum``: ``np.sum`` of a 1-D array, numpy's pairwise summation (8 accumulators in blocks
  of up to 128, halves above);
- ``norm3``: ``np.linalg.norm`` of a 3-vector, and of each row of an (K, 3) array with
  ``axis=1``: ``sqrt((x^2 + y^2) + z^2)``, summed in index order;
- ``np_linspace``: ``np.linspace(start, stop, num)``: ``i * step + start``, the last value
  ``stop`` itself;
- ``np_arange``: ``np.arange(start, stop, step)`` with floats: ``ceil((stop - start) / step)``
  values ``start + i * ((start + step) - start)``;
- ``np_interp``: ``np.interp(x, xp, fp)`` for non-decreasing ``xp`` and no NaN: the interval
  is the last ``j`` with ``xp[j] <= x``, the value ``slope * (x - xp[j]) + fp[j]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_PW_BLOCK = 128  # numpy's PW_BLOCKSIZE


@njit(cache=True, nogil=True)
def _pairwise_block(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise sum of a[lo:lo + n], n <= 128 (no further split)."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0 = a[lo]
    r1 = a[lo + 1]
    r2 = a[lo + 2]
    r3 = a[lo + 3]
    r4 = a[lo + 4]
    r5 = a[lo + 5]
    r6 = a[lo + 6]
    r7 = a[lo + 7]
    i = 8
    while i < n - (n % 8):
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


@njit(cache=True, nogil=True)
def np_sum(a: np.ndarray) -> float:
    """``float(np.sum(a))`` of a 1-D float64 array."""
    n = a.shape[0]
    if n <= _PW_BLOCK:
        return _pairwise_block(a, 0, n)
    # numpy recurses: sum(lo, n) = sum(lo, n2) + sum(lo + n2, n - n2), n2 = n // 2 rounded down
    # to a multiple of 8; the same tree, walked with explicit stacks (depth < 64)
    f_lo = np.empty(64, dtype=np.int64)
    f_n = np.empty(64, dtype=np.int64)
    f_state = np.empty(64, dtype=np.int64)
    vals = np.empty(64)
    top = 0
    nv = 0
    f_lo[0] = 0
    f_n[0] = n
    f_state[0] = 0
    while top >= 0:
        lo = f_lo[top]
        m = f_n[top]
        if m <= _PW_BLOCK:
            vals[nv] = _pairwise_block(a, lo, m)
            nv += 1
            top -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        st = f_state[top]
        if st == 0:
            f_state[top] = 1
            top += 1
            f_lo[top] = lo
            f_n[top] = n2
            f_state[top] = 0
        elif st == 1:
            f_state[top] = 2
            top += 1
            f_lo[top] = lo + n2
            f_n[top] = m - n2
            f_state[top] = 0
        else:
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]
            top -= 1
    return vals[0]


@njit(cache=True, nogil=True)
def norm3(x: float, y: float, z: float) -> float:
    """``np.linalg.norm([x, y, z])`` (also each row of ``np.linalg.norm(a, axis=1)``)."""
    return math.sqrt((x * x + y * y) + z * z)


@njit(cache=True, nogil=True)
def np_linspace(start: float, stop: float, num: int) -> np.ndarray:
    """``np.linspace(start, stop, num)`` (endpoint included), num >= 1."""
    out = np.empty(num)
    div = num - 1
    if div <= 0:
        out[0] = start
        return out
    delta = stop - start
    step = delta / div
    if step == 0.0:
        for i in range(num):
            out[i] = (i / div) * delta + start
    else:
        for i in range(num):
            out[i] = i * step + start
    out[num - 1] = stop
    return out


@njit(cache=True, nogil=True)
def np_arange(start: float, stop: float, step: float) -> np.ndarray:
    """``np.arange(start, stop, step)`` with float arguments, step > 0."""
    n = int(math.ceil((stop - start) / step))
    if n <= 0:
        return np.empty(0)
    out = np.empty(n)
    out[0] = start
    if n > 1:
        second = start + step
        out[1] = second
        delta = second - start
        for i in range(2, n):
            out[i] = start + i * delta
    return out


@njit(cache=True, nogil=True)
def interp_at(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """``np.interp`` at one point; xp non-decreasing (K >= 1), no NaN."""
    n = xp.shape[0]
    if n == 1:
        return fp[0]
    if x > xp[n - 1]:
        return fp[n - 1]
    if x < xp[0]:
        return fp[0]
    # the last j with xp[j] <= x (numpy's binary search finds the same one)
    lo = 0
    hi = n
    while lo < hi:
        mid = lo + ((hi - lo) >> 1)
        if x >= xp[mid]:
            lo = mid + 1
        else:
            hi = mid
    j = lo - 1
    if j == n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    res = slope * (x - xp[j]) + fp[j]
    if math.isnan(res):
        res = slope * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(res) and fp[j] == fp[j + 1]:
            res = fp[j]
    return res


@njit(cache=True, nogil=True)
def np_interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp(x, xp, fp)``; xp non-decreasing, no NaN."""
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        out[i] = interp_at(x[i], xp, fp)
    return out
