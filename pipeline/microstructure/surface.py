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
from .._intrinsics import any_inside4
from ..rng import uniform
from ._constants import (ENDS, FLEN, FLEN_SD, JITTER, PITCH, PLATE, PUSH, RAYS, RGROUP, RHEIGHT, RJIT, RLEN,
                         RLEN_SD, RRAMP, RSER, RSPACE, RSQUEEZE, SCALE, SHAPE, T0, TIP, VESSEL_AXIS_R, VWALL,
                         WALLVAR, CTRL)
from ._distortion import pull_back
from ._lattice import _controls, _node_from, _spline, chain_interval, is_centre
from ._ray_cells import group_span, ray_band_width, ray_cell_phase, ray_group, ray_row, ray_slice_tables
from ._slice import _in_tip_wall, _polygon_phase, _squeeze_and_classify, _vessel_phase, tip_walls
from ._vessels import member_of

# Primitive kinds (column 0 of a row).
P_BAND = 1  # edge of a ray band: |pT − t_r| = b (a = column k)
P_RAY_LUMEN = 2  # ray-cell lumen ellipse in (T, L) (k, sub-column, cell along L)
P_RAY_END = 3  # radial end wall of a ray cell (k, sub-column, cell, side)
P_VESSEL_OUT = 4  # vessel outline (n, m)
P_VESSEL_IN = 5  # vessel lumen (n, m)
P_VESSEL_SHARED = 6  # wall shared by cluster neighbours (n, m, side)
P_LUMEN = 7  # fibre lumen ellipse (n, m)
P_PLATE = 8  # end plate plane along L (n, m, side)
P_TIP = 9  # oblique tip wall (n, m, wall)
P_TIP_END = 10  # where a tip wall begins or ends along L (n, m, side)
P_FACE = 11  # balsa: wall along a Voronoi face (n, m, neighbour n, neighbour m)
P_PLY = 12  # ply boundary (ply, side)
P_REACH = 13  # not a surface: how far the point's candidate set is valid
N_COLS = 7
MAX_PRIMS = 160
VBUCKET = 8  # nodes per side of a vessel bucket
VESSEL_REACH = 24  # nodes: clusters with a member this near a listed point are listed whole
INF = 1e300

# Bound of Σ|w'(f)| of the Catmull-Rom weights over f in [0, 1]: how fast a node moves along L.
CR_SLOPE = 1.6

# Rates (context vector R, floats) the Lipschitz constants need, per wood: see rates().
R_NODE, R_WALL, R_BAND, R_SQ_L, R_SQ, R_TIP = range(6)
N_RATES = 6


def rates(M: np.ndarray) -> np.ndarray:
    """How fast the model's surfaces move with L, and how much the squeeze stretches T
    (the constants of the clearance bounds)."""
    out = np.zeros(N_RATES)
    c = M[PITCH]
    out[R_NODE] = M[JITTER] * c * CR_SLOPE / M[CTRL]
    out[R_WALL] = M[T0] * M[WALLVAR] * CR_SLOPE / M[CTRL]
    if M[RAYS] != 0.0:
        W = ray_band_width(M)
        lam = M[RSQUEEZE] * M[SCALE]
        out[R_BAND] = 0.5 * W * 1.5 / M[RRAMP]
        out[R_SQ_L] = abs(c - 0.5 * W) * 1.5 / M[RRAMP]
        out[R_SQ] = 1.0 + 3.0 * abs(c - 0.5 * W) / lam
    else:
        out[R_SQ] = 1.0
    if M[TIP] > 0.0:
        push = M[PUSH] * M[SCALE]
        w_max = 1.5 * (c + push)
        out[R_TIP] = w_max / M[TIP] + 2.0 * out[R_NODE] + 2.0 * out[R_WALL]
    return out


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _row(P, n, kind, a, b, c, d, g, clr):
    if n < P.shape[0]:
        P[n, 0] = kind
        P[n, 1] = a
        P[n, 2] = b
        P[n, 3] = c
        P[n, 4] = d
        P[n, 5] = g
        P[n, 6] = clr
        return n + 1
    return n


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _ellipse_margin(dR, dT, aR, aT):
    """(sqrt(q) − 1)·min(a): positive outside, its modulus a lower bound on the distance to the
    ellipse of semi-axes aR, aT (the map scaling by 1/a moves points by at most 1/min(a))."""
    q = dR * dR / (aR * aR) + dT * dT / (aT * aT)
    return (math.sqrt(q) - 1.0) * min(aR, aT)


CACHE_SLOTS = 8192  # direct-mapped cache of control values and fibre cells (a power of 2)


