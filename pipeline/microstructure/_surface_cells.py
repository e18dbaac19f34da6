"""The fibre cells at one point: the generator's per-centre tables built for the lumens near the
point, their phase (ellipses or balsa polygons) and their rows, with memos of the pure functions
they read (docs/methods.md#the-wood-as-surfaces)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from .._intrinsics import any_inside4, carve
from ..rng import uniform
from ._constants import (CTRL, ENDS, FLEN, FLEN_SD, JITTER, PITCH, PLATE, SHAPE, T0, TIP, WALLVAR)
from ._lattice import _controls, _spline, chain_interval, is_centre
from ._ray_cells import group_at, group_span, ray_slot
from ._slice import _in_tip_wall, _polygon_phase, centre_tables, face_distance, fibre_min_len
from ._vessels import member_of

from ._surface_rows import (P_FACE, P_LUMEN, P_PLATE, P_REACH, P_TIP, P_TIP_END, R_NODE, R_TIP, R_WALL,
                            _ellipse_margin, _row, _row_x)

CACHE_SLOTS = 1 << 15  # direct-mapped cache of control values and fibre cells (a power of 2)
NEAR = 16  # the near cache: nodes (n mod NEAR, m mod NEAR) with their four control values at one slice
# An evaluation's work arrays, views of three flat per-thread arrays (floats, ints, bytes) of the
# cache: no evaluation allocates, so its kernels compile without Numba's reference counts
# (``_nrt=False``; a count is an atomic add and a call per array a function receives).  Offsets:
# :func:`~pipeline.microstructure.surface.evaluate`'s own, live while it calls one of
# _ellipses, _polygon or _ray_cell, which share the region after them.
F_RAYS, F_VG, F_VB, F_CALLEE = 0, 112, 304, 880  # rays (16, 7); VG (<= 48, 4); VB (<= 48, 2, 6)
I_VSEL, I_VL, I_CALLEE = 0, 48, 288  # vsel (48); VL (<= 48, 5)
# A memo in the same buffers: the spans of ray groups (group_span draws a normal deviate, a log
# and a cosine, for each column near a point), direct-mapped on (column, slot, seed).
SPANS = 256  # entries (a power of 2)
F_SPANS, I_SPANS = F_CALLEE + 1388, I_CALLEE + 18  # (L0, L1) and (k, g, seed) per entry
N_FLOATS, N_INTS, N_BYTES = F_SPANS + 2 * SPANS, I_SPANS + 3 * SPANS, 272
NOREF = dict(cache=True, nogil=True, error_model="numpy", _nrt=False)  # the evaluation's kernels


def new_cache():
    """Per-thread memo of pure functions of ids (control values of (node, slice), the fibre cell
    around L) and an evaluation's work arrays: (keys, control values, cell keys, cells, scratch,
    near keys, near control values, work floats, work ints, work bytes).
    The near cache holds, per node of a small window that moves with the points, the four
    control values its spline reads at one control slice: the nodes of one point, and of the
    next points along a ray, are found there without hashing.  It changes no result."""
    return (np.full((CACHE_SLOTS, 4), np.iinfo(np.int64).min, np.int64), np.empty((CACHE_SLOTS, 3)),
            np.full((CACHE_SLOTS, 3), np.iinfo(np.int64).min, np.int64), np.empty((CACHE_SLOTS, 2)),
            np.empty((4, 3)), np.full((NEAR * NEAR, 4), np.iinfo(np.int64).min, np.int64),
            np.empty((NEAR * NEAR, 4, 3)), np.empty(N_FLOATS), _work_ints(), np.empty(N_BYTES, np.uint8))


def _work_ints():
    out = np.empty(N_INTS, np.int64)
    out[I_SPANS:] = np.iinfo(np.int64).min  # no span memoised
    return out


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _slot(a, b, c, d):
    h = (np.uint64(a) * np.uint64(0x9E3779B97F4A7C15)) ^ (np.uint64(b) * np.uint64(0xC2B2AE3D27D4EB4F)) \
        ^ (np.uint64(c) * np.uint64(0x165667B19E3779F9)) ^ np.uint64(d)
    h ^= h >> np.uint64(29)
    return np.int64(h & np.uint64(CACHE_SLOTS - 1))


@njit(**NOREF)
def _near_fill(seed, n, m, k, j, CK, CV, C, NK, NV):
    """Slot j of the near cache: node (n, m)'s control values at slices k - 1 .. k + 2, from the
    large cache or hashed (and kept there)."""
    sd = np.int64(seed)
    NK[j, 0] = n
    NK[j, 1] = m
    NK[j, 2] = k
    NK[j, 3] = sd
    for q in range(4):
        kq = k + q - 1
        i = _slot(n, m, kq, sd)
        if not (CK[i, 0] == n and CK[i, 1] == m and CK[i, 2] == kq and CK[i, 3] == sd):
            _controls(seed, n, m, kq, C[q])
            CK[i, 0] = n
            CK[i, 1] = m
            CK[i, 2] = kq
            CK[i, 3] = sd
            for f in range(3):
                CV[i, f] = C[q, f]
        for f in range(3):
            NV[j, q, f] = CV[i, f]


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def node_cached(seed, M, n, m, L, CK, CV, C, NK, NV):
    """:func:`~pipeline.microstructure._lattice.node_state`, its control values memoised in the
    arrays of the cache tuple (:func:`new_cache`).

    Inlined where it is called, with its misses in :func:`_near_fill`: a call across a function
    boundary costs an atomic reference count per array it touches, more than the node itself.
    It takes the memo's arrays, not the cache tuple: an inlined function copies every tuple it
    is given at each place it is inlined (a whole cache tuple per node cost 4 ns an array)."""
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    j = (n & (NEAR - 1)) * NEAR + (m & (NEAR - 1))
    if not (NK[j, 0] == n and NK[j, 1] == m and NK[j, 2] == k and NK[j, 3] == np.int64(seed)):
        _near_fill(seed, n, m, k, j, CK, CV, C, NK, NV)
    # _node_from on the table's row, read in place (no array views).
    c = M[PITCH]
    r = 0.0
    t = 0.0
    w = 0.0
    for q in range(4):
        wq = w0 if q == 0 else (w1 if q == 1 else (w2 if q == 2 else w3))
        r += wq * NV[j, q, 0]
        t += wq * NV[j, q, 1]
        w += wq * NV[j, q, 2]
    return n * c + M[JITTER] * c * r, m * c + M[JITTER] * c * t, M[T0] * (1.0 + M[WALLVAR] * w)


@njit(**NOREF)
def _cell_fill(seed, M, L, n, m, min_len, i, EK, EV):
    """Slot i of the fibre-cell cache: fibre (n, m)'s cell around L."""
    ph = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * M[FLEN]
    lo, hi = chain_interval(L, seed, _rng.FIBRE_END, n, m, ph, M[FLEN], M[FLEN_SD], min_len)
    EK[i, 0] = n
    EK[i, 1] = m
    EK[i, 2] = np.int64(seed)
    EV[i, 0] = lo
    EV[i, 1] = hi


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _fibre_cell(seed, M, L, n, m, min_len, EK, EV):
    """:func:`chain_interval` of fibre (n, m) at L, memoised (a cell holds for every L inside it)."""
    i = _slot(n, m, 7, np.int64(seed))
    if not (EK[i, 0] == n and EK[i, 1] == m and EK[i, 2] == np.int64(seed) and EV[i, 0] <= L < EV[i, 1]):
        _cell_fill(seed, M, L, n, m, min_len, i, EK, EV)
    return EV[i, 0], EV[i, 1]


