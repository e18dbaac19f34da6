"""Kernels of the fibre lattice: node states (the distorted lattice of cell centres and wall
thicknesses) and the stationary renewal chains that place fibre ends along L and ray-cell
ends along R (docs/methods.md#fibre-lattice)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from ..rng import normal
from ..rng import uniform
from ._constants import CTRL, JITTER, PITCH, T0, WALLVAR

# --------------------------------------------------------------------------
# Lattice nodes
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _spline(L, spacing):
    """Control index k and Catmull-Rom weights of the control values k-1 .. k+2 at L."""
    x = L / spacing
    k = math.floor(x)
    f = x - k
    f2 = f * f
    f3 = f2 * f
    w0 = 0.5 * (-f + 2.0 * f2 - f3)
    w1 = 0.5 * (2.0 - 5.0 * f2 + 3.0 * f3)
    w2 = 0.5 * (f + 4.0 * f2 - 3.0 * f3)
    w3 = 0.5 * (f3 - f2)
    return np.int64(k), w0, w1, w2, w3


@njit(inline="always", cache=True, error_model="numpy")
def _controls(seed, n, m, k, out):
    """The three control values (R, T, wall) of node (n, m) at control slice k, in [-1, 1)."""
    out[0] = 2.0 * uniform(seed, _rng.NODE_R, n, m, k) - 1.0
    out[1] = 2.0 * uniform(seed, _rng.NODE_T, n, m, k) - 1.0
    out[2] = 2.0 * uniform(seed, _rng.NODE_WALL, n, m, k) - 1.0


@njit(inline="always", cache=True, error_model="numpy")
def _node_from(M, n, m, w0, w1, w2, w3, C0, C1, C2, C3):
    """Node position and inset from the control values C0..C3 (k-1 .. k+2) and weights."""
    c = M[PITCH]
    r = 0.0
    t = 0.0
    w = 0.0
    for q in range(4):
        wq = w0 if q == 0 else (w1 if q == 1 else (w2 if q == 2 else w3))
        C = C0 if q == 0 else (C1 if q == 1 else (C2 if q == 2 else C3))
        r += wq * C[0]
        t += wq * C[1]
        w += wq * C[2]
    return n * c + M[JITTER] * c * r, m * c + M[JITTER] * c * t, M[T0] * (1.0 + M[WALLVAR] * w)


@njit(cache=True, nogil=True, error_model="numpy")
def node_state(seed, M, n, m, L):
    """Jittered position (R, T) [µm] and wall inset t [µm] of node (n, m) at L.

    Control values every ``M[CTRL]`` µm along L are interpolated with a local
    Catmull-Rom spline, so a node at any L needs only four control values.
    """
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    C = np.empty((4, 3))
    for q in range(4):
        _controls(seed, n, m, k + q - 1, C[q])
    return _node_from(M, n, m, w0, w1, w2, w3, C[0], C[1], C[2], C[3])


@njit(cache=True, nogil=True, error_model="numpy")
def node_states(seed, M, L, n_lo, m_lo, NR, NT, Nt, CV, CF, cn, ck):
    """:func:`node_state` of the window's nodes, their control values kept in ``CV``.

    CV[n - cn, m - m_lo, k - ck] holds the control values of node (n, m) at
    control slice k once CF (same index) is 1; the slices of one block share
    them (control slices are tens of µm apart), so each is hashed once.
    """
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    nn, nm = NR.shape
    for i in range(nn):
        a = np.uint64(n_lo + i - cn)
        for j in range(nm):
            for q in range(4):
                z = np.uint64(k + q - 1 - ck)
                if CF[a, j, z] == 0:
                    _controls(seed, n_lo + i, m_lo + j, k + q - 1, CV[a, j, z])
                    CF[a, j, z] = 1
            NR[i, j], NT[i, j], Nt[i, j] = _node_from(
                M, n_lo + i, m_lo + j, w0, w1, w2, w3,
                CV[a, j, k - 1 - ck], CV[a, j, k - ck], CV[a, j, k + 1 - ck], CV[a, j, k + 2 - ck])


@njit(inline="always", cache=True, error_model="numpy")
def is_centre(n, m):
    """Fibre centres: every second node column, alternate columns shifted by one node."""
    return m % 2 == 0 and (n - m // 2) % 2 == 0


# --------------------------------------------------------------------------
# Stationary 1-D renewal chains (fibre ends along L, ray cells along R)
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _boundary(seed, kind, a, b, q, phase, mean, sd, emax):
    e = normal(seed, kind, a, b, q) * sd * 0.7071067811865476
    if e > emax:
        e = emax
    elif e < -emax:
        e = -emax
    return q * mean + phase + e


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def chain_interval(x, seed, kind, a, b, phase, mean, sd, min_len):
    """The cell (lo, hi) of a jittered-lattice chain that contains x.

    Boundaries sit at q·mean + phase + e_q with e_q ~ N(0, sd²/2) clipped to
    ±(mean − min_len)/2, so lengths are ≈ N(mean, sd²), never below min_len,
    and finding the cell at any x costs O(1) (no walk from an origin).
    """
    emax = max(0.0, 0.5 * (mean - min_len))
    q0 = np.int64(math.floor((x - phase) / mean))
    b0 = _boundary(seed, kind, a, b, q0, phase, mean, sd, emax)
    if x < b0:
        return _boundary(seed, kind, a, b, q0 - 1, phase, mean, sd, emax), b0
    b1 = _boundary(seed, kind, a, b, q0 + 1, phase, mean, sd, emax)
    if x < b1:
        return b0, b1
    return b1, _boundary(seed, kind, a, b, q0 + 2, phase, mean, sd, emax)