def new_cache():
    """Per-thread memo of pure functions of ids (control values of (node, slice), the fibre cell
    around L): (keys, control values, cell keys, cells).  It changes no result."""
    return (np.full((CACHE_SLOTS, 4), np.iinfo(np.int64).min, np.int64), np.empty((CACHE_SLOTS, 3)),
            np.full((CACHE_SLOTS, 3), np.iinfo(np.int64).min, np.int64), np.empty((CACHE_SLOTS, 2)),
            np.empty((4, 3)))


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _slot(a, b, c, d):
    h = (np.uint64(a) * np.uint64(0x9E3779B97F4A7C15)) ^ (np.uint64(b) * np.uint64(0xC2B2AE3D27D4EB4F)) \
        ^ (np.uint64(c) * np.uint64(0x165667B19E3779F9)) ^ np.uint64(d)
    h ^= h >> np.uint64(29)
    return np.int64(h & np.uint64(CACHE_SLOTS - 1))


@njit(cache=True, nogil=True, error_model="numpy")
def node_cached(seed, M, n, m, L, cache):
    """:func:`~pipeline.microstructure._lattice.node_state`, its control values memoised."""
    CK, CV = cache[0], cache[1]
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    sd = np.int64(seed)
    C = cache[4]
    for q in range(4):
        kq = k + q - 1
        i = _slot(n, m, kq, sd)
        if CK[i, 0] == n and CK[i, 1] == m and CK[i, 2] == kq and CK[i, 3] == sd:
            for f in range(3):
                C[q, f] = CV[i, f]
        else:
            _controls(seed, n, m, kq, C[q])
            CK[i, 0] = n
            CK[i, 1] = m
            CK[i, 2] = kq
            CK[i, 3] = sd
            for f in range(3):
                CV[i, f] = C[q, f]
    return _node_from(M, n, m, w0, w1, w2, w3, C[0], C[1], C[2], C[3])


@njit(cache=True, nogil=True, error_model="numpy")
def _fibre_cell(seed, M, L, n, m, min_len, cache):
    """:func:`chain_interval` of fibre (n, m) at L, memoised (a cell holds for every L inside it)."""
    EK, EV = cache[2], cache[3]
    sd = np.int64(seed)
    i = _slot(n, m, 7, sd)
    if EK[i, 0] == n and EK[i, 1] == m and EK[i, 2] == sd and EV[i, 0] <= L < EV[i, 1]:
        return EV[i, 0], EV[i, 1]
    ph = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * M[FLEN]
    lo, hi = chain_interval(L, seed, _rng.FIBRE_END, n, m, ph, M[FLEN], M[FLEN_SD], min_len)
    EK[i, 0] = n
    EK[i, 1] = m
    EK[i, 2] = sd
    EV[i, 0] = lo
    EV[i, 1] = hi
    return lo, hi


@njit(cache=True, nogil=True, error_model="numpy")
def _nodes(seed, M, L, n0, m0, NW, have, n, m, cache):
    """Node (n, m)'s (R, T, inset) at L, from the small window cache NW (origin n0, m0)."""
    i = n - n0
    j = m - m0
    if 0 <= i < NW.shape[0] and 0 <= j < NW.shape[1]:
        if have[i, j] == 0:
            NW[i, j, 0], NW[i, j, 1], NW[i, j, 2] = node_cached(seed, M, n, m, L, cache)
            have[i, j] = 1
        return NW[i, j, 0], NW[i, j, 1], NW[i, j, 2]
    return node_cached(seed, M, n, m, L, cache)


