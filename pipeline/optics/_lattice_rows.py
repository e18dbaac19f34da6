"""Numba kernels: the reference lattices as rows for the surface march, so that ``exact`` traces
them with the engine that traces the wood (docs/methods.md#the-exact-method).

A lattice context is ``(geo, kind, seed, reach)`` (:func:`lattice_context`); at a point,
:func:`lattice_rows` gives the phase (:func:`pipeline.optics._exact.phase_at`, the phase the
voxelisations sample) and a row per surface near the point, in the wood's row format
(kind, i, j, 0, 0, g, clearance):

* tubes: each tube's outer and inner circle, g = distance to the site − radius, clearance |g|
  (a circle's g is its distance);
* honeycombs: each lumen, g = the largest of its face functions (x − m)·e + w/2 over the
  neighbours within two indices, negative inside; |g| is the distance to the lumen's boundary
  inside, a lower bound of it outside (each half-plane holds the lumen);
* a reach row: no surface of a site outside the 5 × 5 indices around the point is nearer.

Every g is 1-Lipschitz and every negative set convex, as the march requires.  The normal of a
crossing is the analytic gradient of the switching row (:func:`lattice_normal`).
"""

import math

import numpy as np
from numba import njit

from ..microstructure.surface import P_REACH, put_row
from ._exact import CELLS, TUBES, _fill_sites, lattice_index, phase_at, site

P_TUBE_OUT = P_REACH + 1  # outer circle of tube (i, j)
P_TUBE_IN = P_REACH + 2  # inner circle (lumen) of tube (i, j)
P_CELL = P_REACH + 3  # lumen of honeycomb cell (i, j)
CONTEXT_LEN = 4  # a lattice context is a 4-tuple; the wood's is longer
BLOCK = 2  # rows for the sites within this many indices of the point's


def lattice_context(geo: np.ndarray, kind: int, seed: int) -> tuple:
    """The march's context of a lattice of ``geo`` (:attr:`Lattice.geo`): with ``reach`` [µm], a lower
    bound on the distance from any point to a surface of a site more than BLOCK indices away."""
    a = np.array([[geo[0], geo[2]], [geo[1], geo[3]]])
    sigma = float(np.linalg.svd(a, compute_uv=False).min())  # |A·w| >= sigma·|w|
    far = (BLOCK + 0.5) * sigma - math.sqrt(2.0) * geo[6]  # distance to such a site
    if kind == TUBES:
        reach = far - geo[11]
    else:
        # A lumen lies within the covering radius of the lattice (0.71 pitch) plus the jitter of its site.
        reach = far - (0.71 * math.hypot(geo[0], geo[1]) + 1.42 * geo[6])
    if not reach > 0.0:
        raise ValueError(f"a lattice whose sites reach {reach:g} µm beyond the rows listed: lower the jitter")
    return (np.ascontiguousarray(geo, np.float64), np.int64(kind), np.uint64(seed), float(reach))


@njit(inline="always", cache=True, nogil=True)
def _cell_g(tab, i, j, x, y, h, face):
    """g of the lumen of site tab[i, j] at (x, y) (its neighbours tab[i ± 2, j ± 2]; half wall h),
    and in ``face`` the unit vector e of its largest face."""
    cx = tab[i, j, 0]
    cy = tab[i, j, 1]
    g = -1e300
    for a in range(i - 2, i + 3):
        for b in range(j - 2, j + 3):
            if a == i and b == j:
                continue
            kx = tab[a, b, 0]
            ky = tab[a, b, 1]
            ex = kx - cx
            ey = ky - cy
            n = math.sqrt(ex * ex + ey * ey)
            ex /= n
            ey /= n
            f = (x - 0.5 * (cx + kx)) * ex + (y - 0.5 * (cy + ky)) * ey + h
            if f > g:
                g = f
                face[0] = ex
                face[1] = ey
    return g


@njit(cache=True, nogil=True)
def lattice_rows(R, T, ctx, P):
    """(phase, rows) of the lattice of ``ctx`` at (R, T) [µm] (L plays no part)."""
    geo, kind, seed, reach = ctx
    ph = phase_at(geo, kind, seed, R, T)
    i0, j0 = lattice_index(geo, R, T)
    face = np.empty(2)
    side = 2 * BLOCK + 5 if kind == CELLS else 1
    tab = np.empty((side, side, 2))  # honeycombs: the sites within BLOCK + 2 indices
    if kind == CELLS:
        _fill_sites(geo, seed, i0, j0, tab)
    half = BLOCK + 2
    n = 0
    for i in range(i0 - BLOCK, i0 + BLOCK + 1):
        for j in range(j0 - BLOCK, j0 + BLOCK + 1):
            sx, sy = site(geo, seed, i, j)
            dist = math.sqrt((R - sx) ** 2 + (T - sy) ** 2)
            if kind == TUBES:
                g_out = dist - geo[11]
                g_in = dist - geo[12]
                if min(abs(g_out), abs(g_in)) < reach:
                    n = put_row(P, n, P_TUBE_OUT, i, j, 0, 0, g_out, abs(g_out))
                    n = put_row(P, n, P_TUBE_IN, i, j, 0, 0, g_in, abs(g_in))
            elif dist - (0.71 * math.sqrt(geo[0] ** 2 + geo[1] ** 2) + 1.42 * geo[6]) < reach:
                g = _cell_g(tab, i - i0 + half, j - j0 + half, R, T, geo[11], face)
                if abs(g) < reach:
                    n = put_row(P, n, P_CELL, i, j, 0, 0, g, abs(g))
    return ph, put_row(P, n, P_REACH, 0, 0, 0, 0, reach, reach)


@njit(cache=True, nogil=True)
def lattice_normal(R, T, ctx, key, nrm):
    """The unit gradient (R, T, L) of row ``key`` at (R, T) into ``nrm``: the radial direction of a
    circle, the face normal of a lumen's largest face."""
    geo, kind, seed, reach = ctx
    i = np.int64(key[1])
    j = np.int64(key[2])
    nrm[2] = 0.0
    if key[0] == P_CELL and kind == CELLS:
        face = np.empty(2)
        tab = np.empty((5, 5, 2))
        _fill_sites(geo, seed, i, j, tab)
        _cell_g(tab, 2, 2, R, T, geo[11], face)
        nrm[0] = face[0]
        nrm[1] = face[1]
        return True
    if key[0] != P_TUBE_OUT and key[0] != P_TUBE_IN:
        return False
    sx, sy = site(geo, seed, i, j)
    dist = math.sqrt((R - sx) ** 2 + (T - sy) ** 2)
    if dist == 0.0:
        return False
    nrm[0] = (R - sx) / dist
    nrm[1] = (T - sy) / dist
    return True
