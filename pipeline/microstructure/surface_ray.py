"""The wood's primitives along a ray: proven steps to the first roots of its lumens (fibre and
ray-cell), ray bands, balsa's faces and end plates, and how far its reach rows hold
(docs/methods.md#proven-steps-along-the-ray).

A point evaluation bounds each primitive by a ball: its margin over how fast anything can move,
whichever way the ray goes.  Along a known direction a fibre lumen's first root is bounded far
more closely.  In the ply's frame the ray is x(s) = x₀ + s·u.  The pull-back p = x − D(x), D
bilinear on the distortion grid, is p₀ + s·(I − ∇D(x₀))·u up to a remainder: ∇D jumps by at most
the grid's second difference (Kxx, Kyy over G) where the ray crosses a grid line, and turns by at
most the cross difference (Kxy over G²) per µm inside a cell (the tile's bounds,
:func:`~pipeline.microstructure.region._tile_curvature`).  The squeeze scales T by its slope at
the point up to its own curvature; the lumen's centre and semi-axes move with L at the model's
rates.  Summed, the pulled-back point departs from the line p₀ + s·v by at most e(s), e rising.

A lumen's margin (√q − 1)·min(a) is 1-Lipschitz in the pulled-back point, so over [0, S] its g
stays positive wherever the line stays outside the ellipse grown by the factor 1 + e(S)/min(a):
the line's first root on that ellipse (a quadratic), capped at S, is a proven step for the lumen.
"""

import math

from numba import njit

from ._constants import PITCH, RAYS, RSQUEEZE, SCALE, T0, TILE
from ._distortion import pull_back_slopes
from ._ray_cells import ray_band_width
from ._surface_cells import NOREF
from ._surface_rows import (C_AR, C_AT, C_CROSS, C_DR, C_DT, C_PR, C_SQUEEZE, C_ST, P_BAND, P_FACE, P_LUMEN, P_PLATE,
                            P_RAY_LUMEN, P_REACH, P_TIP_END,
                            R_BAND, R_NODE, R_SQ, R_SQ_L,
                            R_WALL)
from .surface import _ply_of

STEP_CELLS = 16  # a proven step reaches at most this many grid cells (within region.CURVE_REACH)
N_FRAME = 19  # floats of a ray's frame at a point (:func:`ray_frame`)
(F_VR, F_VT, F_VPT, F_AX, F_AY, F_T1X, F_T1Y, F_KXX, F_KYY, F_KXY, F_G, F_RSQ, F_C2, F_LF, F_LB, F_CAP, F_UL,
 F_VL, F_RN) = range(N_FRAME)