@njit(**NOREF)
def _span_fill(seed, M, k, g, i, WF, WI):
    L0, L1 = group_span(seed, M, k, g)
    WI[I_SPANS + 3 * i] = k
    WI[I_SPANS + 3 * i + 1] = g
    WI[I_SPANS + 3 * i + 2] = np.int64(seed)
    WF[F_SPANS + 2 * i] = L0
    WF[F_SPANS + 2 * i + 1] = L1


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def span_cached(seed, M, k, g, WF, WI):
    """:func:`~pipeline.microstructure._ray_cells.group_span`, memoised in the work buffers."""
    i = _slot(k, g, 11, np.int64(seed)) & (SPANS - 1)
    if not (WI[I_SPANS + 3 * i] == k and WI[I_SPANS + 3 * i + 1] == g and WI[I_SPANS + 3 * i + 2] == np.int64(seed)):
        _span_fill(seed, M, k, g, i, WF, WI)
    return WF[F_SPANS + 2 * i], WF[F_SPANS + 2 * i + 1]


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def group_cached(seed, M, k, L, WF, WI):
    """:func:`~pipeline.microstructure._ray_cells.ray_group` with its span memoised."""
    g = ray_slot(seed, M, k, L)
    L0, L1 = span_cached(seed, M, k, g, WF, WI)
    return group_at(L, L0, L1, g)


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _nodes(seed, M, L, n0, m0, NW, have, n, m, CK, CV, C, NK, NV):
    """Node (n, m)'s (R, T, inset) at L, from the small window cache NW (origin n0, m0)."""
    i = n - n0
    j = m - m0
    inside = 0 <= i < NW.shape[0] and 0 <= j < NW.shape[1]
    if inside and have[i, j] != 0:
        return NW[i, j, 0], NW[i, j, 1], NW[i, j, 2]
    a, b, c = node_cached(seed, M, n, m, L, CK, CV, C, NK, NV)  # one call site: it is inlined
    if inside:
        NW[i, j, 0] = a
        NW[i, j, 1] = b
        NW[i, j, 2] = c
        have[i, j] = 1
    return a, b, c


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _fibre(seed, M, L, n, m, vessels, nv, NW, have, n0, m0, FErow, FJrow, CK, CV, C, NK, NV, EK, EV):
    """The generator's per-centre tables (build_slice) for centre (n, m) at L.

    Writes FErow (cR, cT, 1/aR², 1/aT², bias) and FJrow (tip walls); returns
    (flag, lo, hi, aR, aT, Nt) with flag 0 open, 1 closed, 2 vessel member, and the lumen's
    semi-axes as computed (<= 0: no lumen).
    """
    flag = 0
    lo = np.nan
    hi = np.nan
    if member_of(vessels, nv, n, m):
        flag = 2
    elif M[ENDS] != 0.0:
        lo, hi = _fibre_cell(seed, M, L, n, m, fibre_min_len(M), EK, EV)
    cR, cT, Nt = _nodes(seed, M, L, n0, m0, NW, have, n, m, CK, CV, C, NK, NV)
    rR1 = rR0 = tT1 = tT0 = 0.0
    if M[SHAPE] != 1.0:
        rR1, _, _ = _nodes(seed, M, L, n0, m0, NW, have, n + 1, m, CK, CV, C, NK, NV)
        rR0, _, _ = _nodes(seed, M, L, n0, m0, NW, have, n - 1, m, CK, CV, C, NK, NV)
        _, tT1, _ = _nodes(seed, M, L, n0, m0, NW, have, n, m + 1, CK, CV, C, NK, NV)
        _, tT0, _ = _nodes(seed, M, L, n0, m0, NW, have, n, m - 1, CK, CV, C, NK, NV)
    flag, aR, aT = centre_tables(seed, M, L, n, m, flag, lo, hi, cR, cT, Nt, rR1, rR0, tT1, tT0, FErow, FJrow)
    return flag, lo, hi, aR, aT, Nt


