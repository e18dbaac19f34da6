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
def _add_dipole(out, gR, gT, R0, T0_, k1, k2, k3, k4, sign, rv, acut, bcut):
    """Add one dipole (docs/methods.md#distortion) to the tile grid ``out``.

    d(a, b) = [σ(k1 a) − σ(k2 a)]·(k4/k2)·exp(−b²/(2 (k3/k2)²)), in reference
    voxels; u uses (a, b) = (R, T), v uses (T, R).  Separable, so the grid
    costs O(n) exponentials per dipole.
    """
    n = gR.shape[0]
    w = k3 / k2
    amp = sign * k4 / k2 * rv
    AR = np.zeros(n)
    BR = np.zeros(n)
    AT = np.zeros(n)
    BT = np.zeros(n)
    anyR = False
    anyT = False
    for i in range(n):
        a = (gR[i] - R0) / rv
        if abs(a) <= acut:
            AR[i] = (_sig(k1 * a) - _sig(k2 * a)) * amp
            anyR = True
        if abs(a) <= bcut:
            BR[i] = math.exp(-a * a / (2.0 * w * w))
        b = (gT[i] - T0_) / rv
        if abs(b) <= acut:
            AT[i] = (_sig(k1 * b) - _sig(k2 * b)) * amp
            anyT = True
        if abs(b) <= bcut:
            BT[i] = math.exp(-b * b / (2.0 * w * w))
    if not (anyR or anyT):
        return 0
    for i in range(n):
        for j in range(n):
            out[i, j, 0] += AR[i] * BT[j]
            out[i, j, 1] += AT[j] * BR[i]
    return 1


@njit(cache=True, nogil=True, error_model="numpy")
def distortion_tile(seed, M, a, b, out, stats):
    """Displacement d = (dR, dT) [µm] on the (TILE+1)² grid of tile (a, b).

    Grid node (i, j) of the tile sits at ((a·TILE + i)·G, (b·TILE + j)·G)
    with G = pitch / GRID_PER_PITCH.  Each dipole's contribution to a node
    depends only on the pair, and dipoles are added in a fixed global order,
    so nodes shared by two tiles get identical values.
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
    out[:, :, :] = 0.0
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
    if amp > 0.0:
        for m in range(m_lo, m_hi + 1):
            for nn in range(n_lo, n_hi + 1):
                if not is_centre(nn, m) or member_of(vessels, nv, nn, m):
                    continue
                k3 = 2.0 + uniform(seed, _rng.DIPOLE, nn, m, 0)
                k4 = (1.0 + uniform(seed, _rng.DIPOLE, nn, m, 1)) * amp
                if near_ray(seed, M, m, 5):
                    k4 *= 0.3
                sign = 1.0 if uniform(seed, _rng.DIPOLE_SIGN, nn, m, 0) < 0.5 else -1.0
                terms += _add_dipole(out, gR, gT, nn * c, m * c, 0.08, 0.06, k3, k4, sign,
                                     rv, 250.0, 4.0 * k3 / 0.06)
        for v in range(nv):
            terms += _add_dipole(out, gR, gT, vessels[v, 0] * c, vessels[v, 1] * c,
                                 0.06, 0.055, 2.0, 15.0 * amp, 1.0, rv, 250.0, 4.0 * 2.0 / 0.055)
        # Rare large-scale dipoles: support ±1200 reference voxels.
        if M[LARGE_P] > 0.0:
            halo = 1200.0 * rv
            for m in range(np.int64(math.floor((gT[0] - halo) / c)),
                           np.int64(math.ceil((gT[n - 1] + halo) / c)) + 1):
                for nn in range(np.int64(math.floor((gR[0] - halo) / c)),
                                np.int64(math.ceil((gR[n - 1] + halo) / c)) + 1):
                    if not is_centre(nn, m) or uniform(seed, _rng.LARGE_DIPOLE, nn, m, 0) >= M[LARGE_P]:
                        continue
                    k3 = 1.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 1))
                    k4 = 0.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 2)) * amp
                    sign = 1.0 if uniform(seed, _rng.LARGE_DIPOLE, nn, m, 3) < 0.5 else -1.0
                    terms += _add_dipole(out, gR, gT, nn * c, m * c, 0.01, 0.008, k3, k4, sign,
                                         rv, 1200.0, 3.0 * k3 / 0.008)
    # Stationary global bend of the radial files (random phases).
    A = M[BEND_A]
    if A > 0.0:
        lam = M[BEND_WL]
        ph1 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 0)
        ph2 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 1)
        for i in range(n):
            for j in range(n):
                out[i, j, 1] += A * math.sin(2.0 * math.pi * gR[i] / lam + ph1)
                out[i, j, 0] += 0.5 * A * math.sin(2.0 * math.pi * gT[j] / (1.618 * lam) + ph2)
    stats[ST_DIPOLES] += terms
    stats[ST_TILES] += 1


@njit(inline="always", cache=True, error_model="numpy")
def pull_back(patch, gi0, gj0, G, R, T):
    """p1 = X − d(X), d bilinear on the global distortion grid (indices from global coords)."""
    x = R / G
    y = T / G
    ix = math.floor(x)
    iy = math.floor(y)
    fx = x - ix
    fy = y - iy
    i = np.uint64(np.int64(ix) - gi0)
    j = np.uint64(np.int64(iy) - gj0)
    i1 = i + np.uint64(1)
    j1 = j + np.uint64(1)
    dR = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 0] + fy * patch[i, j1, 0])
          + fx * ((1.0 - fy) * patch[i1, j, 0] + fy * patch[i1, j1, 0]))
    dT = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 1] + fy * patch[i, j1, 1])
          + fx * ((1.0 - fy) * patch[i1, j, 1] + fy * patch[i1, j1, 1]))
    return R - dR, T - dT