@njit(inline="always", **NOREF)
def ray_frame(R, T, L, d, ctx, P, n, F):
    """The frame at (R, T, L) for the direction ``d``, given the rows P[:n] evaluated there, into F:
    the pulled-back velocity and the remainder's coefficients (:func:`pull_remainder`).  Raises
    the reach rows' clearances.  False where the point is outside the grid."""
    (M, rt, plies, seeds, spans, patches, pshape, origins, lips, vessels, nvs, boxes, th, first, bsh, bptr,
     blist, curv) = ctx
    reach = -1  # the fibre cells' reach row
    squeeze = 1.0  # inside a ray band there is none
    for i in range(n):
        if P[i, 0] == P_REACH and (P[i, 1] == 1.0 or P[i, 1] == 2.0):
            squeeze = P[i, C_SQUEEZE]
            if P[i, 1] == 1.0:
                reach = i
    q = _ply_of(T, spans, th, first, plies.shape[0])
    cs, sn = plies[q, 0], plies[q, 1]
    Rp = cs * R + sn * L + plies[q, 2]
    Tp = T + plies[q, 3]
    uR = cs * d[0] + sn * d[2]
    uT = d[1]
    uL = -sn * d[0] + cs * d[2]
    G = M[PITCH] / 8.0
    gi0, gj0 = origins[q, 0], origins[q, 1]
    x = Rp / G
    y = Tp / G
    ix = math.floor(x)
    iy = math.floor(y)
    i = ix - gi0
    j = iy - gj0
    if i < 0 or j < 0 or i >= pshape[q, 0] - 1 or j >= pshape[q, 1] - 1:
        return False
    rx, ry, tx, ty = pull_back_slopes(patches[q], gi0, gj0, G, Rp, Tp)
    vR = uR - (rx * uR + ry * uT)
    vpT = uT - (tx * uR + ty * uT)
    ti = i // TILE
    tj = j // TILE
    lam_p = lips[q, ti, tj]
    rsq = rt[R_SQ] if M[RAYS] != 0.0 else 1.0
    # Within a cell the ray meets the next grid line after t1 [µm] along each axis.
    fx = x - ix
    fy = y - iy
    F[F_T1X] = (1.0 - fx) * G / uR if uR > 0.0 else (fx * G / -uR if uR < 0.0 else 1e300)
    F[F_T1Y] = (1.0 - fy) * G / uT if uT > 0.0 else (fy * G / -uT if uT < 0.0 else 1e300)
    F[F_VR] = vR
    F[F_VPT] = vpT
    F[F_VT] = vpT * squeeze
    F[F_AX] = abs(uR)
    F[F_AY] = abs(uT)
    F[F_UL] = abs(uL)
    F[F_VL] = uL
    F[F_KXX] = curv[q, ti, tj, 0]
    F[F_KYY] = curv[q, ti, tj, 1]
    F[F_KXY] = curv[q, ti, tj, 2] / G
    F[F_G] = G
    F[F_RSQ] = rsq
    # The squeeze's curvature (two bands at most reach a point) over the pulled-back T's travel;
    # what moves with L: a fibre lumen (centre and semi-axes) and the squeeze, a band's edges.
    c2 = 0.0
    if M[RAYS] != 0.0:
        lam = M[RSQUEEZE] * M[SCALE]
        c2 = 2.0 * 6.0 * abs(M[PITCH] - 0.5 * ray_band_width(M)) / (lam * lam)
    F[F_C2] = 0.5 * c2 * lam_p * lam_p
    F[F_LF] = (2.0 * rt[R_NODE] + rt[R_WALL] + rt[R_SQ_L] + (rsq - 1.0) * rt[R_BAND]) * abs(uL)
    F[F_LB] = rt[R_BAND] * abs(uL)
    F[F_RN] = rt[R_NODE] * abs(uL)
    F[F_CAP] = 0.0
    if reach >= 0:
        _fibre_reach(M[PITCH], P, reach, F)
    for i in range(n):
        if P[i, 0] == P_REACH and P[i, 1] == 2.0:
            _balsa_reach(M[PITCH], P, i, F)
    return True


@njit(inline="always", **NOREF)
def _balsa_reach(c, P, i, F):
    """Balsa's reach row i: no centre but the nine listed lies within half a cell of the point, and
    the centres move at most 2·R_NODE more than a lumen with L, so half a cell over the pulled-back
    speed, less e, is a proven step for every face not listed."""
    cap = STEP_CELLS * F[F_G]
    speed = math.sqrt(F[F_VR] * F[F_VR] + F[F_VT] * F[F_VT]) + 2.0 * F[F_RN]
    if speed > 0.0:
        half = 0.5 * c
        S = min(half / speed, cap)
        S = min(S, (half - fibre_remainder(F, S)) / speed)
        if S > P[i, 6]:
            P[i, 6] = S
    F[F_CAP] = min(P[i, 6], cap)