@njit(cache=True, nogil=True, error_model="numpy")
def _fibre(seed, M, L, n, m, vessels, nv, NW, have, n0, m0, FErow, FJrow, cache):
    """The generator's per-centre tables (build_slice) for centre (n, m) at L.

    Writes FErow (cR, cT, 1/aR², 1/aT², bias) and FJrow (tip walls); returns
    (flag, lo, hi, aR, aT, Nt) with flag 0 open, 1 closed, 2 vessel member, and the lumen's
    semi-axes as computed (<= 0: no lumen).
    """
    polygon = M[SHAPE] == 1.0
    push = M[PUSH] * M[SCALE]
    plate = 0.5 * M[PLATE]
    tip = M[TIP]
    min_len = min(50.0, 0.5 * M[FLEN])
    if tip > 0.0:
        min_len = max(min_len, min(tip, 0.5 * M[FLEN]))
    flag = 0
    lo = np.nan
    hi = np.nan
    aR = 0.0
    aT = 0.0
    if member_of(vessels, nv, n, m):
        flag = 2
    elif M[ENDS] != 0.0:
        lo, hi = _fibre_cell(seed, M, L, n, m, min_len, cache)
        if tip == 0.0 and (L - lo < plate or hi - L < plate):
            flag = 1
    cR, cT, Nt = _nodes(seed, M, L, n0, m0, NW, have, n, m, cache)
    if polygon:
        FErow[0] = cR
        FErow[1] = cT
    else:
        rR1, _, _ = _nodes(seed, M, L, n0, m0, NW, have, n + 1, m, cache)
        rR0, _, _ = _nodes(seed, M, L, n0, m0, NW, have, n - 1, m, cache)
        _, tT1, _ = _nodes(seed, M, L, n0, m0, NW, have, n, m + 1, cache)
        _, tT0, _ = _nodes(seed, M, L, n0, m0, NW, have, n, m - 1, cache)
        aR = 0.5 * (rR1 - rR0) - Nt
        aT = 0.5 * (tT1 - tT0) + push - Nt
        raw_R = aR
        raw_T = aT
        if aR <= 0.0 or aT <= 0.0:
            if flag == 0:
                flag = 1
            aR = 1.0
            aT = 1.0
        FErow[0] = 0.5 * (rR1 + rR0)
        FErow[1] = 0.5 * (tT1 + tT0)
        FErow[2] = 1.0 / (aR * aR)
        FErow[3] = 1.0 / (aT * aT)
    FErow[4] = 0.0 if flag == 0 else 1e300
    FJrow[0] = 0.0
    if tip > 0.0 and flag == 0 and not polygon and not math.isnan(lo):
        ph = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * M[FLEN]
        tip_walls(seed, n, m, L, lo, hi, tip, ph, M[FLEN], aR, aT, FJrow)
    if not polygon:
        aR = raw_R
        aT = raw_T
    return flag, lo, hi, aR, aT, Nt


