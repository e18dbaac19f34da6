"""Kernels of the distortion map: dipoles and the global bend, tabulated per tile on a grid,
and the pull-back of a point through it (docs/methods.md#distortion)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from ..rng import uniform
from ._constants import BEND_A, BEND_WL, DIST, GRID_PER_PITCH, LARGE_P, PITCH, SCALE, ST_DIPOLES, ST_TILES, TILE
from ._lattice import is_centre
from ._ray_cells import near_ray
from ._vessels import member_of, vessels_in_region

# --------------------------------------------------------------------------
# Distortion: dipoles and the global bend, tabulated per tile on a grid
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _sig(x):
    return 1.0 / (1.0 + math.exp(-x))


@njit(cache=True, nogil=True, error_model="numpy")
def _sig_diff(g, X0, k1, k2, rv, acut, D):
    """D[i] = σ(k1 a) − σ(k2 a) at a = (g[i] − X0)/rv where |a| ≤ acut, else 0; whether any |a| is."""
    hit = False
    for i in range(g.shape[0]):
        a = (g[i] - X0) / rv
        if abs(a) <= acut:
            D[i] = _sig(k1 * a) - _sig(k2 * a)
            hit = True
        else:
            D[i] = 0.0
    return hit


@njit(cache=True, nogil=True, error_model="numpy")
def _gauss(g, X0, w, rv, bcut, B):
    """B[i] = exp(−a²/(2 w²)) at a = (g[i] − X0)/rv where |a| ≤ bcut, else 0."""
    for i in range(g.shape[0]):
        a = (g[i] - X0) / rv
        B[i] = math.exp(-a * a / (2.0 * w * w)) if abs(a) <= bcut else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _add_separable(out, gR, gT, R0, T0_, DR, DT, anyR, anyT, k2, k3, k4, sign, rv, bcut, BR, BT, S):
    """Add one dipole (docs/methods.md#distortion) to the tile grid ``out`` (2, n, n), given its sigmoid
    differences along R and T (:func:`_sig_diff`, which depend on the dipole's position alone);
    ``S``: n scratch.

    d(a, b) = [σ(k1 a) − σ(k2 a)]·(k4/k2)·exp(−b²/(2 (k3/k2)²)), in reference
    voxels; u uses (a, b) = (R, T), v uses (T, R).  Separable, so the grid
    costs O(n) exponentials per dipole.
    """
    if not (anyR or anyT):
        return 0
    w = k3 / k2
    amp = sign * k4 / k2 * rv
    n = gR.shape[0]
    # Only the span of nonzero factors: adding a zero product leaves a sum that started at +0 as
    # it is, bit for bit, so the grid is the full outer product's.  The rows are added over
    # zero-based views so that the loops vectorise (each lane the scalar product and sum).
    if anyR:
        _gauss(gT, T0_, w, rv, bcut, BT)
        b0, b1 = _nonzero_span(BT)
        if b1 > b0:
            bt = BT[b0:b1]
            for i in range(n):
                if DR[i] != 0.0:
                    _axpy(out[0, i, b0:b1], DR[i] * amp, bt)
    if anyT:
        _gauss(gR, R0, w, rv, bcut, BR)
        t0, t1 = _nonzero_span(DT)
        if t1 > t0:
            dt = S[:t1 - t0]
            for j in range(t1 - t0):
                dt[j] = DT[t0 + j] * amp
            for i in range(n):
                if BR[i] != 0.0:
                    _axpy(out[1, i, t0:t1], BR[i], dt)
    return 1


@njit(inline="always", cache=True, error_model="numpy")
def _axpy(y, a, x):
    """y[j] += x[j]·a for every j (the product as written, then the sum)."""
    for j in range(y.shape[0]):
        y[j] += x[j] * a


@njit(cache=True, nogil=True, error_model="numpy")
def _add_dipole(out, gR, gT, R0, T0_, k1, k2, k3, k4, sign, rv, acut, bcut, work):
    """:func:`_add_separable` with the dipole's own sigmoid differences (``work``: 5 × n scratch)."""
    anyR = _sig_diff(gR, R0, k1, k2, rv, acut, work[0])
    anyT = _sig_diff(gT, T0_, k1, k2, rv, acut, work[1])
    return _add_separable(out, gR, gT, R0, T0_, work[0], work[1], anyR, anyT, k2, k3, k4, sign, rv, bcut,
                          work[2], work[3], work[4])


@njit(inline="always", cache=True, error_model="numpy")
def _nonzero_span(x):
    """(first, last + 1) index of the nonzero entries of ``x`` ((0, 0) if none)."""
    lo = 0
    while lo < x.shape[0] and x[lo] == 0.0:
        lo += 1
    hi = x.shape[0]
    while hi > lo and x[hi - 1] == 0.0:
        hi -= 1
    return lo, hi


@njit(cache=True, nogil=True, error_model="numpy")
def large_range(M, a, b):
    """(n_lo, n_hi, m_lo, m_hi): the nodes whose large-scale dipole reaches tile (a, b)."""
    c = M[PITCH]
    G = c / GRID_PER_PITCH
    halo = 1200.0 * (0.5 * M[SCALE])
    return (np.int64(math.floor(((a * TILE) * G - halo) / c)), np.int64(math.ceil(((a * TILE + TILE) * G + halo) / c)),
            np.int64(math.floor(((b * TILE) * G - halo) / c)), np.int64(math.ceil(((b * TILE + TILE) * G + halo) / c)))


@njit(cache=True, nogil=True, error_model="numpy")
def large_dipoles_in(seed, M, n_lo, n_hi, m_lo, m_hi, out):
    """The nodes (nn, m) of [n_lo, n_hi] × [m_lo, m_hi] that hold a large-scale dipole, by m then
    nn, into ``out``; their number."""
    k = 0
    for m in range(m_lo, m_hi + 1):
        for nn in range(n_lo, n_hi + 1):
            if is_centre(nn, m) and uniform(seed, _rng.LARGE_DIPOLE, nn, m, 0) < M[LARGE_P]:
                out[k, 0] = nn
                out[k, 1] = m
                k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy")
def distortion_tile(seed, M, a, b, out, stats, large, large_box):
    """Displacement d = (dR, dT) [µm] on the (TILE+1)² grid of tile (a, b).

    Grid node (i, j) of the tile sits at ((a·TILE + i)·G, (b·TILE + j)·G)
    with G = pitch / GRID_PER_PITCH.  Each dipole's contribution to a node
    depends only on the pair, and dipoles are added in a fixed global order,
    so nodes shared by two tiles get identical values.  ``large``: the
    large-scale dipoles (:func:`large_dipoles_in`) of the nodes ``large_box``
    (n_lo, n_hi, m_lo, m_hi), which must hold :func:`large_range`.
    """
    c = M[PITCH]
    G = c / GRID_PER_PITCH
    rv = 0.5 * M[SCALE]  # a reference voxel [µm]
    n = TILE + 1
    gR = np.empty(n)
    gT = np.empty(n)
    for i in range(n):
        gR[i] = (a * TILE + i) * G
        gT[i] = (b * TILE + i) * G
    uv = np.zeros((2, n, n))  # (dR, dT) in planes while summing: contiguous rows
    amp = M[DIST]
    # Fibre and vessel dipoles: support ±250 reference voxels.
    halo = 250.0 * rv
    n_lo = np.int64(math.floor((gR[0] - halo) / c)) - 1
    n_hi = np.int64(math.ceil((gR[n - 1] + halo) / c)) + 1
    m_lo = np.int64(math.floor((gT[0] - halo) / c)) - 1
    m_hi = np.int64(math.ceil((gT[n - 1] + halo) / c)) + 1
    vessels = np.empty((4096, 5), np.int64)
    nv = vessels_in_region(seed, M, n_lo, n_hi, m_lo, m_hi, vessels)
    terms = 0
    work = np.empty((5, n))
    if amp > 0.0:
        # A fibre dipole's sigmoid differences depend on its column (R) and row (T) alone: once each.
        DR = np.empty((n_hi - n_lo + 1, n))
        anyR = np.empty(n_hi - n_lo + 1, np.bool_)
        for nn in range(n_lo, n_hi + 1):
            anyR[nn - n_lo] = _sig_diff(gR, nn * c, 0.08, 0.06, rv, 250.0, DR[nn - n_lo])
        DT = np.empty(n)
        for m in range(m_lo, m_hi + 1):
            anyT = _sig_diff(gT, m * c, 0.08, 0.06, rv, 250.0, DT)
            for nn in range(n_lo, n_hi + 1):
                if not is_centre(nn, m) or member_of(vessels, nv, nn, m):
                    continue
                k3 = 2.0 + uniform(seed, _rng.DIPOLE, nn, m, 0)
                k4 = (1.0 + uniform(seed, _rng.DIPOLE, nn, m, 1)) * amp
                if near_ray(seed, M, m, np.int64(5)):  # not a literal: near_ray compiles once
                    k4 *= 0.3
                sign = 1.0 if uniform(seed, _rng.DIPOLE_SIGN, nn, m, 0) < 0.5 else -1.0
                terms += _add_separable(uv, gR, gT, nn * c, m * c, DR[nn - n_lo], DT, anyR[nn - n_lo], anyT,
                                        0.06, k3, k4, sign, rv, 4.0 * k3 / 0.06, work[2], work[3], work[4])
        for v in range(nv):
            terms += _add_dipole(uv, gR, gT, vessels[v, 0] * c, vessels[v, 1] * c,
                                 0.06, 0.055, 2.0, 15.0 * amp, 1.0, rv, 250.0, 4.0 * 2.0 / 0.055, work)
        # Rare large-scale dipoles: support ±1200 reference voxels.
        if M[LARGE_P] > 0.0:
            n0, n1, m0, m1 = large_range(M, a, b)
            if large_box[0] > n0 or large_box[1] < n1 or large_box[2] > m0 or large_box[3] < m1:
                raise ValueError("the large dipoles given do not cover the tile's range")
            for q in range(large.shape[0]):
                nn, m = large[q, 0], large[q, 1]
                if nn < n0 or nn > n1 or m < m0 or m > m1:
                    continue
                k3 = 1.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 1))
                k4 = 0.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 2)) * amp
                sign = 1.0 if uniform(seed, _rng.LARGE_DIPOLE, nn, m, 3) < 0.5 else -1.0
                terms += _add_dipole(uv, gR, gT, nn * c, m * c, 0.01, 0.008, k3, k4, sign,
                                     rv, 1200.0, 3.0 * k3 / 0.008, work)
    # Stationary global bend of the radial files (random phases).
    A = M[BEND_A]
    if A > 0.0:
        lam = M[BEND_WL]
        ph1 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 0)
        ph2 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 1)
        for i in range(n):  # each a function of one coordinate: once per grid line
            work[0, i] = A * math.sin(2.0 * math.pi * gR[i] / lam + ph1)
            work[1, i] = 0.5 * A * math.sin(2.0 * math.pi * gT[i] / (1.618 * lam) + ph2)
        for i in range(n):
            for j in range(n):
                uv[1, i, j] += work[0, i]
                uv[0, i, j] += work[1, j]
    for i in range(n):
        for j in range(n):
            out[i, j, 0] = uv[0, i, j]
            out[i, j, 1] = uv[1, i, j]
    stats[ST_DIPOLES] += terms
    stats[ST_TILES] += 1


