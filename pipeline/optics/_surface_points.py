"""One point of a surface medium for the exact march (docs/methods.md#the-exact-method): its phase
and rows, and the normal of one of its primitives, for generated wood or a reference lattice,
chosen by the context's type when the march compiles, so that one kernel traces both."""

import numpy as np
from numba import njit, types
from numba.extending import overload

from ..microstructure.surface import evaluate_at
from ._lattice_rows import CONTEXT_LEN, lattice_normal, lattice_rows


def _is_lattice(ctx) -> bool:
    return isinstance(ctx, types.BaseTuple) and len(ctx) == CONTEXT_LEN


def surface_at(R, T, L, lq, ctx, P, cache, want):
    """(phase, number of rows) of the medium of ``ctx`` at (R, T, L), its rows in ``P``: generated
    wood (:func:`~pipeline.microstructure.surface.evaluate_at`) or a reference lattice
    (:func:`~pipeline.optics._lattice_rows.lattice_rows`).  Chosen by the context's type when the
    march compiles, so one kernel traces both."""
    raise NotImplementedError("surface_at runs inside the march's Numba kernel only")


@overload(surface_at, inline="always")
def _surface_at(R, T, L, lq, ctx, P, cache, want):
    if _is_lattice(ctx):
        return lambda R, T, L, lq, ctx, P, cache, want: lattice_rows(R, T, ctx, P)
    return lambda R, T, L, lq, ctx, P, cache, want: evaluate_at(R, T, L, lq, ctx, P, cache, want)


def surface_normal(base, lq, ctx, P, key, cache, h_grad, nrm, e):
    """(found, evaluations): the unit normal of primitive ``key`` at ``base`` into ``nrm``.  The
    wood's is the central-difference gradient of its g (step ``h_grad``); a lattice's, its
    circle's or face's own."""
    raise NotImplementedError("surface_normal runs inside the march's Numba kernel only")


@overload(surface_normal)
def _surface_normal(base, lq, ctx, P, key, cache, h_grad, nrm, e):
    if _is_lattice(ctx):
        return lambda base, lq, ctx, P, key, cache, h_grad, nrm, e: (lattice_normal(base[0], base[1], ctx, key, nrm),
                                                                     0)
    return lambda base, lq, ctx, P, key, cache, h_grad, nrm, e: _gradient(base, lq, ctx, P, key, cache, h_grad,
                                                                          nrm, e)


# Inlined into _gradient (six differences a normal): a call copied the context and cache each time.
@njit(inline="always", cache=True, nogil=True)
def _g_of(X, d, s, lq, ctx, P, key, cache):
    """Signed function of primitive ``key`` at X + s·d (nan when it is not listed there)."""
    ph, n = surface_at(X[0] + s * d[0], X[1] + s * d[1], X[2] + s * d[2], lq, ctx, P, cache, key)
    for i in range(n):
        if (P[i, 0] == key[0] and P[i, 1] == key[1] and P[i, 2] == key[2] and P[i, 3] == key[3]
                and P[i, 4] == key[4]):
            return P[i, 5]
    return np.nan


@njit(cache=True, nogil=True)
def _gradient(base, lq, ctx, P, key, cache, h_grad, nrm, e):
    """(found, evaluations): the central-difference gradient of primitive ``key``'s g at ``base``
    (one-sided where the primitive is not listed on a side), normalised into ``nrm``."""
    g0 = np.nan  # g at base: only for a one-sided difference
    k = 6
    ok = True
    for q in range(3):
        e[0] = 0.0
        e[1] = 0.0
        e[2] = 0.0
        e[q] = 1.0
        gp = _g_of(base, e, h_grad, lq, ctx, P, key, cache)
        gm = _g_of(base, e, -h_grad, lq, ctx, P, key, cache)
        nrm[q] = (gp - gm) / (2.0 * h_grad)
        if not (nrm[q] == nrm[q]):  # a side where the primitive is not listed: one-sided
            if not (g0 == g0):
                g0 = _g_of(base, e, 0.0, lq, ctx, P, key, cache)
                k += 1
            nrm[q] = (gp - g0) / h_grad if gp == gp else (g0 - gm) / h_grad
        if not (nrm[q] == nrm[q]):
            ok = False
    return ok, k