@njit(inline="always", **NOREF)
def _fibre_reach(c, P, reach, F):
    """The fibre cells' reach row: the lumens listed are every lumen that reaches the 2 × 2 lattice
    cells around the point (its inner quarter); the pulled-back point stays within e(S) of the
    line over a step S (the lumens' own motion is in e), so the line's exit from those cells, less
    e, is a proven step for every lumen not listed, as is (whichever is longer) half a cell."""
    vR = F[F_VR]
    vT = F[F_VT]
    pR = P[reach, C_PR]
    sT = P[reach, C_ST]
    lo_r = math.floor(pR / c)
    lo_t = math.floor(sT / c)
    lo_r = (lo_r - 1.0 if pR / c - lo_r < 0.5 else lo_r) * c
    lo_t = (lo_t - 1.0 if sT / c - lo_t < 0.5 else lo_t) * c
    far_r = (lo_r + 2.0 * c - pR) if vR > 0.0 else pR - lo_r
    far_t = (lo_t + 2.0 * c - sT) if vT > 0.0 else sT - lo_t
    cap = STEP_CELLS * F[F_G]
    S = cap
    for k in range(2):  # the exit of the line, then that less the remainder over it
        e = fibre_remainder(F, S) if k else 0.0
        S = min(S, (far_r - e) / abs(vR) if vR != 0.0 else 1e300, (far_t - e) / abs(vT) if vT != 0.0 else 1e300)
    speed = math.sqrt(vR * vR + vT * vT)
    if speed > 0.0:
        half = 0.5 * c
        S = max(S, (half - fibre_remainder(F, min(half / speed, cap))) / speed)
    if S > P[reach, 6]:
        P[reach, 6] = S
    F[F_CAP] = min(P[reach, 6], cap)


@njit(inline="always", **NOREF)
def pull_remainder(F, S):
    """How far the pulled-back point (before the squeeze) can be from the line p₀ + s·v within
    s ≤ S [µm]: the slope's jumps at the grid lines crossed after t1 and its turn within cells."""
    G = F[F_G]
    hx = max(S - F[F_T1X], 0.0)
    hy = max(S - F[F_T1Y], 0.0)
    e = F[F_AX] * F[F_KXX] * (hx + F[F_AX] * hx * hx / (2.0 * G))
    e += F[F_AY] * F[F_KYY] * (hy + F[F_AY] * hy * hy / (2.0 * G))
    return e + F[F_KXY] * F[F_AX] * F[F_AY] * S * S


@njit(inline="always", **NOREF)
def fibre_remainder(F, S):
    """e(S) for a fibre lumen: the pull-back's remainder through the squeeze (its slope at most
    F_RSQ, its curvature F_C2), and the lumen's and the squeeze's motion with L."""
    return F[F_RSQ] * pull_remainder(F, S) + F[F_C2] * S * S + F[F_LF] * S


@njit(inline="always", **NOREF)
def plane_step(F, g, rate, rate_l):
    """A proven step for a surface at |g| along one pulled-back coordinate that moves at ``rate``
    per µm along the ray (its surface at ``rate_l``): a ray band's edge along T, the bands' reach."""
    w = rate + rate_l
    if w <= 0.0:
        return STEP_CELLS * F[F_G]
    S = min(g / w, STEP_CELLS * F[F_G])
    return min(max((g - pull_remainder(F, S)) / w, 0.0), S)


@njit(inline="always", **NOREF)
def _first_hit(alpha, beta, gamma, r2):
    """The least s > 0 with α s² + 2β s + γ = r² from γ > r² (outside), else 0 (inside or on it);
    1e300 if the line never comes that close."""
    c = gamma - r2
    if c <= 0.0:
        return 0.0
    if beta >= 0.0:
        return 1e300
    disc = beta * beta - alpha * c
    if disc < 0.0:
        return 1e300
    return c / (-beta + math.sqrt(disc))


@njit(inline="always", **NOREF)
def ellipse_step(F, d1, d2, a1, a2, w1, w2, cap, fibre):
    """(proven step, crossing) along the ray for the ellipse (semi-axes a1, a2) the point is offset
    (d1, d2) from, moving at (w1, w2) per µm: a fibre lumen in the pulled-back plane (``fibre``),
    or a ray-cell lumen in (pulled-back T, L).  Its g stays positive as far as the step (capped at
    ``cap``), and is negative at the crossing (the first root of the ellipse shrunk by the
    remainder; 0 where the line misses it or the remainder is too large to tell)."""
    i1 = 1.0 / (a1 * a1)
    i2 = 1.0 / (a2 * a2)
    alpha = w1 * w1 * i1 + w2 * w2 * i2
    beta = d1 * w1 * i1 + d2 * w2 * i2
    gamma = d1 * d1 * i1 + d2 * d2 * i2
    amin = min(a1, a2)
    hit = _first_hit(alpha, beta, gamma, 1.0)
    S = min(hit, cap)
    best = 0.0
    for _ in range(2):  # S at the unperturbed root (or the cap), then halfway to the first bound
        r = 1.0 + _ellipse_remainder(F, S, fibre) / amin
        s1 = min(_first_hit(alpha, beta, gamma, r * r), S)
        best = max(best, s1)
        S = 0.5 * (S + s1)
    cross = 0.0
    if hit < cap:
        r = 1.0 - _ellipse_remainder(F, 1.5 * hit, fibre) / amin
        if r > 0.5:
            cross = _first_hit(alpha, beta, gamma, r * r)
            if cross >= 1.5 * hit:
                cross = 0.0
    return best, cross


