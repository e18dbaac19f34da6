"""The Newton step of the Cauchy maximum-likelihood fit, compiled (Numba).

:func:`pipeline.analysis.cauchy_newton` fits every bootstrap resample of a summary (thousands of
fits a pool); in NumPy each Newton step was seven array sums and their temporaries, most of the
time of `twray trace` and a seventh of a study's.  Here one call gives the step, with the same
numbers bit for bit:

* a sum is NumPy's pairwise summation (blocks of eight partial sums up to 128 terms, halves
  rounded to multiples of eight above), which is what ``np.sum`` does on a contiguous array;
* each term is written in the order NumPy evaluated it (``-2.0 * d * w`` is ``(-2.0 * d) * w``);
* the 2 × 2 system is solved by ``np.linalg.solve`` and the slope is ``np.dot``, which Numba
  hands to the same LAPACK and BLAS as NumPy.

The log-likelihood stays in NumPy (its caller): NumPy's vectorised ``log`` and the C library's
differ in the last bit for about one value in 10⁴, and the line search compares likelihoods.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_BLOCK = 128  # NumPy's PW_BLOCKSIZE


@njit(cache=True, nogil=True)
def _block(a, lo, n):
    """NumPy's pairwise sum of a[lo:lo + n] for n <= 128: eight partial sums."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    whole = n - n % 8
    while i < whole:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def pairwise_sum(a):
    """``np.sum(a)`` of a contiguous 1-D float64 array, bit for bit: NumPy halves a range of more
    than 128 terms (the first half a multiple of eight) and adds the halves' sums.  Written with a
    stack: a recursive kernel read back from Numba's cache can crash."""
    n = a.size
    if n <= _BLOCK:
        return _block(a, 0, n)
    # Post-order walk of the halving tree: (lo, n, visited) frames and the partial sums.
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    seen = np.zeros(64, np.bool_)
    sums = np.empty(64)
    top = 0
    vals = 0
    los[0], ns[0], seen[0] = 0, n, False
    while top >= 0:
        lo, m = los[top], ns[top]
        if m <= _BLOCK:
            sums[vals] = _block(a, lo, m)
            vals += 1
            top -= 1
        elif seen[top]:
            vals -= 1
            sums[vals - 1] = sums[vals - 1] + sums[vals]
            top -= 1
        else:
            seen[top] = True
            half = m // 2
            half -= half % 8
            # the right half is pushed first so that the left one is summed first
            los[top + 1], ns[top + 1], seen[top + 1] = lo + half, m - half, False
            los[top + 2], ns[top + 2], seen[top + 2] = lo, half, False
            top += 2
    return sums[0]


@njit(cache=True, nogil=True)
def newton_step(x, loc, log_g, g2, work):
    """The Newton step in (θ0, log γ) of the Cauchy negative log-likelihood of ``x`` at (``loc``,
    ``log_g``), ``g2`` = exp(2 log γ), and its slope along the gradient: (step, slope, ok); not ok
    where the Hessian is singular or the step not finite or not a descent (the caller then descends
    along the gradient, in ``work[5, :2]``, scaled by the Hessian's diagonal, ``|h|`` in
    ``work[5, 2:4]``).  ``work``: (6, max(n, 4)) scratch."""
    n = x.size
    t_g0, t_g1, t_h00, t_h01, t_h11 = work[0, :n], work[1, :n], work[2, :n], work[3, :n], work[4, :n]
    for i in range(n):
        d = x[i] - loc
        q = d * d + g2
        w = 1.0 / q
        w2 = w * w
        t_g0[i] = (-2.0 * d) * w
        t_g1[i] = (2.0 * g2) * w
        t_h00[i] = (2.0 * (g2 - d * d)) * w2
        t_h01[i] = ((4.0 * d) * g2) * w2
        t_h11[i] = (((4.0 * g2) * d) * d) * w2
    grad = np.empty(2)
    grad[0] = pairwise_sum(t_g0)
    grad[1] = pairwise_sum(t_g1) - n
    h01 = pairwise_sum(t_h01)
    h = np.empty((2, 2))
    h[0, 0] = pairwise_sum(t_h00)
    h[0, 1] = h01
    h[1, 0] = h01
    h[1, 1] = pairwise_sum(t_h11)
    work[5, 0] = grad[0]
    work[5, 1] = grad[1]
    work[5, 2] = abs(h[0, 0])
    work[5, 3] = abs(h[1, 1])
    try:
        step = -np.linalg.solve(h, grad)
    except Exception:  # singular, or not finite: as np.linalg.solve's LinAlgError
        return np.zeros(2), 0.0, False
    if not (np.isfinite(step[0]) and np.isfinite(step[1])):
        return step, 0.0, False
    slope = np.dot(step, grad)
    return step, slope, not slope >= 0.0
