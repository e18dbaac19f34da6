"""The wood model at one point: its phase, bit for bit the generator's, and the surfaces near it
(docs/methods.md#the-wood-as-surfaces).

:func:`evaluate` classifies one point with the generator's own kernels
(pull-back, ray bands and squeeze, ray cells, vessel clusters, lumen
ellipses, tip walls, balsa polygons), built for that point alone instead of
for a slice of voxels, so that sampling it at voxel centres gives
:func:`~pipeline.microstructure.model.generate_block` exactly.  Beside the
phase it lists the *primitives* near the point: each inequality of the model
whose switching could change the phase, as a row

    (kind, id a, id b, id c, id d, g, clearance)

with ``g`` the smooth signed function whose zero set is that surface (in the
pulled-back coordinates, or in L), and ``clearance`` [µm] a proven lower bound
on how far the point can move in space before ``g`` changes sign (or +inf
when the primitive cannot change the phase from here).  A bound is the
primitive's margin (a lower bound on the distance to its zero set at fixed
L) divided by a Lipschitz constant: how fast the pulled-back point moves
(the distortion's bilinear Jacobian, the squeeze) plus how fast the surface
moves along L (the spline of the lattice, the tapers).  The minimum over the
rows is a ball free of phase changes: a tracer may step that far blindly.
"""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from .._intrinsics import carve
from ..rng import uniform
from ._constants import (PITCH, RAYS, RHEIGHT, RJIT, RLEN, RLEN_SD, RSER, RSPACE, RSQUEEZE, SCALE, SHAPE, T0,
                         TILE, VWALL)
from ._distortion import pull_back
from ._lattice import chain_interval
from ._ray_cells import ray_band_width, ray_cell_phase, ray_row, ray_slice_tables
from ._slice import _squeeze_and_classify, _vessel_phase, add_ray_row, vessel_outline, vessel_walls

from ._surface_cells import (F_CALLEE, F_RAYS, F_VB, F_VG, I_VL, I_VSEL, NOREF, _ellipses, _polygon,  # noqa: F401
                             group_cached, new_cache, node_cached, span_cached)

from ._surface_rows import (C_CROSS, INF, MAX_PRIMS, N_COLS, P_BAND, P_FACE, P_LUMEN, P_PLATE, P_PLY, P_RAY_END,  # noqa: F401
                            P_RAY_LUMEN, P_REACH, P_TIP, P_TIP_END, P_VESSEL_IN, P_VESSEL_OUT, P_VESSEL_SHARED,
                            R_BAND, R_NODE, R_SQ, R_SQ_L, VBUCKET, VESSEL_REACH, _ellipse_margin, _row, _row_x, rates)

put_row = _row  # (P, n, kind, a, b, c, d, g, clearance) -> n + 1: how any surface lists a row for the march