@njit(cache=True, nogil=True, error_model="numpy")
def evaluate(R, T, L, lq, seed, M, ply, patch, gi0, gj0, lam_p, vessels, nv, vbox, vidx, rt, P, cache):
    """Phase at the global point (R, T, L) [µm] of one ply, and the primitives near it.

    ply : (cos, sin, ΔR, ΔT, ΔL) of the ply (:func:`~pipeline.microstructure.model.generate_block`).
    lq : 0 for the exact point; > 0 rounds a rotated ply's L to multiples of lq,
        as the generator does for its slices (lq = voxel/2).
    patch, gi0, gj0 : the ply's distortion grid; lam_p : the Lipschitz constant of its pull-back.
    vessels, nv : the ply's vessel members for the node box ``vbox`` (n_lo, n_hi, m_lo, m_hi)
        widened by :data:`VESSEL_REACH`; a point whose cell leaves ``vbox`` returns 255.
    vidx : (bucket grid shape, pointers, cluster starts): per bucket of VBUCKET² nodes of vbox,
        the clusters with a member within 12 nodes of it, ascending.
    rt : :func:`rates`.  P : (MAX_PRIMS, N_COLS) rows written.
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
    np_ = 0
    k_in = lam_p * rt[R_SQ] + rt[R_SQ_L]  # pulled-back point, per µm of travel
    # Ray bands: rows whose band or squeeze can reach the point, in increasing k.
    W = ray_band_width(M)
    W2 = 0.5 * W
    lam = M[RSQUEEZE] * M[SCALE]
    rays = np.empty((16, 7))
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
            L0, L1, g = ray_group(seed, M, k, Ls)
            b = 0.0
            if math.isnan(L0):
                # No band at this L: one appears only inside a group's span along L.
                dist_l = INF
                for gg in range(g - 1, g + 2):
                    a0, a1 = group_span(seed, M, k, gg)
                    dist_l = min(dist_l, max(a0 - Ls, Ls - a1, 0.0))
                gb = abs(pT - t_r)
                np_ = _row(P, np_, P_BAND, k, 0, 0, 0, gb, max(dist_l, gb / (lam_p + rt[R_BAND])))
                continue
            else:
                x = min(Ls - L0, L1 - Ls) / M[RRAMP]
                x = min(max(x, 0.0), 1.0)
                taper = x * x * (3.0 - 2.0 * x)
                if taper > 0.0 and nr < 16:
                    rays[nr, 0] = t_r
                    rays[nr, 1] = 0.5 * W * taper
                    rays[nr, 2] = L0
                    rays[nr, 3] = L1
                    rays[nr, 4] = k
                    rays[nr, 5] = g
                    rays[nr, 6] = taper
                    b = rays[nr, 1]
                    nr += 1
            gb = abs(pT - t_r) - b
            np_ = _row(P, np_, P_BAND, k, 0, 0, 0, gb, abs(gb) / (lam_p + rt[R_BAND]))
        np_ = _row(P, np_, P_REACH, 0, 0, 0, 0, c, c / (lam_p + rt[R_BAND]))
    sT, r = _squeeze_and_classify(pT, c, W2, lam, rays, nr)
    if r >= 0:
        return _ray_cell(seed, M, Ls, pR, sT, rays[r:r + 1], lam_p, rt, P, np_)
    n_fl = np.int64(math.floor(pR * inv_c))
    w_fl = np.int64(math.floor(sT * inv_c))
    if n_fl < vbox[0] or n_fl > vbox[1] or w_fl < vbox[2] or w_fl > vbox[3]:
        return np.uint8(255), 0
    # Vessel clusters with a member near the point, whole and in the generator's order (the
    # clusters listed in the point's bucket of ``vidx`` hold every such cluster).
    vsel = np.empty(48, np.int64)
    ns = 0
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
    VL = np.empty((max(ns, 1), 5), np.int64)
    VG = np.empty((max(ns, 1), 4))
    VB = np.empty((max(ns, 1), 2, 6))
    for q in range(ns):
        for f in range(5):
            VL[q, f] = vessels[vsel[q], f]
        n = VL[q, 0]
        m = VL[q, 1]
        rl, _, _ = node_cached(seed, M, n - 3, m, Ls, cache)
        rr, _, _ = node_cached(seed, M, n + 3, m, Ls, cache)
        _, td, _ = node_cached(seed, M, n, m - 3, Ls, cache)
        _, tu, _ = node_cached(seed, M, n, m + 3, Ls, cache)
        VG[q, 0] = 0.5 * (rl + rr)
        VG[q, 1] = 0.5 * (td + tu)
        VG[q, 2] = 0.5 * (rr - rl) * VESSEL_AXIS_R
        VG[q, 3] = 0.5 * (tu - td)
    for q in range(ns):
        for side in range(2):
            u = q - 1 + 2 * side
            VB[q, side, 0] = 0.0
            if u < 0 or u >= ns or VL[u, 2] != VL[q, 2]:
                continue
            ex = VG[u, 0] - VG[q, 0]
            ey = VG[u, 1] - VG[q, 1]
            VB[q, side, 0] = 1.0
            VB[q, side, 1] = ex
            VB[q, side, 2] = ey
            VB[q, side, 3] = math.sqrt(ex * ex + ey * ey)
            VB[q, side, 4] = 0.5 * (VG[u, 0] + VG[q, 0])
            VB[q, side, 5] = 0.5 * (VG[u, 1] + VG[q, 1])
    first = -1
    for q in range(ns):
        i0 = np.int64(math.floor((VG[q, 0] - VG[q, 2]) / c))
        i1 = np.int64(math.floor((VG[q, 0] + VG[q, 2]) / c))
        j0 = np.int64(math.floor((VG[q, 1] - VG[q, 3]) / c))
        j1 = np.int64(math.floor((VG[q, 1] + VG[q, 3]) / c))
        if i0 <= n_fl <= i1 and j0 <= w_fl <= j1:
            first = q - VL[q, 3]
    vwall = M[VWALL]
    rn = rt[R_NODE]
    for q in range(ns):
        dR = pR - VG[q, 0]
        dT = sT - VG[q, 1]
        g = _ellipse_margin(dR, dT, VG[q, 2], VG[q, 3])
        np_ = _row(P, np_, P_VESSEL_OUT, VL[q, 0], VL[q, 1], 0, 0, g, abs(g) / (k_in + 2.1 * rn))
        if g >= 0.0:
            continue
        aR = VG[q, 2] - vwall
        aT = VG[q, 3] - vwall
        if aR <= 0.0 or aT <= 0.0:
            continue
        g = _ellipse_margin(dR, dT, aR, aT)
        np_ = _row(P, np_, P_VESSEL_IN, VL[q, 0], VL[q, 1], 0, 0, g, abs(g) / (k_in + 2.1 * rn))
        if g >= 0.0:
            continue
        for side in range(2):
            if VB[q, side, 0] == 0.0:
                continue
            gb = ((pR - VB[q, side, 4]) * VB[q, side, 1] + (sT - VB[q, side, 5]) * VB[q, side, 2]) \
                / VB[q, side, 3] + 0.5 * vwall
            far = math.hypot(pR - VB[q, side, 4], sT - VB[q, side, 5])
            rate = rn * (1.0 + 2.0 * far / VB[q, side, 3])
            np_ = _row(P, np_, P_VESSEL_SHARED, VL[q, 0], VL[q, 1], side, 0, gb, abs(gb) / (k_in + rate))
    if first >= 0:
        ph = _vessel_phase(pR, sT, VG, VB, VL, first, vwall)
        if ph >= 0:
            return np.uint8(ph), np_
    if M[SHAPE] == 1.0:
        return _polygon(seed, M, Ls, pR, sT, VL, ns, k_in, rt, P, np_, cache)
    return _ellipses(seed, M, Ls, pR, sT, n_fl, w_fl, VL, ns, k_in, rt, P, np_, cache)


@njit(cache=True, nogil=True, error_model="numpy")
def _ellipses(seed, M, L, pR, sT, n_fl, w_fl, VL, ns, k_in, rt, P, np_, cache):
    """Fibre lumens: the phase from the four candidates of the point's cell, the rows from the
    lumens of the 3 × 3 cells around it (so a step of one cell meets no other lumen)."""
    c = M[PITCH]
    j0 = w_fl >> 1
    n0 = n_fl - 4
    m0 = 2 * j0 - 3
    NW = np.empty((10, 10, 3))
    have = np.zeros((10, 10), np.uint8)
    C4 = np.empty((1, 1, 5, 4))
    FE4 = np.empty((4, 1, 5))
    Nt4 = np.empty((4, 1))
    FJ4 = np.zeros((4, 1, 7))
    CIJ = np.full((1, 1, 4, 2), -1, np.int64)
    FE = np.empty(5)
    FJ = np.zeros(7)
    rn = rt[R_NODE]
    rw = rt[R_WALL]
    plate = 0.5 * M[PLATE]
    tip = M[TIP]
    tips = tip > 0.0 and M[ENDS] != 0.0
    inside = False
    for mj in range(-1, 3):
        m = 2 * (j0 + mj)
        for n in range(n_fl - 3, n_fl + 5):
            if not is_centre(n, m):
                continue
            flag, lo, hi, aR, aT, Nt = _fibre(seed, M, L, n, m, VL, ns, NW, have, n0, m0, FE, FJ, cache)
            base = n_fl - ((n_fl - (j0 + mj)) & 1)
            if 0 <= mj <= 1 and (n == base or n == base + 2):
                t = 2 * mj + (n - base) // 2
                for f in range(5):
                    C4[0, 0, f, t] = FE[f]
                    FE4[t, 0, f] = FE[f]
                Nt4[t, 0] = Nt
                for f in range(7):
                    FJ4[t, 0, f] = FJ[f]
                if tips and FJ[0] > 0.0:
                    CIJ[0, 0, t, 0] = t
                    CIJ[0, 0, t, 1] = 0
            if flag == 2:
                continue
            dR = pR - FE[0]
            dT = sT - FE[1]
            kk = k_in + 2.0 * rn + rw
            if aR <= 0.0 or aT <= 0.0:
                # No lumen at this L; one opens only once both semi-axes grow past 0.
                dist = math.hypot(dR, dT) - max(aR, aT, 0.0)
                clr = max(-min(aR, aT) / (rn + rw), dist / kk)
                np_ = _row(P, np_, P_LUMEN, n, m, 0, 0, max(dist, 0.0) + 1.0, clr)
                continue
            ge = _ellipse_margin(dR, dT, aR, aT)
            clr = abs(ge) / kk
            if flag == 1 and not math.isnan(lo) and tip == 0.0:
                g1 = (L - lo) - plate
                g2 = (hi - L) - plate
                if ge < 0.0:
                    np_ = _row(P, np_, P_PLATE, n, m, 0, 0, g1, abs(g1))
                    np_ = _row(P, np_, P_PLATE, n, m, 1, 0, g2, abs(g2))
                else:  # outside a closed lumen: it must open and be entered
                    viol = max(-g1 if g1 < 0.0 else 0.0, -g2 if g2 < 0.0 else 0.0)
                    clr = max(clr, viol)
            np_ = _row(P, np_, P_LUMEN, n, m, 0, 0, ge, clr)
            if ge < 0.0 and tips and not math.isnan(lo):
                for side in range(2):
                    b = lo if side == 0 else hi
                    gt = abs(L - b) - tip
                    np_ = _row(P, np_, P_TIP_END, n, m, side, 0, gt, abs(gt))
                for w in range(np.int64(FJ[0])):
                    d = dR * FJ[1 + 3 * w] + dT * FJ[2 + 3 * w] - FJ[3 + 3 * w]
                    gs = abs(d) - Nt
                    np_ = _row(P, np_, P_TIP, n, m, w, 0, gs, abs(gs) / (k_in + rt[R_TIP]))
    np_ = _row(P, np_, P_REACH, 1, 0, 0, 0, c, c / (k_in + 2.0 * rn + rw))
    inside = any_inside4(C4, (np.uint64(0), np.uint64(0), np.uint64(0), np.uint64(0)), pR, sT)
    if inside and tips:
        inside = not _in_tip_wall(pR, sT, np.uint64(0), np.uint64(0), FE4, Nt4, FJ4, CIJ)
    return np.uint8(0) if inside else np.uint8(1), np_


@njit(cache=True, nogil=True, error_model="numpy")
def _polygon(seed, M, L, pR, sT, VL, ns, k_in, rt, P, np_, cache):
    """Balsa: the generator's Voronoi test on the nine candidate centres, and their faces."""
    c = M[PITCH]
    inv_c = 1.0 / c
    u = pR * inv_c
    w = sT * inv_c
    jc = np.int64(round(w / 2.0))
    n_lo = np.int64(math.floor(u)) - 6
    m_lo = 2 * (jc - 1) - 1
    FE = np.zeros((14, 8, 5))
    FF = np.zeros((14, 8), np.uint8)
    Nt = np.zeros((14, 8))
    LO = np.full((14, 8, 2), np.nan)
    NW = np.empty((16, 10, 3))
    have = np.zeros((16, 10), np.uint8)
    FJ = np.zeros(7)
    FErow = np.empty(5)
    for j in range(jc - 1, jc + 2):
        m = 2 * j
        par = j % 2
        n0 = 2 * np.int64(round((u - par) / 2.0)) + par
        for n in (n0 - 2, n0, n0 + 2):
            flag, lo, hi, _, _, t = _fibre(seed, M, L, n, m, VL, ns, NW, have, n_lo - 1, m_lo - 1, FErow, FJ, cache)
            ii = n - n_lo
            jj = m - m_lo
            for f in range(5):
                FE[ii, jj, f] = FErow[f]
            FF[ii, jj] = flag
            Nt[ii, jj] = t
            LO[ii, jj, 0] = lo
            LO[ii, jj, 1] = hi
    cand_i = np.empty(9, np.int64)
    cand_j = np.empty(9, np.int64)
    ph = _polygon_phase(pR, sT, u, w, n_lo, m_lo, FE, FF, Nt, cand_i, cand_j)
    # The faces of the nearest centre with its neighbours, and its end planes.
    best = -1
    bd = 1e300
    for q in range(9):
        dR = pR - FE[cand_i[q], cand_j[q], 0]
        dT = sT - FE[cand_i[q], cand_j[q], 1]
        d2 = dR * dR + dT * dT
        if d2 < bd:
            bd = d2
            best = q
    bi = cand_i[best]
    bj = cand_j[best]
    rn = rt[R_NODE]
    rw = rt[R_WALL]
    for q in range(9):
        if q == best:
            continue
        ii = cand_i[q]
        jj = cand_j[q]
        ex = FE[ii, jj, 0] - FE[bi, bj, 0]
        ey = FE[ii, jj, 1] - FE[bi, bj, 1]
        dR = pR - FE[ii, jj, 0]
        dT = sT - FE[ii, jj, 1]
        e = math.sqrt(ex * ex + ey * ey)
        dist = (dR * dR + dT * dT - bd) / (2.0 * e)
        g = dist - 0.5 * (Nt[bi, bj] + Nt[ii, jj])
        far = math.hypot(pR - 0.5 * (FE[ii, jj, 0] + FE[bi, bj, 0]), sT - 0.5 * (FE[ii, jj, 1] + FE[bi, bj, 1]))
        rate = rn * (1.0 + 2.0 * far / e) + rw
        np_ = _row(P, np_, P_FACE, bi + n_lo, bj + m_lo, ii + n_lo, jj + m_lo, g, abs(g) / (k_in + rate))
    if FF[bi, bj] == 1 and not math.isnan(LO[bi, bj, 0]):
        plate = 0.5 * M[PLATE]
        g1 = (L - LO[bi, bj, 0]) - plate
        g2 = (LO[bi, bj, 1] - L) - plate
        np_ = _row(P, np_, P_PLATE, bi + n_lo, bj + m_lo, 0, 0, g1, abs(g1))
        np_ = _row(P, np_, P_PLATE, bi + n_lo, bj + m_lo, 1, 0, g2, abs(g2))
    np_ = _row(P, np_, P_REACH, 2, 0, 0, 0, 0.5 * c, 0.5 * c / (k_in + 4.0 * rn + rw))
    return ph, np_