# Inlined into evaluate, its one caller: as a call it was given the cache's ten arrays, five more
# and nine numbers, some 115 words copied at every point (docs/performance.md: about 13 % of the
# march).  The other phases (_polygon, _ray_cell) stay calls: inlined too, evaluate was slower.
@njit(inline="always", **NOREF)
def _ellipses(seed, M, L, pR, sT, n_fl, w_fl, VL, ns, k_in, rt, P, np_, cache, want, sq_slope):
    """Fibre lumens: the phase from the four candidates of the point's cell, the rows from the
    lumens that reach the 2 × 2 cells around the point (a ball of half a cell meets no other).
    Each lumen's row holds its offset and semi-axes (C_DR..), the reach row the squeeze's slope
    ``sq_slope`` at the point (for a ray's proven steps, pipeline/microstructure/surface_ray.py)."""
    c = M[PITCH]
    j0 = w_fl >> 1
    fr = pR / c - n_fl
    fw = sT / c - w_fl
    na = n_fl - 1 if fr < 0.5 else n_fl
    wa = w_fl - 1 if fw < 0.5 else w_fl
    m_first = 2 * (wa >> 1)
    m_last = 2 * ((wa + 1) >> 1) + 2
    n_first = na - 1
    n_last = na + 3
    wanted = want[0] > 0.0
    if wanted:  # the wanted centre alone, wherever it is
        n_first = np.int64(want[1])
        n_last = n_first
        m_first = np.int64(want[2])
        m_last = m_first
    n0 = n_first - 1
    m0 = m_first - 1
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    f0 = F_CALLEE
    NW = carve(WF, f0, (8, 8, 3))
    have = carve(WU, 0, (8, 8))
    have[:] = 0
    C4 = carve(WF, f0 + 192, (1, 1, 5, 4))
    FE4 = carve(WF, f0 + 212, (4, 1, 5))
    Nt4 = carve(WF, f0 + 232, (4, 1))
    FJ4 = carve(WF, f0 + 236, (4, 1, 7))
    FJ4[:] = 0.0
    CIJ = carve(WI, I_CALLEE, (1, 1, 4, 2))
    CIJ[:] = -1
    FE = carve(WF, f0 + 264, (5,))
    FJ = carve(WF, f0 + 269, (7,))
    FJ[:] = 0.0
    rn = rt[R_NODE]
    rw = rt[R_WALL]
    plate = 0.5 * M[PLATE]
    tip = M[TIP]
    tips = tip > 0.0 and M[ENDS] != 0.0
    inside = False
    for m in range(m_first, m_last + 1, 2):
        mj = (m >> 1) - j0
        for n in range(n_first, n_last + 1):
            if not is_centre(n, m):
                continue
            flag, lo, hi, aR, aT, Nt = _fibre(seed, M, L, n, m, VL, ns, NW, have, n0, m0, FE, FJ, CK, CV, C, NK, NV,
                                              EK, EV)
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
                np_ = _row_x(P, np_, P_LUMEN, n, m, 0, 0, max(dist, 0.0) + 1.0, clr, 0.0, 0.0, 0.0, 0.0)
                continue
            ge = _ellipse_margin(dR, dT, aR, aT)
            clr = abs(ge) / kk
            if not math.isnan(lo) and tip == 0.0:  # end plates: the lumen between its two planes
                g1 = (L - lo) - plate
                g2 = (hi - L) - plate
                if ge < 0.0 or wanted:
                    np_ = _row(P, np_, P_PLATE, n, m, 0, 0, g1, abs(g1))
                    np_ = _row(P, np_, P_PLATE, n, m, 1, 0, g2, abs(g2))
                elif flag == 1:  # outside a closed lumen: it must open and be entered
                    viol = max(-g1 if g1 < 0.0 else 0.0, -g2 if g2 < 0.0 else 0.0)
                    clr = max(clr, viol)
            np_ = _row_x(P, np_, P_LUMEN, n, m, 0, 0, ge, clr, dR, dT, aR, aT)
            if (ge < 0.0 or wanted) and tips and not math.isnan(lo):
                for side in range(2):
                    b = lo if side == 0 else hi
                    gt = abs(L - b) - tip
                    np_ = _row(P, np_, P_TIP_END, n, m, side, 0, gt, abs(gt))
                for w in range(np.int64(FJ[0])):
                    d = dR * FJ[1 + 3 * w] + dT * FJ[2 + 3 * w] - FJ[3 + 3 * w]
                    gs = abs(d) - Nt
                    np_ = _row(P, np_, P_TIP, n, m, w, 0, gs, abs(gs) / (k_in + rt[R_TIP]))
    np_ = _row_x(P, np_, P_REACH, 1, 0, 0, 0, 0.5 * c, 0.5 * c / (k_in + 2.0 * rn + rw), sq_slope, pR, sT, 0.0)
    if wanted:
        return np.uint8(0), np_
    inside = any_inside4(C4, (np.uint64(0), np.uint64(0), np.uint64(0), np.uint64(0)), pR, sT)
    if inside and tips:
        inside = not _in_tip_wall(pR, sT, np.uint64(0), np.uint64(0), FE4, Nt4, FJ4, CIJ)
    return np.uint8(0) if inside else np.uint8(1), np_