@njit(inline="always", **NOREF)
def _ellipse_remainder(F, S, fibre):
    """e(S) of a fibre lumen, or of a ray-cell lumen: the pulled-back T's remainder and the cell's
    motion with the band's half-width (its centre and semi-axis along T, 2.5 times the edge's)."""
    return fibre_remainder(F, S) if fibre else pull_remainder(F, S) + 2.5 * F[F_LB] * S


# Inlined into the march, its one caller: as a call it is given the context, some hundred words.
@njit(inline="always", **NOREF)
def along_clearances(R, T, L, d, ctx, P, n, F, skip):
    """Raise the clearances of the rows P[:n] at (R, T, L) to proven steps along ``d`` (both are
    lower bounds on how far g keeps its sign): fibre and ray-cell lumens approached from outside,
    ray bands and the reach rows; and note where the ray is surely inside each lumen (C_CROSS).

    Lazily: a lumen's step is worked out only while its ball is among the two least clearances
    of the rows other than row ``skip`` (the primitive crossed last, -1 for none; the march steps
    by those two), so a step costs a few lumens'
    quadratics, not every listed lumen's; a lumen left with its ball has C_CROSS -1."""
    if not ray_frame(R, T, L, d, ctx, P, n, F):
        for i in range(n):
            if P[i, 0] == P_LUMEN or P[i, 0] == P_RAY_LUMEN:
                P[i, C_CROSS] = -1.0
        return
    M = ctx[0]
    # Ray-cell lumens: every cell within a sub-column and a cell height of the point (in pulled-back
    # T and in L) is listed, so a step that stays that close meets no other.
    ray_cap = -1.0
    for i in range(n):
        if P[i, 0] == P_RAY_LUMEN:
            sw = 2.0 * (P[i, C_AR] + M[T0])
            h = 2.0 * (P[i, C_AT] + M[T0])
            wT = abs(F[F_VPT]) + 2.5 * F[F_LB]
            S = min(sw / wT if wT > 0.0 else 1e300, h / F[F_UL] if F[F_UL] > 0.0 else 1e300, STEP_CELLS * F[F_G])
            S2 = (sw - pull_remainder(F, S)) / wT if wT > 0.0 else 1e300
            ray_cap = max(min(S, S2), 0.0)
            break
    # Balsa's rows are the faces of the nearest centre's cell: from its polymer the first wall met
    # is one of them, but from inside a wall the ray may cross into a neighbour's polymer and on to
    # that cell's walls, which no row lists.  Faces get proven steps only from the polymer.
    in_cell = True
    for i in range(n):
        if P[i, 0] == P_FACE and P[i, 5] <= 0.0:
            in_cell = False
    for i in range(n):
        kind = P[i, 0]
        if kind == P_BAND or (kind == P_REACH and P[i, 1] == 0.0):  # a band, or the bands' reach
            st = plane_step(F, abs(P[i, 5]), abs(F[F_VPT]), F[F_LB])
            if st > P[i, 6]:
                P[i, 6] = st
        elif kind == P_FACE and F[F_CAP] > 0.0 and in_cell:
            # A balsa face: a line in the pulled-back plane (its normal C_DR, C_DT) moving with L.
            w = abs(F[F_VR] * P[i, C_DR] + F[F_VT] * P[i, C_DT]) + P[i, C_AR] * F[F_UL]
            g = abs(P[i, 5])
            S = min(g / w if w > 0.0 else 1e300, F[F_CAP])
            st = min(max((g - fibre_remainder(F, S)) / w, 0.0) if w > 0.0 else 1e300, S)
            if st > P[i, 6]:
                P[i, 6] = st
        elif (kind == P_PLATE or kind == P_TIP_END) and P[i, 5] > 0.0:
            # An end plate, or where a tip wall begins, approached: a plane of L, fixed; L moves with
            # the ray (short of it by 1e-9 of the way, for rounding).  (Past it the fibre's next cell
            # applies, and its g jumps.)
            st = min(P[i, 5] / F[F_UL] * (1.0 - 1e-9) if F[F_UL] > 0.0 else 1e300, STEP_CELLS * F[F_G])
            if st > P[i, 6]:
                P[i, 6] = st
        elif kind == P_LUMEN or kind == P_RAY_LUMEN:
            cap = F[F_CAP] if kind == P_LUMEN else ray_cap
            ok = P[i, 5] > 0.0 and P[i, C_AR] > 0.0 and P[i, C_AT] > 0.0 and cap > P[i, 6]
            P[i, C_CROSS] = -1.0 if ok else 0.0
    for _ in range(n):
        # The two least clearances (the skip row aside); a lumen among them not yet worked out is.
        a = -1
        b = -1
        for i in range(n):
            if i == skip:
                continue
            if a < 0 or P[i, 6] < P[a, 6]:
                b = a
                a = i
            elif b < 0 or P[i, 6] < P[b, 6]:
                b = i
        i = a if a >= 0 and P[a, C_CROSS] < 0.0 and (P[a, 0] == P_LUMEN or P[a, 0] == P_RAY_LUMEN) else b
        if i < 0 or not (P[i, C_CROSS] < 0.0 and (P[i, 0] == P_LUMEN or P[i, 0] == P_RAY_LUMEN)):
            return
        fibre = P[i, 0] == P_LUMEN
        w1 = F[F_VR] if fibre else F[F_VPT]
        w2 = F[F_VT] if fibre else F[F_VL]
        st, P[i, C_CROSS] = ellipse_step(F, P[i, C_DR], P[i, C_DT], P[i, C_AR], P[i, C_AT], w1, w2,
                                         F[F_CAP] if fibre else ray_cap, fibre)
        if st > P[i, 6]:
            P[i, 6] = st