@njit(cache=True, nogil=True, error_model="numpy")
def _ray_cell(seed, M, L, pR, pT, ray, lam_p, rt, P, np_):
    """Inside a ray band: the generator's ray-cell phase, and the lumens and end walls near."""
    RC = np.empty((1, 6, 8))
    ray_slice_tables(seed, M, L, ray, 1, RC)
    memo = np.full((8, 4), np.nan)
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
                np_ = _row(P, np_, P_RAY_LUMEN, k, s, ell, 0, g, abs(g) / k3)
                continue
            g = _ellipse_margin(pT - Tc, L - Lc, aT, aL)
            np_ = _row(P, np_, P_RAY_LUMEN, k, s, ell, 0, g, abs(g) / k3)
            if g >= 0.0:
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


@njit(cache=True, nogil=True, error_model="numpy")
def clearance(P, n):
    """The smallest clearance of rows P[:n] [µm]: no phase change within that distance."""
    best = INF
    for i in range(n):
        if P[i, 6] < best:
            best = P[i, 6]
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def find_row(P, n, key):
    """Index of the row of P[:n] with the primitive ``key`` (kind, a, b, c, d), or -1."""
    for i in range(n):
        if (P[i, 0] == key[0] and P[i, 1] == key[1] and P[i, 2] == key[2] and P[i, 3] == key[3]
                and P[i, 4] == key[4]):
            return i
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def evaluate_at(R, T, L, lq, ctx, P, cache):
    """:func:`evaluate` in the ply holding T (the generator's rule: ply q holds q·h <= T < (q+1)·h),
    with the ply's T boundaries as rows.  ``ctx``: :func:`context_tuple`."""
    (M, rt, plies, seeds, spans, patches, pshape, origins, lips, vessels, nvs, boxes, th, first, bsh, bptr,
     blist) = ctx
    q = 0
    if th < 1e300:
        q = np.int64(math.floor(T / th)) - first
        if q > 0 and T < spans[q, 0]:
            q -= 1
        elif q < plies.shape[0] - 1 and T >= spans[q, 1]:
            q += 1
        q = min(max(q, 0), plies.shape[0] - 1)
    ph, n = evaluate(R, T, L, lq, seeds[q], M, plies[q], patches[q, :pshape[q, 0], :pshape[q, 1]],
                     origins[q, 0], origins[q, 1], lips[q], vessels[q], nvs[q], boxes[q],
                     (bsh[q], bptr[q], blist[q]), rt, P, cache)
    if th < 1e300 and ph != 255:
        g0 = T - spans[q, 0]
        g1 = spans[q, 1] - T
        if q > 0:
            n = _row(P, n, P_PLY, q + first, 0, 0, 0, g0, abs(g0))
        if q < plies.shape[0] - 1:
            n = _row(P, n, P_PLY, q + first, 1, 0, 0, g1, abs(g1))
    return ph, n


