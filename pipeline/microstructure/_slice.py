"""Kernels of one slice (fixed L in ply coordinates): its tables, then the phase of every point
(lumens, end plates, fibre tips, vessels, ray cells; docs/methods.md#the-microstructure-model)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from .._intrinsics import any_inside4
from ..rng import uniform
from ._constants import (ENDS, FLEN, FLEN_SD, PITCH, PLATE, POLYMER, PUSH, RAYS, RRAMP, RSPACE, RSQUEEZE, SCALE,
                         SHAPE, ST_LATTICE, ST_NODES, TIP, VESSEL_AXIS_R, VWALL, WALL)
from ._distortion import pull_back
from ._lattice import chain_interval, is_centre, node_state, node_states
from ._ray_cells import ray_band_width, ray_cell_phase, ray_group, ray_row
from ._vessels import member_of

# --------------------------------------------------------------------------
# One slice (fixed L in ply coordinates): tables, then the per-point phase
@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def tip_walls(seed, n, m, L, lo, hi, tip, phase, mean, aR, aT, out):
    """The oblique walls where fibre (n, m) meets the fibres before and after it, at L.

    Consecutive fibres of a file overlap over 2·tip along L around their
    boundary b: their tapered tips slide past each other, separated by a wall
    whose trace in the slice is the line (p − c)·u = s with u a unit direction
    in the R-T plane drawn per boundary, and s = w·(b − L)/tip moving across
    the lumen (w its half-width along u) from one side at b − tip to the other
    at b + tip.  The wall plane is inclined to L by atan(w/tip).
    The cell [lo, hi) holds L; since a cell is at least ``tip`` long, only its
    own two boundaries can be that close.  out = (count, (uR, uT, s) per wall).
    """
    count = 0
    for side in range(2):
        b = lo if side == 0 else hi
        if abs(L - b) >= tip:
            continue
        q = np.int64(round((b - phase) / mean))  # the boundary's index in the chain
        phi = 2.0 * math.pi * uniform(seed, _rng.FIBRE_TIP, n, m, q)
        uR = math.cos(phi)
        uT = math.sin(phi)
        w = math.sqrt(aR * aR * uR * uR + aT * aT * uT * uT)
        out[1 + 3 * count] = uR
        out[2 + 3 * count] = uT
        out[3 + 3 * count] = w * (b - L) / tip
        count += 1
    out[0] = count


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def fibre_min_len(M):
    """The shortest fibre cell along L: a cell holds its two tips only."""
    min_len = min(50.0, 0.5 * M[FLEN])
    if M[TIP] > 0.0:
        min_len = max(min_len, min(M[TIP], 0.5 * M[FLEN]))
    return min_len


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def centre_tables(seed, M, L, n, m, flag, lo, hi, cR, cT, Nt, rR1, rR0, tT1, tT0, FErow, FJrow):
    """The per-centre tables of fibre (n, m) at L (see :func:`build_slice`): FErow and FJrow from
    its node (cR, cT, inset Nt), its neighbours' R (n ± 1) and T (m ± 1) and its cell [lo, hi)
    along L; ``flag`` 2 for a vessel member.  Returns (flag, aR, aT), the semi-axes as computed
    (<= 0: no lumen)."""
    polygon = M[SHAPE] == 1.0
    tip = M[TIP]
    if flag == 0 and tip == 0.0 and not math.isnan(lo) and (L - lo < 0.5 * M[PLATE] or hi - L < 0.5 * M[PLATE]):
        flag = 1
    raw_R = 0.0
    raw_T = 0.0
    aR = 0.0
    aT = 0.0
    if polygon:
        FErow[0] = cR
        FErow[1] = cT
    else:
        aR = 0.5 * (rR1 - rR0) - Nt
        aT = 0.5 * (tT1 - tT0) + M[PUSH] * M[SCALE] - Nt
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
    return flag, raw_R, raw_T


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def vessel_outline(rl, rr, td, tu, out):
    """A vessel member's outline (cR, cT, aR, aT) from the R of nodes (n ∓ 3, m) and the T of
    nodes (n, m ∓ 3)."""
    out[0] = 0.5 * (rl + rr)
    out[1] = 0.5 * (td + tu)
    out[2] = 0.5 * (rr - rl) * VESSEL_AXIS_R
    out[3] = 0.5 * (tu - td)


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)  # allocates nothing
def vessel_walls(VG, vessels, nv, VB):
    """The walls cluster neighbours share (VB, see :func:`build_slice`) from their outlines VG."""
    for v in range(nv):
        for side in range(2):
            u = v - 1 + 2 * side
            VB[v, side, 0] = 0.0
            if u < 0 or u >= nv or vessels[u, 2] != vessels[v, 2]:
                continue
            ex = VG[u, 0] - VG[v, 0]
            ey = VG[u, 1] - VG[v, 1]
            VB[v, side, 0] = 1.0
            VB[v, side, 1] = ex
            VB[v, side, 2] = ey
            VB[v, side, 3] = math.sqrt(ex * ex + ey * ey)
            VB[v, side, 4] = 0.5 * (VG[u, 0] + VG[v, 0])
            VB[v, side, 5] = 0.5 * (VG[u, 1] + VG[v, 1])


# --------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def build_slice(seed, M, L, n_lo, m_lo, NR, NT, Nt, FE, FF, FJ, vessels, nv, VG, VB, VIDX, rays, stats,
                CV, CF, cn, ck, ENDS_):
    """Fill the node, fibre, vessel and ray tables of one slice at L.

    NR, NT, Nt : node positions and wall insets on the window starting at (n_lo, m_lo).
    FE : per centre (cR, cT, 1/aR², 1/aT², bias) of the inset lumen ellipse; the
        bias is 0 for an open lumen and huge for a closed one.
    FF : per centre flag, 0 open lumen, 1 closed (end plate or no lumen), 2 vessel member.
    FJ : per centre the oblique tip walls crossing its lumen at L (``M[TIP]`` > 0):
        (count, then (uR, uT, s) per wall); a lumen point p is wall where
        |(p − centre)·u − s| < its inset t (see :func:`tip_walls`).
    VG : per vessel member (cR, cT, aR, aT) of its outline.
    VB : per vessel member and cluster neighbour (the one before, the one after):
        (1 if there is one else 0, eR, eT, |e|, mR, mT), e from this member's
        centre to the neighbour's and m their midpoint (the shared wall's bisector).
    VIDX : per lattice cell of the window, the first member of the vessel cluster
        whose outline may cover it, or -1.
    rays : rows (t_r, b, L0, L1, k, slot, taper) of ray groups active at L.
    CV, CF, cn, ck : the block's control values (see :func:`node_states`).
    ENDS_ : per centre (index as CV's) the fibre cell (lo, hi) along L last found;
        it holds for every L in [lo, hi), so slices inside it reuse it.
    Returns the number of active ray rows.
    """
    c = M[PITCH]
    nn, nm = NR.shape
    node_states(seed, M, L, n_lo, m_lo, NR, NT, Nt, CV, CF, cn, ck)
    stats[ST_NODES] += nn * nm
    min_len = fibre_min_len(M)
    for i in range(1, nn - 1):
        for j in range(1, nm - 1):
            n = n_lo + i
            m = m_lo + j
            if not is_centre(n, m):
                continue
            flag = 0
            lo = np.nan
            hi = np.nan
            if member_of(vessels, nv, n, m):
                flag = 2
            elif M[ENDS] != 0.0:
                a = n - cn
                lo = ENDS_[a, j, 0]
                hi = ENDS_[a, j, 1]
                if not (lo <= L < hi):  # also when not looked up yet (NaN)
                    ph = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * M[FLEN]
                    lo, hi = chain_interval(L, seed, _rng.FIBRE_END, n, m, ph, M[FLEN], M[FLEN_SD],
                                            min_len)
                    ENDS_[a, j, 0] = lo
                    ENDS_[a, j, 1] = hi
                    stats[ST_LATTICE] += 1
            FF[i, j], _, _ = centre_tables(seed, M, L, n, m, flag, lo, hi, NR[i, j], NT[i, j], Nt[i, j],
                                           NR[i + 1, j], NR[i - 1, j], NT[i, j + 1], NT[i, j - 1], FE[i, j],
                                           FJ[i, j])
    for v in range(nv):
        n = vessels[v, 0]
        m = vessels[v, 1]
        rl, _, _ = node_state(seed, M, n - 3, m, L)
        rr, _, _ = node_state(seed, M, n + 3, m, L)
        _, td, _ = node_state(seed, M, n, m - 3, L)
        _, tu, _ = node_state(seed, M, n, m + 3, L)
        vessel_outline(rl, rr, td, tu, VG[v])
    vessel_walls(VG, vessels, nv, VB)
    VIDX[:, :] = -1
    for v in range(nv):
        first = v - vessels[v, 3]
        i0 = max(np.int64(math.floor((VG[v, 0] - VG[v, 2]) / c)) - n_lo, 0)
        i1 = min(np.int64(math.floor((VG[v, 0] + VG[v, 2]) / c)) - n_lo, nn - 1)
        j0 = max(np.int64(math.floor((VG[v, 1] - VG[v, 3]) / c)) - m_lo, 0)
        j1 = min(np.int64(math.floor((VG[v, 1] + VG[v, 3]) / c)) - m_lo, nm - 1)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                VIDX[i, j] = first
    stats[ST_NODES] += 4 * nv
    nr = 0
    if M[RAYS] != 0.0:
        W = ray_band_width(M)
        k_lo = np.int64(math.floor(m_lo / M[RSPACE])) - 1
        k_hi = np.int64(math.ceil((m_lo + nm) / M[RSPACE])) + 1
        for k in range(k_lo, k_hi + 1):
            row = ray_row(seed, M, k)
            if row < m_lo - 8 or row > m_lo + nm + 8:
                continue
            L0, L1, g = ray_group(seed, M, k, L)
            if math.isnan(L0):
                continue
            nr = add_ray_row(M, L, L0, L1, row * c, k, g, W, rays, nr)
    return nr


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def add_ray_row(M, L, L0, L1, t_r, k, g, W, rays, nr):
    """Append the row (t_r, b, L0, L1, k, slot, taper) of a ray group active at L to ``rays``
    when its taper there is positive; returns the number of rows."""
    x = min(L - L0, L1 - L) / M[RRAMP]
    x = min(max(x, 0.0), 1.0)
    taper = x * x * (3.0 - 2.0 * x)
    if taper <= 0.0 or nr >= rays.shape[0]:
        return nr
    rays[nr, 0] = t_r
    rays[nr, 1] = 0.5 * W * taper
    rays[nr, 2] = L0
    rays[nr, 3] = L1
    rays[nr, 4] = k
    rays[nr, 5] = g
    rays[nr, 6] = taper
    return nr + 1


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _vessel_phase(pR, pT, VG, VB, vessels, first, wall):
    """-1 outside the vessel cluster starting at member ``first``, else the phase there."""
    inside = False
    f = np.uint64(first)
    for v in range(f, f + np.uint64(vessels[f, 4])):
        # |x| >= a > 0 gives (x / a)² >= 1 exactly: skip the divisions.
        if abs(pR - VG[v, 0]) >= VG[v, 2] or abs(pT - VG[v, 1]) >= VG[v, 3]:
            continue
        dR = (pR - VG[v, 0]) / VG[v, 2]
        dT = (pT - VG[v, 1]) / VG[v, 3]
        if dR * dR + dT * dT >= 1.0:
            continue
        inside = True
        aR = VG[v, 2] - wall
        aT = VG[v, 3] - wall
        if aR <= 0.0 or aT <= 0.0:
            continue
        if abs(pR - VG[v, 0]) >= aR or abs(pT - VG[v, 1]) >= aT:
            continue
        dR = (pR - VG[v, 0]) / aR
        dT = (pT - VG[v, 1]) / aT
        if dR * dR + dT * dT >= 1.0:
            continue
        # Cluster neighbours share a flat wall on the bisector of their centres.
        lumen = True
        for side in range(2):
            if VB[v, side, 0] != 0.0 and (((pR - VB[v, side, 4]) * VB[v, side, 1]
                                           + (pT - VB[v, side, 5]) * VB[v, side, 2])
                                          / VB[v, side, 3] > -0.5 * wall):
                lumen = False
        if lumen:
            return 0
    return 1 if inside else -1


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _squeeze_and_classify(pT, c, W2, lam, rays, nr):
    """Ray band test and squeeze pull-back.  Returns (pT after squeeze, ray row or -1, the
    squeeze's slope d(pT after)/d(pT) by the chain rule through its rows: 1 inside a band)."""
    for r in range(nr):
        if abs(pT - rays[np.uint64(r), 0]) < rays[np.uint64(r), 1]:
            return pT, r, 1.0
    slope = 1.0
    for rs in range(nr):
        ru = np.uint64(rs)
        d = pT - rays[ru, 0]
        x = abs(d) - rays[ru, 1]
        if x < lam:
            # Pull-back of the squeeze: the band edge maps to the removed row's edge.
            q = 1.0 - x / lam
            shift = rays[ru, 6] * (c - W2) * q * q * q
            slope *= 1.0 - 3.0 * rays[ru, 6] * (c - W2) * q * q / lam
            pT = pT + shift if d > 0 else pT - shift
    return pT, -1, slope


@njit(cache=True, nogil=True, error_model="numpy")
def candidate_table(FE, n_lo, m_lo, C4, FJ, CIJ):
    """The lumen ellipses that can hold a point, per lattice cell (for the fibre phase).

    A point in lattice cell (n, w) = (floor(R/c), floor(T/c)): lumens of row
    m = 2j reach |w - m| < 2 nodes, so only rows 2·j0 and 2·j0 + 2
    (j0 = w >> 1) and, in each, the two centres bracketing n can contain it.
    C4[n - n_lo, j0 - (m_lo >> 1)] holds those four ellipses' FE rows,
    fields-major (centre R ×4, centre T ×4, 1/aR² ×4, 1/aT² ×4, bias ×4), for
    :func:`~pipeline._intrinsics.any_inside4`; a candidate outside FE's window
    (never met by a point of the slice) gets a closed lumen's bias.
    CIJ[a, b, t] : with fibre tips (FJ has rows), the FE index (i, j) of
    candidate t if its lumen is crossed by a tip wall, else -1 (shape 0: no tips).
    """
    nn, nm = FE.shape[0], FE.shape[1]
    jb0 = m_lo >> 1
    for a in range(C4.shape[0]):
        n_fl = n_lo + a
        for b in range(C4.shape[1]):
            for dj in range(2):
                j = jb0 + b + dj
                mi = 2 * j - m_lo
                for di in range(2):
                    t = 2 * dj + di
                    ii = n_fl - ((n_fl - j) & 1) - n_lo + 2 * di
                    inside = 0 <= ii < nn and 0 <= mi < nm
                    for f in range(5):
                        C4[a, b, f, t] = FE[ii, mi, f] if inside else 0.0
                    if not inside:
                        C4[a, b, 4, t] = 1e300
                    if CIJ.shape[0] > 0:
                        crossed = inside and FJ[ii, mi, 0] > 0.0
                        CIJ[a, b, t, 0] = ii if crossed else -1
                        CIJ[a, b, t, 1] = mi


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _polygon_phase(pR, pT, u, w, n_lo, m_lo, FE, FF, Nt, cand_i, cand_j):
    """Thin uniform walls on the Voronoi faces of the jittered centres (balsa).

    cand_i, cand_j : int64[9] scratch for the candidate centres.
    """
    jc = np.int64(round(w / 2.0))
    nc = 0
    best = -1
    bd = 1e300
    for j in range(jc - 1, jc + 2):
        m = 2 * j
        par = j % 2
        n0 = 2 * np.int64(round((u - par) / 2.0)) + par
        for n in (n0 - 2, n0, n0 + 2):
            ii = n - n_lo
            jj = m - m_lo
            dR = pR - FE[ii, jj, 0]
            dT = pT - FE[ii, jj, 1]
            d2 = dR * dR + dT * dT
            cand_i[nc] = ii
            cand_j[nc] = jj
            if d2 < bd:
                bd = d2
                best = nc
            nc += 1
    bi = cand_i[best]
    bj = cand_j[best]
    if FF[bi, bj] != 0:
        return WALL
    for q in range(nc):
        if q != best and face_distance(pR, pT, FE, bi, bj, cand_i[q], cand_j[q], bd) < 0.5 * (
                Nt[bi, bj] + Nt[cand_i[q], cand_j[q]]):
            return WALL
    return POLYMER


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def face_distance(pR, pT, FE, bi, bj, ii, jj, bd):
    """Distance from (pR, pT) to the Voronoi face between centres (bi, bj) (nearest, at squared
    distance ``bd``) and (ii, jj) of FE, positive on the nearest's side."""
    ex = FE[ii, jj, 0] - FE[bi, bj, 0]
    ey = FE[ii, jj, 1] - FE[bi, bj, 1]
    dR = pR - FE[ii, jj, 0]
    dT = pT - FE[ii, jj, 1]
    return (dR * dR + dT * dT - bd) / (2.0 * math.sqrt(ex * ex + ey * ey))


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _in_tip_wall(pR, pT, a, b, FE, Nt, FJ, CIJ):
    """Whether a lumen point lies in an oblique tip wall of the candidate lumen holding it."""
    for t in range(4):
        ii = CIJ[a, b, t, 0]
        if ii < 0:
            continue
        mi = np.uint64(CIJ[a, b, t, 1])
        iu = np.uint64(ii)
        dR = pR - FE[iu, mi, 0]
        dT = pT - FE[iu, mi, 1]
        if dR * dR * FE[iu, mi, 2] + dT * dT * FE[iu, mi, 3] + FE[iu, mi, 4] >= 1.0:
            continue
        for w in range(np.int64(FJ[iu, mi, 0])):
            d = dR * FJ[iu, mi, 1 + 3 * w] + dT * FJ[iu, mi, 2 + 3 * w] - FJ[iu, mi, 3 + 3 * w]
            if abs(d) < Nt[iu, mi]:
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _eval_bucket(out, order, start, stop, nL, j_lo, j_hi, rotated, Rp, Tp, P1, patch, gi0, gj0, G,
                 seed, M, n_lo, m_lo, FE, FF, Nt, vessels, VG, VB, VIDX, rays, nr, RC, C4, SQ, SR, reuse,
                 FJ, CIJ, need, ns):
    """Phases of the voxels of one slice bucket.

    Per point: a ray band (:func:`ray_cell_phase`), else the vessel cluster
    whose outline may cover the point's lattice cell (:func:`_vessel_phase`),
    else the fibre lattice (the four candidate lumens of :func:`candidate_table`
    in one vector test, or the polygon cells of :func:`_polygon_phase`).  The
    helpers are inlined and read per-slice tables, so a point costs no call.
    Indices on this path are cast to uint64: Numba wraps negative signed
    indices around, a test on every access that unsigned ones skip.

    SQ, SR : per (R, T) column of an unrotated ply, the squeezed T and ray row
        (-1: none) of :func:`_squeeze_and_classify`; written on every slice, read
        instead of it when ``reuse`` (this slice's ray table is the last one's).
    need, ns : with ``ns`` > 0, only voxel (i, j, k) with ``need[i // ns, j // ns, k // ns]`` is
        classified (the others are left as they are; the caller passes ``reuse`` False).
    """
    c = M[PITCH]
    inv_c = 1.0 / c
    W2 = 0.5 * ray_band_width(M)
    lam = M[RSQUEEZE] * M[SCALE]
    polygon = M[SHAPE] == 1.0
    vwall = M[VWALL]
    has_vessels = vessels.shape[0] > 0
    tips = CIJ.shape[0] > 0
    memo = np.full((8, 4), np.nan)
    cand_i = np.empty(9, np.int64)
    cand_j = np.empty(9, np.int64)
    for s in range(start, stop):
        idx = np.uint64(order[s])
        i = idx // np.uint64(nL)
        k = idx % np.uint64(nL)
        for jj in range(j_lo, j_hi):
            j = np.uint64(jj)
            if ns > 0 and need[i // np.uint64(ns), j // np.uint64(ns), k // np.uint64(ns)] == 0:
                continue
            if rotated:
                pR, pT = pull_back(patch, gi0, gj0, G, Rp[i, k], Tp[j])
            else:
                pR = P1[i, j, 0]
                pT = P1[i, j, 1]
            if reuse:
                sT = SQ[i, j]
                r = SR[i, j]
            else:
                sT, r, _ = _squeeze_and_classify(pT, c, W2, lam, rays, nr)
                if not rotated:
                    SQ[i, j] = sT
                    SR[i, j] = r
            if r >= 0:
                out[i, j, k] = ray_cell_phase(seed, M, pR, sT, np.uint64(r), rays, RC, memo)
                continue
            n_fl = np.int64(math.floor(pR * inv_c))
            w_fl = np.int64(math.floor(sT * inv_c))
            if has_vessels:
                first = VIDX[np.uint64(n_fl - n_lo), np.uint64(w_fl - m_lo)]
                if first >= 0:
                    ph = _vessel_phase(pR, sT, VG, VB, vessels, first, vwall)
                    if ph >= 0:
                        out[i, j, k] = np.uint8(ph)
                        continue
            if polygon:
                out[i, j, k] = _polygon_phase(pR, sT, pR * inv_c, sT * inv_c, n_lo, m_lo, FE, FF, Nt,
                                              cand_i, cand_j)
            else:
                cell = (np.uint64(n_fl - n_lo), np.uint64((w_fl >> 1) - (m_lo >> 1)),
                        np.uint64(0), np.uint64(0))
                inside = any_inside4(C4, cell, pR, sT)
                if inside and tips:
                    inside = not _in_tip_wall(pR, sT, cell[0], cell[1], FE, Nt, FJ, CIJ)
                out[i, j, k] = POLYMER if inside else WALL