@njit(inline="always", **NOREF)
def lumen_root(F, P, i):
    """Where the line p₀ + s·v of the frame F meets the ellipse of lumen row i (fibre or ray cell;
    C_CROSS >= 0: its step worked out, or the ray inside it) unperturbed, entering it from outside
    or leaving it from inside: a guess at its root, within the remainder of it; -1 for none."""
    kind = P[i, 0]
    if not ((kind == P_LUMEN or kind == P_RAY_LUMEN) and P[i, C_CROSS] >= 0.0 and P[i, C_AR] > 0.0
            and P[i, C_AT] > 0.0):
        return -1.0
    fibre = kind == P_LUMEN
    w1 = F[F_VR] if fibre else F[F_VPT]
    w2 = F[F_VT] if fibre else F[F_VL]
    i1 = 1.0 / (P[i, C_AR] * P[i, C_AR])
    i2 = 1.0 / (P[i, C_AT] * P[i, C_AT])
    alpha = w1 * w1 * i1 + w2 * w2 * i2
    beta = P[i, C_DR] * w1 * i1 + P[i, C_DT] * w2 * i2
    c = P[i, C_DR] * P[i, C_DR] * i1 + P[i, C_DT] * P[i, C_DT] * i2 - 1.0
    if P[i, 5] > 0.0:
        hit = _first_hit(alpha, beta, c + 1.0, 1.0)
        return hit if hit < 1e300 else -1.0
    disc = beta * beta - alpha * c  # inside (c < 0): the line leaves the ellipse at the larger root
    return (-beta + math.sqrt(disc)) / alpha if alpha > 0.0 and disc >= 0.0 else -1.0