@njit(cache=True, nogil=True, error_model="numpy")
def _phases(points, lq, ctx, cache):
    out = np.empty(points.shape[0], np.uint8)
    P = np.empty((MAX_PRIMS, N_COLS))
    for i in range(points.shape[0]):
        out[i], _ = evaluate_at(points[i, 0], points[i, 1], points[i, 2], lq, ctx, P, cache)
    return out


def phases(points, lq, ctx):
    """Phase at each of ``points`` (N, 3) [µm] (255: outside the context's region)."""
    return _phases(np.ascontiguousarray(points, np.float64), float(lq), ctx, new_cache())


def context_tuple(ctx: dict) -> tuple:
    """The arrays of :func:`region_context` in the order the kernels take them."""
    return (ctx["M"], ctx["rates"], ctx["plies"], ctx["seeds"], ctx["spans"], ctx["patches"],
            ctx["patch_shape"], ctx["origins"], ctx["lipschitz"], ctx["vessels"], ctx["n_vessels"],
            ctx["boxes"], ctx["ply_thickness"], ctx["first_ply"], ctx["bucket_shape"], ctx["bucket_ptr"],
            ctx["bucket_list"])


# --------------------------------------------------------------------------
# The context of a region: per ply, what evaluate() reads
# --------------------------------------------------------------------------
def lipschitz_of_pull_back(patch: np.ndarray, G: float) -> float:
    """A bound of ‖∂p/∂X‖ for the bilinear pull-back p = X − d(X) on ``patch``: 1 + the largest
    Frobenius norm of ∂d/∂X over its cells (each partial derivative of a bilinear cell lies between
    its two edge differences)."""
    dx = np.abs(np.diff(patch, axis=0)) / G  # (ni-1, nj, 2): ∂d/∂R on cell edges
    dy = np.abs(np.diff(patch, axis=1)) / G
    mx = np.maximum(dx[:, :-1], dx[:, 1:])  # per cell
    my = np.maximum(dy[:-1], dy[1:])
    frob = np.sqrt((mx ** 2).sum(axis=2) + (my ** 2).sum(axis=2))
    return float(1.0 + frob.max()) * (1.0 + 1e-12)


