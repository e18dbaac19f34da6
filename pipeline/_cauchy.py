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


@njit(cache=True, nogil=True, inline="always")
def _block(a, lo, n):
    """NumPy's pairwise sum of a[lo:lo + n] for n <= 128: eight partial sums."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    whole = n - n % 8
    for j in range(lo + 8, lo + whole, 8):
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for j in range(lo + whole, lo + n):
        res += a[j]
    return res


@njit(cache=True, nogil=True, inline="always")
def _leaf_terms(x, lo, n, loc, g2, buf, out):
    """The five sums of the Newton step's terms over the leaf x[lo:lo + n] (n <= 128), each NumPy's
    pairwise sum of that leaf, into ``out``; ``buf``: (5, 128) scratch."""
    b0, b1, b2, b3, b4 = buf[0], buf[1], buf[2], buf[3], buf[4]
    c1 = 2.0 * g2
    c4 = 4.0 * g2
    for k in range(n):
        d = x[lo + k] - loc
        w = 1.0 / (d * d + g2)
        w2 = w * w
        b0[k] = (-2.0 * d) * w
        b1[k] = c1 * w
        b2[k] = (2.0 * (g2 - d * d)) * w2
        b3[k] = ((4.0 * d) * g2) * w2
        b4[k] = ((c4 * d) * d) * w2
    out[0] = _block(b0, 0, n)
    out[1] = _block(b1, 0, n)
    out[2] = _block(b2, 0, n)
    out[3] = _block(b3, 0, n)
    out[4] = _block(b4, 0, n)


@njit(cache=True, nogil=True)
def _tree(a, x, loc, g2, buf, five):
    """NumPy's pairwise sum over n = len(a or x) terms: of ``a`` (``five`` None), or of the Newton
    step's five terms of ``x`` into ``five``.  NumPy halves a range of more than 128 terms (the first
    half a multiple of eight) and adds the halves' sums; written with a stack, since a recursive
    kernel read back from Numba's cache can crash."""
    n = x.size if five is not None else a.size
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    seen = np.zeros(64, np.bool_)
    sums = np.empty((64, 5))
    leaf = np.empty(5)
    top = 0
    vals = 0
    los[0], ns[0], seen[0] = 0, n, False
    while top >= 0:
        lo, m = los[top], ns[top]
        if m <= _BLOCK:
            if five is not None:
                _leaf_terms(x, lo, m, loc, g2, buf, leaf)
                for k in range(5):
                    sums[vals, k] = leaf[k]
            else:
                sums[vals, 0] = _block(a, lo, m)
            vals += 1
            top -= 1
        elif seen[top]:
            vals -= 1
            for k in range(5):
                sums[vals - 1, k] = sums[vals - 1, k] + sums[vals, k]
            top -= 1
        else:
            seen[top] = True
            half = m // 2
            half -= half % 8
            # the right half is pushed first so that the left one is summed first
            los[top + 1], ns[top + 1], seen[top + 1] = lo + half, m - half, False
            los[top + 2], ns[top + 2], seen[top + 2] = lo, half, False
            top += 2
    if five is not None:
        for k in range(5):
            five[k] = sums[0, k]
    return sums[0, 0]


@njit(cache=True, nogil=True)
def pairwise_sum(a):
    """``np.sum(a)`` of a contiguous 1-D float64 array, bit for bit."""
    return _tree(a, a, 0.0, 0.0, np.empty((5, _BLOCK)), None)


@njit(cache=True, nogil=True)
def newton_step(x, loc, log_g, g2, work):
    """The Newton step in (θ0, log γ) of the Cauchy negative log-likelihood of ``x`` at (``loc``,
    ``log_g``), ``g2`` = exp(2 log γ), and its slope along the gradient: (step, slope, ok); not ok
    where the Hessian is singular or the step not finite or not a descent (the caller then descends
    along the gradient, in ``work[5, :2]``, scaled by the Hessian's diagonal, ``|h|`` in
    ``work[5, 2:4]``).  ``work``: (6, 128) scratch."""
    n = x.size
    sums = np.empty(5)
    _tree(x, x, loc, g2, work, sums)
    grad = np.empty(2)
    grad[0] = sums[0]
    grad[1] = sums[1] - n
    h = np.empty((2, 2))
    h[0, 0] = sums[2]
    h[0, 1] = sums[3]
    h[1, 0] = sums[3]
    h[1, 1] = sums[4]
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