@njit(**NOREF)
def _polygon(seed, M, L, pR, sT, VL, ns, k_in, rt, P, np_, cache, sq_slope):
    """Balsa: the generator's Voronoi test on the nine candidate centres, and their faces; the reach
    row holds the squeeze's slope ``sq_slope`` at the point, as the fibre cells' does."""
    c = M[PITCH]
    inv_c = 1.0 / c
    u = pR * inv_c
    w = sT * inv_c
    jc = np.int64(round(w / 2.0))
    n_lo = np.int64(math.floor(u)) - 6
    m_lo = 2 * (jc - 1) - 1
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    f0 = F_CALLEE
    FE = carve(WF, f0, (14, 8, 5))
    FE[:] = 0.0
    FF = carve(WU, 0, (14, 8))
    FF[:] = 0
    Nt = carve(WF, f0 + 560, (14, 8))
    Nt[:] = 0.0
    LO = carve(WF, f0 + 672, (14, 8, 2))
    LO[:] = np.nan
    NW = carve(WF, f0 + 896, (16, 10, 3))
    have = carve(WU, 112, (16, 10))
    have[:] = 0
    FJ = carve(WF, f0 + 1376, (7,))
    FJ[:] = 0.0
    FErow = carve(WF, f0 + 1383, (5,))
    for j in range(jc - 1, jc + 2):
        m = 2 * j
        par = j % 2
        n0 = 2 * np.int64(round((u - par) / 2.0)) + par
        for n in (n0 - 2, n0, n0 + 2):
            flag, lo, hi, _, _, t = _fibre(seed, M, L, n, m, VL, ns, NW, have, n_lo - 1, m_lo - 1, FErow, FJ,
                                           CK, CV, C, NK, NV, EK, EV)
            ii = n - n_lo
            jj = m - m_lo
            for f in range(5):
                FE[ii, jj, f] = FErow[f]
            FF[ii, jj] = flag
            Nt[ii, jj] = t
            LO[ii, jj, 0] = lo
            LO[ii, jj, 1] = hi
    cand_i = carve(WI, I_CALLEE, (9,))
    cand_j = carve(WI, I_CALLEE + 9, (9,))
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
        e = math.hypot(FE[ii, jj, 0] - FE[bi, bj, 0], FE[ii, jj, 1] - FE[bi, bj, 1])
        g = face_distance(pR, sT, FE, bi, bj, ii, jj, bd) - 0.5 * (Nt[bi, bj] + Nt[ii, jj])
        far = math.hypot(pR - 0.5 * (FE[ii, jj, 0] + FE[bi, bj, 0]), sT - 0.5 * (FE[ii, jj, 1] + FE[bi, bj, 1]))
        rate = rn * (1.0 + 2.0 * far / e) + rw
        np_ = _row_x(P, np_, P_FACE, bi + n_lo, bj + m_lo, ii + n_lo, jj + m_lo, g, abs(g) / (k_in + rate),
                     (FE[ii, jj, 0] - FE[bi, bj, 0]) / e, (FE[ii, jj, 1] - FE[bi, bj, 1]) / e, rate, 0.0)
    if not math.isnan(LO[bi, bj, 0]):  # the nearest cell's end plates
        plate = 0.5 * M[PLATE]
        g1 = (L - LO[bi, bj, 0]) - plate
        g2 = (LO[bi, bj, 1] - L) - plate
        np_ = _row(P, np_, P_PLATE, bi + n_lo, bj + m_lo, 0, 0, g1, abs(g1))
        np_ = _row(P, np_, P_PLATE, bi + n_lo, bj + m_lo, 1, 0, g2, abs(g2))
    np_ = _row_x(P, np_, P_REACH, 2, 0, 0, 0, 0.5 * c, 0.5 * c / (k_in + 4.0 * rn + rw), sq_slope, pR, sT, 0.0)
    return ph, np_