def region_context(params, seed: int, thickness_um: float, r_range, l_range) -> dict:
    """What :func:`evaluate` needs for the slab T ∈ [0, thickness] over R ∈ r_range, L ∈ l_range
    [µm]: per ply its placement, seed, distortion grid (assembled from the generator's cached
    tiles), pull-back bound and vessels; arrays padded to the largest ply."""
    from . import _constants as K
    from ._vessels import vessels_in_region
    from .model import N_STATS, _patch, _plies, model_constants

    M = model_constants(params)
    c = params.node_pitch_um
    G = c / K.GRID_PER_PITCH
    stats = np.zeros(N_STATS, np.int64)
    plies = list(_plies(params, seed, 0.0, thickness_um))
    rows, seeds, spans, patches, origins, lams, ves, nvs, boxes = [], [], [], [], [], [], [], [], []
    for _, cs, sn, oR, oT, oL, ply_seed, t0, t1 in plies:
        corners = [cs * r + sn * l + oR for r in r_range for l in l_range]
        r_lo, r_hi = min(corners), max(corners)
        tt_lo, tt_hi = max(t0, 0.0) + oT, min(t1, thickness_um) + oT
        pseed = np.uint64(ply_seed)
        patch, gi0, gj0 = _patch(pseed, M, r_lo - 1.0, r_hi + 1.0, tt_lo - 1.0, tt_hi + 1.0, stats)
        dmax = float(np.abs(patch).max())
        box = (math.floor((r_lo - dmax) / c) - 2, math.ceil((r_hi + dmax) / c) + 2,
               math.floor((tt_lo - dmax - 80.0 * params.scale) / c) - 2,
               math.ceil((tt_hi + dmax + 80.0 * params.scale) / c) + 2)
        vessels = np.empty((8192, 5), np.int64)
        nv = vessels_in_region(pseed, M, box[0] - VESSEL_REACH, box[1] + VESSEL_REACH,
                               box[2] - VESSEL_REACH, box[3] + VESSEL_REACH, vessels)
        rows.append((cs, sn, oR, oT, oL))
        seeds.append(pseed)
        spans.append((t0, t1))
        patches.append(patch)
        origins.append((gi0, gj0))
        lams.append(lipschitz_of_pull_back(patch, G))
        ves.append(vessels[:nv])
        nvs.append(nv)
        boxes.append(box)
    buckets = [_vessel_buckets(v, box) for v, box in zip(ves, boxes)]
    nptr = max(len(b[1]) for b in buckets)
    nlist = max(1, max(len(b[2]) for b in buckets))
    BP = np.zeros((len(plies), nptr), np.int64)
    BL = np.zeros((len(plies), nlist), np.int64)
    for q, (_, ptr, lst) in enumerate(buckets):
        BP[q, :len(ptr)] = ptr
        BL[q, :len(lst)] = lst
    ni = max(p.shape[0] for p in patches)
    nj = max(p.shape[1] for p in patches)
    P = np.zeros((len(plies), ni, nj, 2))
    for q, p in enumerate(patches):
        P[q, :p.shape[0], :p.shape[1]] = p
    V = np.zeros((len(plies), max(1, max(nvs)), 5), np.int64)
    for q, v in enumerate(ves):
        V[q, :len(v)] = v
    return {
        "M": M, "rates": rates(M), "plies": np.array(rows, np.float64), "seeds": np.array(seeds, np.uint64),
        "spans": np.array(spans, np.float64), "patches": P,
        "patch_shape": np.array([p.shape[:2] for p in patches], np.int64),
        "origins": np.array(origins, np.int64), "lipschitz": np.array(lams), "vessels": V,
        "n_vessels": np.array(nvs, np.int64), "boxes": np.array(boxes, np.int64),
        "ply_thickness": float(params.ply_thickness_um) if params.laminate is not None else math.inf,
        "first_ply": int(plies[0][0]), "bucket_shape": np.array([b[0] for b in buckets], np.int64),
        "bucket_ptr": BP, "bucket_list": BL,
    }