@njit(inline="always", cache=True, error_model="numpy")
def _grid_cell(G, R, T):
    """The grid cell (ix, iy) holding (R, T) and the point's fractions (fx, fy) in it."""
    x = R / G
    y = T / G
    ix = math.floor(x)
    iy = math.floor(y)
    return ix, iy, x - ix, y - iy


@njit(inline="always", cache=True, error_model="numpy")
def pull_back(patch, gi0, gj0, G, R, T):
    """p1 = X − d(X), d bilinear on the global distortion grid (indices from global coords)."""
    ix, iy, fx, fy = _grid_cell(G, R, T)
    i = np.uint64(np.int64(ix) - gi0)
    j = np.uint64(np.int64(iy) - gj0)
    i1 = i + np.uint64(1)
    j1 = j + np.uint64(1)
    dR = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 0] + fy * patch[i, j1, 0])
          + fx * ((1.0 - fy) * patch[i1, j, 0] + fy * patch[i1, j1, 0]))
    dT = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 1] + fy * patch[i, j1, 1])
          + fx * ((1.0 - fy) * patch[i1, j, 1] + fy * patch[i1, j1, 1]))
    return R - dR, T - dT


@njit(inline="always", cache=True, error_model="numpy")
def pull_back_slopes(patch, gi0, gj0, G, R, T):
    """∂(dR, dT)/∂(R, T) of the distortion d that :func:`pull_back` subtracts, in its bilinear cell:
    (∂dR/∂R, ∂dR/∂T, ∂dT/∂R, ∂dT/∂T)."""
    ix, iy, fx, fy = _grid_cell(G, R, T)
    i = np.int64(ix) - gi0
    j = np.int64(iy) - gj0
    rx = ((1.0 - fy) * (patch[i + 1, j, 0] - patch[i, j, 0]) + fy * (patch[i + 1, j + 1, 0] - patch[i, j + 1, 0])) / G
    ry = ((1.0 - fx) * (patch[i, j + 1, 0] - patch[i, j, 0]) + fx * (patch[i + 1, j + 1, 0] - patch[i + 1, j, 0])) / G
    tx = ((1.0 - fy) * (patch[i + 1, j, 1] - patch[i, j, 1]) + fy * (patch[i + 1, j + 1, 1] - patch[i, j + 1, 1])) / G
    ty = ((1.0 - fx) * (patch[i, j + 1, 1] - patch[i, j, 1]) + fx * (patch[i + 1, j + 1, 1] - patch[i + 1, j, 1])) / G
    return rx, ry, tx, ty
