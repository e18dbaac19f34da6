"""Kernels of the ray cells: ray columns, groups along L and the ray-cell phase
(docs/methods.md#ray-cells)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from ..rng import normal
from ..rng import uniform
from ._constants import POLYMER, RAY_MIN_GAP, RAY_PERIOD, RGROUP, RGROUP_SD, RHEIGHT, RJIT, RLEN, RLEN_SD, RSER, RSPACE, RWIDTH, SCALE, T0, WALL
from ._lattice import chain_interval

# --------------------------------------------------------------------------
# Ray columns and groups
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def ray_row(seed, M, k):
    """Node row (even T index) of ray column k."""
    x = k * M[RSPACE] + (2.0 * uniform(seed, _rng.RAY_COLUMN, k, 0, 0) - 1.0) * M[RJIT]
    return np.int64(2 * round(0.5 * x))


@njit(cache=True, nogil=True, error_model="numpy")
def near_ray(seed, M, m, dist):
    """True when node row m is within ``dist`` rows of a ray column.

    Ray columns are a property of the lattice: they are where they are whether or
    not ray cells are drawn (``M[RAYS]``), so that switching ray cells off changes
    the ray tissue and its squeeze alone, and leaves the vessels (placed away from
    ray columns) and the fibres' distortion where they were.
    """
    kc = np.int64(round(m / M[RSPACE]))
    for k in range(kc - 1, kc + 2):
        if abs(m - ray_row(seed, M, k)) < dist:
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def group_span(seed, M, k, g):
    """(L0, L1) of the ray group of column k in slot g.

    Each slot of RAY_PERIOD cell heights holds one group of N(mean, sd)
    cells at a random offset, leaving at least RAY_MIN_GAP cells of gap.
    """
    h = M[RHEIGHT]
    period = RAY_PERIOD * h
    phase = uniform(seed, _rng.RAY_GROUP, k, 1, 0) * period
    ncell = round(M[RGROUP] + M[RGROUP_SD] * normal(seed, _rng.RAY_GROUP, k, 3, g))
    lo = max(1.0, min(5.0, round(M[RGROUP])))
    ncell = min(max(ncell, lo), RAY_PERIOD - RAY_MIN_GAP)
    off = math.floor(uniform(seed, _rng.RAY_GROUP, k, 4, g) * (RAY_PERIOD - RAY_MIN_GAP - ncell + 1))
    L0 = g * period + phase + off * h
    return L0, L0 + ncell * h


@njit(inline="always", cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def ray_slot(seed, M, k, L):
    """The slot of column k's ray groups that holds L."""
    period = RAY_PERIOD * M[RHEIGHT]
    phase = uniform(seed, _rng.RAY_GROUP, k, 1, 0) * period
    return np.int64(math.floor((L - phase) / period))


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def ray_group(seed, M, k, L):
    """Ray group of column k around L: (L0, L1, slot); L0 = nan when none (:func:`group_span`)."""
    g = ray_slot(seed, M, k, L)
    L0, L1 = group_span(seed, M, k, g)
    return group_at(L, L0, L1, g)


@njit(inline="always", cache=True, error_model="numpy")
def group_at(L, L0, L1, g):
    """:func:`ray_group`'s answer from slot g's span (L0, L1)."""
    if L < L0 or L > L1:
        return math.nan, math.nan, g
    return L0, L1, g


@njit(inline="always", cache=True, error_model="numpy")
def ray_band_width(M):
    return M[RSER] * (M[RWIDTH] + 2.0 * M[T0])


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def ray_slice_tables(seed, M, L, rays, nr, RC):
    """What the ray cells of the active ray rows share on the slice at L.

    RC[r, s] for sub-column s of row r: (open, Tc, aT, dL², layer id, row id,
    chain phase), where ``open`` is 0 when the slice misses the sub-column's
    cells or they have no lumen, Tc and aT are the lumen's centre and
    semi-axis along T, and dL the slice's offset from the lumen centre over
    its semi-axis along L; RC[r, 0, 7] is the sub-columns' width along T.
    Everything here depends on L, not on the point.
    """
    ns = np.int64(M[RSER])
    h = M[RHEIGHT]
    mean = M[RLEN]
    for r in range(nr):
        t_r = rays[r, 0]
        b = rays[r, 1]
        L0 = rays[r, 2]
        L1 = rays[r, 3]
        k = np.int64(rays[r, 4])
        g = np.int64(rays[r, 5])
        sw = 2.0 * b / ns
        RC[r, 0, 7] = sw
        for s in range(ns):
            RC[r, s, 0] = 0.0
            Tc = t_r - b + (s + 0.5) * sw
            off = 0.5 * h * (s % 2)  # biseriate: the second column is offset by half a cell
            ell = np.int64(math.floor((L - L0 - off) / h))
            if ell < 0 or L0 + off + (ell + 1) * h > L1 + 1e-9:
                continue
            aT = 0.5 * sw - M[T0]
            aL = 0.5 * h - M[T0]
            if aT <= 0.0 or aL <= 0.0:
                continue
            Lc = L0 + off + (ell + 0.5) * h
            dL = (L - Lc) / aL
            ida = k * 8 + s
            RC[r, s, 0] = 1.0
            RC[r, s, 1] = Tc
            RC[r, s, 2] = aT
            RC[r, s, 3] = dL * dL
            RC[r, s, 4] = ida
            RC[r, s, 5] = g * 64 + ell
            RC[r, s, 6] = uniform(seed, _rng.RAY_CELL_PHASE, ida, 0, 0) * mean + 0.5 * mean * (ell % 2)


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def ray_cell_phase(seed, M, pR, pT, r, rays, RC, memo):
    """Phase at (pR, pT) inside the band of active ray row r (tables: :func:`ray_slice_tables`).

    memo : float64[8, 4], per sub-column s the last radial cell found, (layer
        id, row id, lo, hi); a point of the same layer and row inside [lo, hi)
        reuses it (the cell containing a point is unique, so the result is the
        same).  Start it with NaNs.
    """
    ns = np.int64(M[RSER])
    s0 = np.int64(math.floor((pT - (rays[r, 0] - rays[r, 1])) / RC[r, 0, 7]))
    s = np.uint64(min(max(s0, 0), ns - 1))
    if RC[r, s, 0] == 0.0:
        return WALL
    Tc = RC[r, s, 1]
    aT = RC[r, s, 2]
    if abs(pT - Tc) >= aT:  # then (dT)² >= 1 exactly
        return WALL
    dT = (pT - Tc) / aT
    if dT * dT + RC[r, s, 3] >= 1.0:
        return WALL
    # Radial cells along R; successive layers staggered by half a cell length.
    mem = memo[s]
    if mem[0] == RC[r, s, 4] and mem[1] == RC[r, s, 5] and mem[2] <= pR < mem[3]:
        lo = mem[2]
        hi = mem[3]
    else:
        mean = M[RLEN]
        lo, hi = chain_interval(pR, seed, _rng.RAY_CELL_END, np.int64(RC[r, s, 4]),
                                np.int64(RC[r, s, 5]), RC[r, s, 6], mean, M[RLEN_SD], 0.4 * mean)
        mem[0] = RC[r, s, 4]
        mem[1] = RC[r, s, 5]
        mem[2] = lo
        mem[3] = hi
    end_wall = 0.5 * M[SCALE]
    if pR - lo < end_wall or hi - pR < end_wall:
        return WALL
    return POLYMER