def _vessel_buckets(vessels: np.ndarray, box) -> tuple:
    """Per bucket of VBUCKET² nodes over ``box``, the starts of the clusters with a member within
    12 nodes of the bucket (ascending), as (grid shape, pointers, starts)."""
    nb = ((box[1] - box[0]) // VBUCKET + 1, (box[3] - box[2]) // VBUCKET + 1)
    lists = [[] for _ in range(nb[0] * nb[1])]
    v = 0
    while v < len(vessels):
        size = int(vessels[v, 4])
        mem = vessels[v:v + size, :2]
        i0 = max(0, (int(mem[:, 0].min()) - 12 - box[0]) // VBUCKET)
        i1 = min(nb[0] - 1, (int(mem[:, 0].max()) + 12 - box[0]) // VBUCKET)
        j0 = max(0, (int(mem[:, 1].min()) - 12 - box[2]) // VBUCKET)
        j1 = min(nb[1] - 1, (int(mem[:, 1].max()) + 12 - box[2]) // VBUCKET)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                lists[i * nb[1] + j].append(v)
        v += size
    ptr = np.zeros(len(lists) + 1, np.int64)
    ptr[1:] = np.cumsum([len(x) for x in lists])
    flat = np.array([v for x in lists for v in x], np.int64)
    return np.array(nb, np.int64), ptr, flat