@njit(**NOREF)
def evaluate(R, T, L, lq, seed, M, ply, patch, gi0, gj0, lam_tab, vessels, nv, vbox, vidx, rt, P, cache, want):
    """Phase at the global point (R, T, L) [µm] of one ply, and the primitives near it.

    ply : (cos, sin, ΔR, ΔT, ΔL) of the ply (:func:`~pipeline.microstructure.model.generate_block`).
    lq : 0 for the exact point; > 0 rounds a rotated ply's L to multiples of lq,
        as the generator does for its slices (lq = voxel/2).
    patch, gi0, gj0 : the ply's distortion grid; lam_tab : per tile of it, the Lipschitz constant of
        its pull-back near the tile (:func:`~pipeline.microstructure.region.region_context`).
    vessels, nv : the ply's vessel members for the node box ``vbox`` (n_lo, n_hi, m_lo, m_hi)
        widened by :data:`VESSEL_REACH`; a point whose cell leaves ``vbox`` returns 255.
    vidx : (bucket grid shape, pointers, cluster starts): per bucket of VBUCKET² nodes of vbox,
        the clusters with a member within 12 nodes of it, ascending.
    rt : :func:`rates`.  P : (MAX_PRIMS, N_COLS) rows written.
    want : a primitive key (kind, a, b, c, d), or kind 0: with a kind, only the rows of that
        primitive's object are written and the phase returned is meaningless (0).
    Returns (phase, number of rows); phase 255 when the point lies outside the
    distortion grid (the caller widens it).
    """
    cs, sn, oR, oT, oL = ply[0], ply[1], ply[2], ply[3], ply[4]
    Rp = cs * R + sn * L + oR
    Lp = -sn * R + cs * L + oL
    Tp = T + oT
    if lq > 0.0 and sn != 0.0:
        Ls = np.int64(round(Lp / lq)) * lq
    else:
        Ls = Lp
    c = M[PITCH]
    inv_c = 1.0 / c
    G = c / 8.0
    ix = np.int64(math.floor(Rp / G)) - gi0
    iy = np.int64(math.floor(Tp / G)) - gj0
    if ix < 0 or iy < 0 or ix >= patch.shape[0] - 1 or iy >= patch.shape[1] - 1:
        return np.uint8(255), 0
    pR, pT = pull_back(patch, gi0, gj0, G, Rp, Tp)
    lam_p = lam_tab[ix // TILE, iy // TILE]
    np_ = 0
    k_in = lam_p * rt[R_SQ] + rt[R_SQ_L]  # pulled-back point, per µm of travel
    # Ray bands: rows whose band or squeeze can reach the point, in increasing k.
    W = ray_band_width(M)
    W2 = 0.5 * W
    lam = M[RSQUEEZE] * M[SCALE]
    WF = cache[7]
    WI = cache[8]
    rays = carve(WF, F_RAYS, (16, 7))
    nr = 0
    if M[RAYS] != 0.0:
        reach = W2 + lam + c
        k_lo = np.int64(math.floor(((pT - reach) * inv_c - M[RJIT] - 2.0) / M[RSPACE])) - 1
        k_hi = np.int64(math.ceil(((pT + reach) * inv_c + M[RJIT] + 2.0) / M[RSPACE])) + 1
        for k in range(k_lo, k_hi + 1):
            row = ray_row(seed, M, k)
            t_r = row * c
            if abs(pT - t_r) > reach:
                continue
            L0, L1, g = group_cached(seed, M, k, Ls, WF, WI)
            b = 0.0
            if math.isnan(L0):
                # No band at this L: one appears only inside a group's span along L.
                dist_l = INF
                for gg in range(g - 1, g + 2):
                    a0, a1 = span_cached(seed, M, k, gg, WF, WI)
                    dist_l = min(dist_l, max(a0 - Ls, Ls - a1, 0.0))
                gb = abs(pT - t_r)
                np_ = _row(P, np_, P_BAND, k, 0, 0, 0, gb, max(dist_l, gb / (lam_p + rt[R_BAND])))
                continue
            before = nr
            nr = add_ray_row(M, Ls, L0, L1, t_r, k, g, W, rays, nr)
            if nr > before:
                b = rays[before, 1]
            gb = abs(pT - t_r) - b
            np_ = _row(P, np_, P_BAND, k, 0, 0, 0, gb, abs(gb) / (lam_p + rt[R_BAND]))
        np_ = _row(P, np_, P_REACH, 0, 0, 0, 0, c, c / (lam_p + rt[R_BAND]))
    sT, r, sq_slope = _squeeze_and_classify(pT, c, W2, lam, rays, nr)
    if r >= 0:
        return _ray_cell(seed, M, Ls, pR, sT, rays[r:r + 1], lam_p, rt, P, np_, want[0] > 0.0, WF)
    n_fl = np.int64(math.floor(pR * inv_c))
    w_fl = np.int64(math.floor(sT * inv_c))
    if n_fl < vbox[0] or n_fl > vbox[1] or w_fl < vbox[2] or w_fl > vbox[3]:
        return np.uint8(255), 0
    # Vessel clusters with a member near the point, whole and in the generator's order (the
    # clusters listed in the point's bucket of ``vidx`` hold every such cluster).
    vsel = carve(WI, I_VSEL, (48,))
    ns = np.int64(0)  # not the literal 0: each callee would compile for it too
    bshape, bptr, blist = vidx
    b = ((n_fl - vbox[0]) // VBUCKET) * bshape[1] + (w_fl - vbox[2]) // VBUCKET
    for e in range(bptr[b], bptr[b + 1]):
        v = blist[e]
        size = vessels[v, 4]
        near = False
        for u in range(v, v + size):
            if abs(vessels[u, 0] - n_fl) <= 12 and abs(vessels[u, 1] - w_fl) <= 12:
                near = True
        if near and ns + size <= 48:
            for u in range(v, v + size):
                vsel[ns] = u
                ns += 1
    nq = max(ns, 1)
    VL = carve(WI, I_VL, (nq, 5))
    VG = carve(WF, F_VG, (nq, 4))
    VB = carve(WF, F_VB, (nq, 2, 6))
    CK, CV, _, _, C, NK, NV, _, _, _ = cache
    wk = want[0]
    # Asked for a fibre's primitive only: the vessels' members matter (a member has no lumen of
    # its own), not their outlines, walls or rows.
    cells = wk == P_LUMEN or wk == P_PLATE or wk == P_TIP or wk == P_TIP_END or wk == P_FACE
    for q in range(ns):
        for f in range(5):
            VL[q, f] = vessels[vsel[q], f]
    for q in range(0 if cells else ns):
        n = VL[q, 0]
        m = VL[q, 1]
        rl, _, _ = node_cached(seed, M, n - 3, m, Ls, CK, CV, C, NK, NV)
        rr, _, _ = node_cached(seed, M, n + 3, m, Ls, CK, CV, C, NK, NV)
        _, td, _ = node_cached(seed, M, n, m - 3, Ls, CK, CV, C, NK, NV)
        _, tu, _ = node_cached(seed, M, n, m + 3, Ls, CK, CV, C, NK, NV)
        vessel_outline(rl, rr, td, tu, VG[q])
    if not cells:
        vessel_walls(VG, VL, ns, VB)
    first = -1
    for q in range(0 if cells else ns):
        i0 = np.int64(math.floor((VG[q, 0] - VG[q, 2]) / c))
        i1 = np.int64(math.floor((VG[q, 0] + VG[q, 2]) / c))
        j0 = np.int64(math.floor((VG[q, 1] - VG[q, 3]) / c))
        j1 = np.int64(math.floor((VG[q, 1] + VG[q, 3]) / c))
        if i0 <= n_fl <= i1 and j0 <= w_fl <= j1:
            first = q - VL[q, 3]
    vwall = M[VWALL]
    rn = rt[R_NODE]
    for q in range(0 if cells else ns):
        dR = pR - VG[q, 0]
        dT = sT - VG[q, 1]
        g = _ellipse_margin(dR, dT, VG[q, 2], VG[q, 3])
        np_ = _row(P, np_, P_VESSEL_OUT, VL[q, 0], VL[q, 1], 0, 0, g, abs(g) / (k_in + 2.1 * rn))
        if g >= 0.0 and want[0] == 0.0:
            continue
        aR = VG[q, 2] - vwall
        aT = VG[q, 3] - vwall
        if aR <= 0.0 or aT <= 0.0:
            continue
        g = _ellipse_margin(dR, dT, aR, aT)
        np_ = _row(P, np_, P_VESSEL_IN, VL[q, 0], VL[q, 1], 0, 0, g, abs(g) / (k_in + 2.1 * rn))
        if g >= 0.0 and want[0] == 0.0:
            continue
        for side in range(2):
            if VB[q, side, 0] == 0.0:
                continue
            gb = ((pR - VB[q, side, 4]) * VB[q, side, 1] + (sT - VB[q, side, 5]) * VB[q, side, 2]) \
                / VB[q, side, 3] + 0.5 * vwall
            far = math.hypot(pR - VB[q, side, 4], sT - VB[q, side, 5])
            rate = rn * (1.0 + 2.0 * far / VB[q, side, 3])
            np_ = _row(P, np_, P_VESSEL_SHARED, VL[q, 0], VL[q, 1], side, 0, gb, abs(gb) / (k_in + rate))
    if wk > 0.0 and not cells:
        return np.uint8(0), np_
    if first >= 0 and wk == 0.0:
        ph = _vessel_phase(pR, sT, VG, VB, VL, first, vwall)
        if ph >= 0:
            return np.uint8(ph), np_
    if M[SHAPE] == 1.0:
        return _polygon(seed, M, Ls, pR, sT, VL, ns, k_in, rt, P, np_, cache, sq_slope)
    return _ellipses(seed, M, Ls, pR, sT, n_fl, w_fl, VL, ns, k_in, rt, P, np_, cache, want, sq_slope)


@njit(**NOREF)
def _ray_cell(seed, M, L, pR, pT, ray, lam_p, rt, P, np_, wanted, WF):
    """Inside a ray band: the generator's ray-cell phase, and the lumens and end walls near."""
    RC = carve(WF, F_CALLEE, (1, 6, 8))
    ray_slice_tables(seed, M, L, ray, np.int64(1), RC)
    memo = carve(WF, F_CALLEE + 48, (8, 4))
    memo[:] = np.nan
    ph = ray_cell_phase(seed, M, pR, pT, np.uint64(0), ray, RC, memo)
    ns = np.int64(M[RSER])
    h = M[RHEIGHT]
    t_r = ray[0, 0]
    b = ray[0, 1]
    L0 = ray[0, 2]
    L1 = ray[0, 3]
    k = np.int64(ray[0, 4])
    g_id = np.int64(ray[0, 5])
    sw = 2.0 * b / ns
    aL = 0.5 * h - M[T0]
    aT = 0.5 * sw - M[T0]
    mean = M[RLEN]
    end_wall = 0.5 * M[SCALE]
    s0 = np.int64(math.floor((pT - (t_r - b)) / sw))
    k3 = lam_p + 1.0 + 2.5 * rt[R_BAND]
    for s in range(max(s0 - 1, 0), min(s0 + 2, ns)):
        Tc = t_r - b + (s + 0.5) * sw
        off = 0.5 * h * (s % 2)
        ell0 = np.int64(math.floor((L - L0 - off) / h))
        for ell in range(ell0 - 1, ell0 + 2):
            if ell < 0 or L0 + off + (ell + 1) * h > L1 + 1e-9:
                continue
            Lc = L0 + off + (ell + 0.5) * h
            if aT <= 0.0 or aL <= 0.0:
                g = math.hypot(pT - Tc, 0.0) - max(aT, 0.0)
                np_ = _row_x(P, np_, P_RAY_LUMEN, k, s, ell, 0, g, abs(g) / k3, pT - Tc, L - Lc, aT, aL)
                continue
            g = _ellipse_margin(pT - Tc, L - Lc, aT, aL)
            np_ = _row_x(P, np_, P_RAY_LUMEN, k, s, ell, 0, g, abs(g) / k3, pT - Tc, L - Lc, aT, aL)
            if g >= 0.0 and not wanted:
                continue
            ida = k * 8 + s
            phase = uniform(seed, _rng.RAY_CELL_PHASE, ida, 0, 0) * mean + 0.5 * mean * (ell % 2)
            lo, hi = chain_interval(pR, seed, _rng.RAY_CELL_END, ida, g_id * 64 + ell, phase, mean, M[RLEN_SD],
                                    0.4 * mean)
            g1 = (pR - lo) - end_wall
            g2 = (hi - pR) - end_wall
            np_ = _row(P, np_, P_RAY_END, k, s, ell, 0, g1, abs(g1) / lam_p)
            np_ = _row(P, np_, P_RAY_END, k, s, ell, 1, g2, abs(g2) / lam_p)
    return ph, np_


@njit(**NOREF)
def clearance(P, n):
    """The smallest clearance of rows P[:n] [µm]: no phase change within that distance."""
    best = INF
    for i in range(n):
        if P[i, 6] < best:
            best = P[i, 6]
    return best


@njit(**NOREF)
def find_row(P, n, key):
    """Index of the row of P[:n] with the primitive ``key`` (kind, a, b, c, d), or -1."""
    for i in range(n):
        if (P[i, 0] == key[0] and P[i, 1] == key[1] and P[i, 2] == key[2] and P[i, 3] == key[3]
                and P[i, 4] == key[4]):
            return i
    return -1


@njit(**NOREF)
def _ply_of(T, spans, th, first, nply):
    """The ply holding T (the generator's rule: ply q holds q·h <= T < (q+1)·h)."""
    q = 0
    if th < 1e300:
        q = np.int64(math.floor(T / th)) - first
        if q > 0 and T < spans[q, 0]:
            q -= 1
        elif q < nply - 1 and T >= spans[q, 1]:
            q += 1
        q = min(max(q, 0), nply - 1)
    return q


@njit(**NOREF)
def _ply_rows(P, n, T, spans, q, th, first, nply, ph):
    """The rows of ply q's T boundaries: boundary b lies between plies b - 1 and b, the same row,
    g = T − its T, on both sides."""
    if th < 1e300 and ph != 255:
        g0 = T - spans[q, 0]
        g1 = T - spans[q, 1]
        if q > 0:
            n = _row(P, n, P_PLY, q + first, 0, 0, 0, g0, abs(g0))
        if q < nply - 1:
            n = _row(P, n, P_PLY, q + 1 + first, 0, 0, 0, g1, abs(g1))
    return n


@njit(inline="always", **NOREF)
def evaluate_at(R, T, L, lq, ctx, P, cache, want):
    """:func:`evaluate` in the ply holding T, with the ply's T boundaries as rows.  ``ctx``:
    :func:`context_tuple`.  Inlined where it is called (its branches live in the two calls above):
    a call passes every array of the context and the cache, hundreds of words."""
    (M, rt, plies, seeds, spans, patches, pshape, origins, lips, vessels, nvs, boxes, th, first, bsh, bptr,
     blist, _curv) = ctx
    nply = plies.shape[0]
    q = _ply_of(T, spans, th, first, nply)
    ph, n = evaluate(R, T, L, lq, seeds[q], M, plies[q], patches[q, :pshape[q, 0], :pshape[q, 1]],
                     origins[q, 0], origins[q, 1], lips[q], vessels[q], nvs[q], boxes[q],
                     (bsh[q], bptr[q], blist[q]), rt, P, cache, want)
    return ph, _ply_rows(P, n, T, spans, q, th, first, nply, ph)
