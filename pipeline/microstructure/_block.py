"""Kernel of a block of voxels for one ply: every voxel centre pulled back and classified
(docs/methods.md#the-microstructure-model).

The phase at a point is a pure function of (constants, seed, position):

    output X ──dipole pull-back──► p1 ──ray band? / ray squeeze──► p ──lattice──► phase

All lengths are in µm.  Nothing here depends on the block being generated,
only on global coordinates, so any block (chunk) can be generated alone and
the voxels are identical whatever the chunking."""

import math

import numpy as np
from numba import njit

from ._constants import CTRL, ENDS, GRID_PER_PITCH, PITCH, RAYS, SHAPE, ST_VOXELS, TIP
from ._distortion import pull_back
from ._ray_cells import ray_band_width, ray_slice_tables
from ._slice import _eval_bucket, build_slice, candidate_table

# --------------------------------------------------------------------------
# A block of voxels for one ply
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def fill_block(out, seed, M, gstart, origin, voxel, j_lo, j_hi, ply, patch, gi0, gj0, dmax,
               vessels, nv, stats, need, ns):
    """Fill ``out[R, T, L]`` for T indices [j_lo, j_hi) of the block from one ply.

    need, ns : with ``ns`` > 0, only voxel (i, j, k) with ``need[i // ns, j // ns, k // ns]`` is
    filled, and slices with none are not built (the others keep what ``out`` held).

    ply : (cos θ, sin θ, ΔR, ΔT, ΔL), the rotation of the ply in the L-R plane and
    its offset.  Ply coordinates: R' = cos·R + sin·L + ΔR, T' = T + ΔT,
    L' = −sin·R + cos·L + ΔL.  An unrotated ply is evaluated slice by slice at the
    exact L; a rotated one on the global L' lattice of spacing voxel/2.
    """
    nR, nT, nL = out.shape
    cs, sn, oR, oT, oL = ply[0], ply[1], ply[2], ply[3], ply[4]
    c = M[PITCH]
    G = c / GRID_PER_PITCH
    rotated = sn != 0.0
    polygon = M[SHAPE] == 1.0
    tips = M[TIP] > 0.0 and M[ENDS] != 0.0 and not polygon
    q = 0.5 * voxel
    # Ply coordinates of each (R, L) pair, and its slice key.
    Rp = np.empty((nR, nL))
    Lp = np.empty((nR, nL))
    key = np.empty(nR * nL, np.int64)
    for i in range(nR):
        R = origin[0] + (gstart[0] + i + 0.5) * voxel
        for k in range(nL):
            L = origin[2] + (gstart[2] + k + 0.5) * voxel
            Rp[i, k] = cs * R + sn * L + oR
            Lp[i, k] = -sn * R + cs * L + oL
            if rotated:
                key[i * nL + k] = np.int64(round(Lp[i, k] / q))
            else:
                key[i * nL + k] = k
    Tp = np.empty(nT)
    for j in range(nT):
        Tp[j] = origin[1] + (gstart[1] + j + 0.5) * voxel + oT
    order = np.argsort(key, kind="mergesort")
    # Unrotated plies: the pre-image of each (R, T) column is the same on every slice.
    P1 = np.empty((nR if not rotated else 0, nT, 2))
    if not rotated:
        for i in range(nR):
            for j in range(j_lo, j_hi):
                a, b = pull_back(patch, gi0, gj0, G, Rp[i, 0], Tp[j])
                P1[i, j, 0] = a
                P1[i, j, 1] = b
    W2 = 0.5 * ray_band_width(M) if M[RAYS] != 0.0 else 0.0
    t_margin = dmax + max(c, W2) + 1.0
    m_lo = np.int64(math.floor((Tp[j_lo] - t_margin) / c)) - 5
    m_hi = np.int64(math.ceil((Tp[j_hi - 1] + t_margin) / c)) + 5
    nm = m_hi - m_lo + 1
    VG = np.empty((max(nv, 1), 4))
    VB = np.empty((max(nv, 1), 2, 6))
    rays = np.empty((64, 7))
    RC = np.empty((64, 6, 8))
    # Control values and fibre cells shared by the slices (see build_slice); their
    # window spans every slice's node window.
    cn = np.int64(math.floor((Rp.min() - dmax - 1.0) / c)) - 4
    cn_hi = np.int64(math.ceil((Rp.max() + dmax + 1.0) / c)) + 4
    l_lo, l_hi = Lp.min() - q, Lp.max() + q  # a rotated ply's slices sit on the L' lattice
    ck = np.int64(math.floor(l_lo / M[CTRL])) - 1
    nk = np.int64(math.floor(l_hi / M[CTRL])) + 3 - ck
    CV = np.empty((cn_hi - cn + 1, nm, nk, 3))
    CF = np.zeros((cn_hi - cn + 1, nm, nk), np.uint8)
    ENDS_ = np.full((cn_hi - cn + 1, nm, 2), np.nan)
    # An unrotated ply's slices read the same (R, T) points: one whose ray table
    # equals the last slice's squeezes and classifies them as it did (SQ, SR).
    SQ = np.empty((nR if not rotated else 0, nT))
    SR = np.empty((nR if not rotated else 0, nT), np.int64)
    last = np.empty((64, 7))
    n_last = -1
    start = np.int64(0)  # not the literal 0: _eval_bucket would compile for it too
    total = nR * nL
    while start < total:
        kb = key[order[start]]
        stop = start
        rmin = 1e300
        rmax = -1e300
        wanted = ns == 0
        while stop < total and key[order[stop]] == kb:
            idx = order[stop]
            r = Rp[idx // nL, idx % nL]
            rmin = min(rmin, r)
            rmax = max(rmax, r)
            if not wanted:
                wanted = _needed(need, ns, idx // nL, idx % nL, j_lo, j_hi)
            stop += 1
        if not wanted:
            start = stop
            continue
        if rotated:
            L = kb * q
        else:
            L = Lp[0, kb]
        n_lo = np.int64(math.floor((rmin - dmax - 1.0) / c)) - 4
        n_hi = np.int64(math.ceil((rmax + dmax + 1.0) / c)) + 4
        nn = n_hi - n_lo + 1
        NR = np.empty((nn, nm))
        NT = np.empty((nn, nm))
        Nt = np.empty((nn, nm))
        FE = np.zeros((nn, nm, 5))
        FE[:, :, 4] = 1e300
        FF = np.ones((nn, nm), np.uint8)
        FJ = np.zeros((nn, nm, 7))
        VIDX = np.empty((nn, nm), np.int64)
        nr = build_slice(seed, M, L, n_lo, m_lo, NR, NT, Nt, FE, FF, FJ, vessels, nv, VG, VB, VIDX,
                         rays, stats, CV, CF, cn, ck, ENDS_)
        ray_slice_tables(seed, M, L, rays, nr, RC)
        reuse = not rotated and nr == n_last and ns == 0
        for r in range(nr):
            for f in range(7):
                reuse = reuse and rays[r, f] == last[r, f]
                last[r, f] = rays[r, f]
        n_last = nr
        nb = ((m_lo + nm - 1) >> 1) - (m_lo >> 1) + 1
        C4 = np.empty((nn, nb, 5, 4))
        CIJ = np.empty((nn if tips else 0, nb, 4, 2), np.int64)
        if not polygon:
            candidate_table(FE, n_lo, m_lo, C4, FJ, CIJ)
        _eval_bucket(out, order, start, stop, nL, j_lo, j_hi, rotated, Rp, Tp, P1, patch, gi0,
                     gj0, G, seed, M, n_lo, m_lo, FE, FF, Nt, vessels[:nv], VG, VB, VIDX, rays, nr, RC,
                     C4, SQ, SR, reuse, FJ, CIJ, need, ns)
        stats[ST_VOXELS] += (stop - start) * (j_hi - j_lo)
        start = stop


@njit(cache=True, nogil=True)
def _needed(need, ns, i, k, j_lo, j_hi):
    """Whether any voxel of column (i, ·, k) in T indices [j_lo, j_hi) is needed."""
    for jc in range(j_lo // ns, (j_hi - 1) // ns + 1):
        if need[i // ns, jc, k // ns] != 0:
            return True
    return False
