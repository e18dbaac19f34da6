"""The gradient in space of one primitive of the wood's surfaces, by the chain rule
(docs/methods.md#analytic-normals).

A primitive's ``g`` (:mod:`pipeline.microstructure.surface`) is a function of
the point's local coordinates: the pulled-back R (``pR``), the squeezed T
(``sT``) and L, through the primitive's own geometry at L (node splines, band
tapers).  Those coordinates are themselves maps of the point in space: the
ply's rotation, the bilinear pull-back of the distortion and the squeeze of the
ray bands.  :func:`gradient` follows that chain once, at one point (the
pull-back's derivative is :func:`~pipeline.microstructure._distortion.pull_back_slopes`
beside the map; the splines', tapers' and squeeze's are here), instead of six
evaluations of the primitive for central differences.

Every kind of row has one: fibre lumens (``P_LUMEN``), vessel outlines,
lumens and the walls cluster members share (``P_VESSEL_OUT``, ``P_VESSEL_IN``,
``P_VESSEL_SHARED``), ray-cell lumens and end walls (``P_RAY_LUMEN``,
``P_RAY_END``), ray-band edges (``P_BAND``), end plates (``P_PLATE``), tip
walls and their ends (``P_TIP``, ``P_TIP_END``), balsa's faces (``P_FACE``) and
ply boundaries (``P_PLY``).
"""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from .._intrinsics import carve
from ..rng import uniform
from ._constants import CTRL, FLEN, JITTER, PITCH, PUSH, RAYS, RHEIGHT, RJIT, RRAMP, RSER, RSPACE, RSQUEEZE, SCALE, \
    T0, TIP, VESSEL_AXIS_R, VWALL, WALLVAR
from ._distortion import pull_back, pull_back_slopes
from ._ray_cells import ray_band_width, ray_row
from ._slice import add_ray_row, fibre_min_len
from ._surface_cells import F_RAYS, NEAR, NOREF, _fibre_cell, group_cached, node_cached
from ._surface_rows import (P_BAND, P_FACE, P_LUMEN, P_PLATE, P_PLY, P_RAY_END, P_RAY_LUMEN, P_TIP, P_TIP_END,
                            P_VESSEL_IN, P_VESSEL_OUT, P_VESSEL_SHARED)
from .surface import _ply_of


@njit(inline="always", **NOREF)
def _taper_slope(M, L, L0, L1):
    """d(taper)/dL of a ray group's smoothstep ramp at L (:func:`add_ray_row`)."""
    a = L - L0
    b = L1 - L
    x = min(a, b) / M[RRAMP]
    if x <= 0.0 or x >= 1.0:
        return 0.0
    return 6.0 * x * (1.0 - x) * (1.0 if a <= b else -1.0) / M[RRAMP]


@njit(inline="always", **NOREF)
def _node_slopes(seed, M, n, m, L, CK, CV, C, NK, NV):
    """Node (n, m)'s (R, T, inset) at L (:func:`node_cached`) and their derivatives along L: the
    Catmull–Rom weights' derivatives on the same four control values."""
    R, T, w = node_cached(seed, M, n, m, L, CK, CV, C, NK, NV)
    sp = M[CTRL]
    x = L / sp
    f = x - math.floor(x)
    f2 = f * f
    d0 = 0.5 * (-1.0 + 4.0 * f - 3.0 * f2)
    d1 = 0.5 * (-10.0 * f + 9.0 * f2)
    d2 = 0.5 * (1.0 + 8.0 * f - 9.0 * f2)
    d3 = 0.5 * (3.0 * f2 - 2.0 * f)
    j = (n & (NEAR - 1)) * NEAR + (m & (NEAR - 1))
    r = d0 * NV[j, 0, 0] + d1 * NV[j, 1, 0] + d2 * NV[j, 2, 0] + d3 * NV[j, 3, 0]
    t = d0 * NV[j, 0, 1] + d1 * NV[j, 1, 1] + d2 * NV[j, 2, 1] + d3 * NV[j, 3, 1]
    v = d0 * NV[j, 0, 2] + d1 * NV[j, 1, 2] + d2 * NV[j, 2, 2] + d3 * NV[j, 3, 2]
    c = M[PITCH]
    return R, T, w, M[JITTER] * c * r / sp, M[JITTER] * c * t / sp, M[T0] * M[WALLVAR] * v / sp


@njit(inline="always", **NOREF)
def _lumen(seed, M, n, m, L, CK, CV, C, NK, NV):
    """Fibre (n, m)'s lumen (cR, cT, aR, aT) at L (:func:`centre_tables`), their slopes along L and the
    wall inset's slope."""
    r1, _, _, r1s, _, _ = _node_slopes(seed, M, n + 1, m, L, CK, CV, C, NK, NV)
    r0, _, _, r0s, _, _ = _node_slopes(seed, M, n - 1, m, L, CK, CV, C, NK, NV)
    _, t1, _, _, t1s, _ = _node_slopes(seed, M, n, m + 1, L, CK, CV, C, NK, NV)
    _, t0, _, _, t0s, _ = _node_slopes(seed, M, n, m - 1, L, CK, CV, C, NK, NV)
    _, _, Nt, _, _, Nts = _node_slopes(seed, M, n, m, L, CK, CV, C, NK, NV)
    return (0.5 * (r1 + r0), 0.5 * (t1 + t0), 0.5 * (r1 - r0) - Nt, 0.5 * (t1 - t0) + M[PUSH] * M[SCALE] - Nt,
            0.5 * (r1s + r0s), 0.5 * (t1s + t0s), 0.5 * (r1s - r0s) - Nts, 0.5 * (t1s - t0s) - Nts, Nts)


@njit(inline="always", **NOREF)
def _margin_slopes(dR, dT, aR, aT):
    """Partial derivatives of (√q − 1)·min(aR, aT) (:func:`_ellipse_margin`) with respect to dR,
    dT, aR and aT."""
    q = dR * dR / (aR * aR) + dT * dT / (aT * aT)
    r = math.sqrt(q)
    mu = min(aR, aT)
    gdR = mu * dR / (aR * aR) / r
    gdT = mu * dT / (aT * aT) / r
    gaR = -mu * dR * dR / (aR * aR * aR) / r + ((r - 1.0) if aR <= aT else 0.0)
    gaT = -mu * dT * dT / (aT * aT * aT) / r + ((r - 1.0) if aT < aR else 0.0)
    return gdR, gdT, gaR, gaT


@njit(inline="always", **NOREF)
def _ellipse(out, dR, dT, aR, aT, cRs, cTs, aRs, aTs, uR, uT, uL, vR, vT, vL, eR, eT, eL):
    """∇g of an ellipse margin in (u, v) whose centre and semi-axes move along L with slopes cRs,
    cTs, aRs, aTs; (uR, uT, uL) = ∇u, (vR, vT, vL) = ∇v and (eR, eT, eL) = ∇L in space."""
    gdR, gdT, gaR, gaT = _margin_slopes(dR, dT, aR, aT)
    gl = -gdR * cRs - gdT * cTs + gaR * aRs + gaT * aTs
    out[0] = gdR * uR + gdT * vR + gl * eR
    out[1] = gdR * uT + gdT * vT + gl * eT
    out[2] = gdR * uL + gdT * vL + gl * eL
    return True


@njit(**NOREF)
def gradient(R, T, L, seed, M, ply, patch, gi0, gj0, vessels, nv, key, cache, out):
    """The gradient in space of primitive ``key`` (kind, a, b, c, d) of the ply at (R, T, L) [µm]
    into ``out``; False (``out`` untouched) where that primitive has no surface at this point (a
    lumen closed at L, a ray-cell row the point is not in) or the point is outside the ply's
    distortion grid.  The arguments are those of :func:`evaluate`."""
    cs, sn, oR, oT, oL = ply[0], ply[1], ply[2], ply[3], ply[4]
    Rp = cs * R + sn * L + oR
    Lp = -sn * R + cs * L + oL
    Tp = T + oT
    c = M[PITCH]
    G = c / 8.0
    ix = np.int64(math.floor(Rp / G)) - gi0
    iy = np.int64(math.floor(Tp / G)) - gj0
    if ix < 0 or iy < 0 or ix >= patch.shape[0] - 1 or iy >= patch.shape[1] - 1:
        return False
    kind = key[0]
    # ∇ of the rotated coordinates: Rp = cs·R + sn·L, Tp = T, Lp = −sn·R + cs·L.
    eR, eT, eL = -sn, 0.0, cs
    if kind == P_PLATE:
        s = 1.0 if key[3] == 0.0 else -1.0
        out[0], out[1], out[2] = s * eR, s * eT, s * eL
        return True
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    n = np.int64(key[1])
    m = np.int64(key[2])
    if kind == P_TIP_END:
        lo, hi = _fibre_cell(seed, M, Lp, n, m, fibre_min_len(M), EK, EV)
        b = lo if key[3] == 0.0 else hi
        s = 1.0 if Lp >= b else -1.0
        out[0], out[1], out[2] = s * eR, s * eT, s * eL
        return True
    pR, pT = pull_back(patch, gi0, gj0, G, Rp, Tp)
    rx, ry, tx, ty = pull_back_slopes(patch, gi0, gj0, G, Rp, Tp)
    # ∇pR = (1 − rx)∇Rp − ry∇Tp, ∇pT = −tx∇Rp + (1 − ty)∇Tp
    uR, uT, uL = (1.0 - rx) * cs, -ry, (1.0 - rx) * sn
    vR, vT, vL = -tx * cs, 1.0 - ty, -tx * sn
    if kind == P_RAY_END:
        s = 1.0 if key[4] == 0.0 else -1.0
        out[0], out[1], out[2] = s * uR, s * uT, s * uL
        return True
    # The ray rows around the point, as the evaluation lists them (their order is the squeeze's).
    W = ray_band_width(M)
    W2 = 0.5 * W
    lam = M[RSQUEEZE] * M[SCALE]
    rays = carve(WF, F_RAYS, (16, 7))
    nr = 0
    if M[RAYS] != 0.0:
        reach = W2 + lam + c
        inv_c = 1.0 / c
        k_lo = np.int64(math.floor(((pT - reach) * inv_c - M[RJIT] - 2.0) / M[RSPACE])) - 1
        k_hi = np.int64(math.ceil(((pT + reach) * inv_c + M[RJIT] + 2.0) / M[RSPACE])) + 1
        for k in range(k_lo, k_hi + 1):
            t_r = ray_row(seed, M, k) * c
            if abs(pT - t_r) > reach:
                continue
            L0, L1, g = group_cached(seed, M, k, Lp, WF, WI)
            if kind == P_BAND and k == n:
                s = 1.0 if pT - t_r >= 0.0 else -1.0
                bs = 0.0
                if not math.isnan(L0) and add_ray_row(M, Lp, L0, L1, t_r, k, g, W, rays, nr) > nr:
                    bs = 0.5 * W * _taper_slope(M, Lp, L0, L1)
                out[0], out[1], out[2] = s * vR - bs * eR, s * vT - bs * eT, s * vL - bs * eL
                return True
            if not math.isnan(L0):
                nr = add_ray_row(M, Lp, L0, L1, t_r, k, g, W, rays, nr)
    if kind == P_BAND:
        return False
    band = -1
    for r in range(nr):
        if abs(pT - rays[r, 0]) < rays[r, 1]:
            band = r
            break
    if kind == P_RAY_LUMEN:
        if band < 0 or rays[band, 4] != n:
            return False
        ns = M[RSER]
        h = M[RHEIGHT]
        b = rays[band, 1]
        bs = 0.5 * W * _taper_slope(M, Lp, rays[band, 2], rays[band, 3])
        s_ = np.int64(key[2])
        ell = np.int64(key[3])
        sw = 2.0 * b / ns
        Tc = rays[band, 0] - b + (s_ + 0.5) * sw
        Tcs = -bs + (s_ + 0.5) * 2.0 * bs / ns
        aT = 0.5 * sw - M[T0]
        aTs = bs / ns
        aL = 0.5 * h - M[T0]
        Lc = rays[band, 2] + 0.5 * h * (s_ % 2) + (ell + 0.5) * h
        if aT <= 0.0 or aL <= 0.0:
            s = 1.0 if pT - Tc >= 0.0 else -1.0
            gl = -s * Tcs - (aTs if aT > 0.0 else 0.0)
            out[0], out[1], out[2] = s * vR + gl * eR, s * vT + gl * eT, s * vL + gl * eL
            return True
        # An ellipse in (pT, L): u = pT, v = L (centre Lc fixed, semi-axis aL fixed).
        return _ellipse(out, pT - Tc, Lp - Lc, aT, aL, Tcs, 0.0, aTs, 0.0, vR, vT, vL, eR, eT, eL, eR, eT, eL)
    if band >= 0:
        return False
    # The squeeze, row after row as the evaluation applies it, with its derivative.
    sT = pT
    sR, sTT, sL = vR, vT, vL
    for r in range(nr):
        d = sT - rays[r, 0]
        x = abs(d) - rays[r, 1]
        if x < lam:
            tau = rays[r, 6]
            taus = _taper_slope(M, Lp, rays[r, 2], rays[r, 3])
            sg = 1.0 if d > 0 else -1.0
            q = 1.0 - x / lam
            amp = rays[r, 6] * (c - W2)
            shift = amp * q * q * q
            # ∇x = sg·∇sT − b'·∇L with b = W/2·taper; ∇shift = (c − W/2)(taper'·q³∇L + taper·3q²·∇q)
            bs = 0.5 * W * taus
            k3 = (c - W2) * tau * 3.0 * q * q / lam  # ∂shift/∂x, negated
            kR = -k3 * (sg * sR - bs * eR) + (c - W2) * taus * q * q * q * eR
            kT = -k3 * (sg * sTT - bs * eT) + (c - W2) * taus * q * q * q * eT
            kL = -k3 * (sg * sL - bs * eL) + (c - W2) * taus * q * q * q * eL
            sT = sT + shift if d > 0 else sT - shift
            sR, sTT, sL = sR + sg * kR, sTT + sg * kT, sL + sg * kL
    if kind == P_LUMEN:
        cR, cT, aR, aT, cRs, cTs, aRs, aTs, _ = _lumen(seed, M, n, m, Lp, CK, CV, C, NK, NV)
        if aR <= 0.0 or aT <= 0.0:
            return False
        return _ellipse(out, pR - cR, sT - cT, aR, aT, cRs, cTs, aRs, aTs, uR, uT, uL, sR, sTT, sL, eR, eT, eL)
    if kind == P_VESSEL_OUT or kind == P_VESSEL_IN:
        cR, cT, aR, aT, cRs, cTs, aRs, aTs = _outline(seed, M, n, m, Lp, CK, CV, C, NK, NV)
        if kind == P_VESSEL_IN:
            aR -= M[VWALL]
            aT -= M[VWALL]
        if aR <= 0.0 or aT <= 0.0:
            return False
        return _ellipse(out, pR - cR, sT - cT, aR, aT, cRs, cTs, aRs, aTs, uR, uT, uL, sR, sTT, sL, eR, eT, eL)
    if kind == P_VESSEL_SHARED:
        return _shared_wall(out, seed, M, pR, sT, Lp, n, m, np.int64(key[3]), vessels, nv, cache,
                            uR, uT, uL, sR, sTT, sL, eR, eT, eL)
    if kind == P_FACE:
        return _face(out, seed, M, pR, sT, Lp, n, m, np.int64(key[3]), np.int64(key[4]), cache,
                     uR, uT, uL, sR, sTT, sL, eR, eT, eL)
    if kind == P_TIP:
        return _tip_wall(out, seed, M, pR, sT, Lp, n, m, np.int64(key[3]), cache,
                         uR, uT, uL, sR, sTT, sL, eR, eT, eL)
    return False


@njit(inline="always", **NOREF)
def _outline(seed, M, n, m, L, CK, CV, C, NK, NV):
    """A vessel member's outline (cR, cT, aR, aT) at L (:func:`vessel_outline`) and their slopes."""
    rl, _, _, rls, _, _ = _node_slopes(seed, M, n - 3, m, L, CK, CV, C, NK, NV)
    rr, _, _, rrs, _, _ = _node_slopes(seed, M, n + 3, m, L, CK, CV, C, NK, NV)
    _, td, _, _, tds, _ = _node_slopes(seed, M, n, m - 3, L, CK, CV, C, NK, NV)
    _, tu, _, _, tus, _ = _node_slopes(seed, M, n, m + 3, L, CK, CV, C, NK, NV)
    return (0.5 * (rl + rr), 0.5 * (td + tu), 0.5 * (rr - rl) * VESSEL_AXIS_R, 0.5 * (tu - td),
            0.5 * (rls + rrs), 0.5 * (tds + tus), 0.5 * (rrs - rls) * VESSEL_AXIS_R, 0.5 * (tus - tds))


@njit(**NOREF)
def _shared_wall(out, seed, M, pR, sT, L, n, m, side, vessels, nv, cache, uR, uT, uL, vR, vT, vL, eR, eT, eL):
    """The wall member (n, m) shares with its cluster neighbour on ``side``: g = (p − mid)·e/|e| +
    wall/2 on the bisector of their outline centres (:func:`vessel_walls`), e = c_u − c_v."""
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    v = -1
    for i in range(nv):
        if vessels[i, 0] == n and vessels[i, 1] == m:
            v = i
            break
    u = v - 1 + 2 * side
    if v < 0 or u < 0 or u >= nv or vessels[u, 2] != vessels[v, 2]:
        return False
    vR_, vT_, _, _, vRs, vTs, _, _ = _outline(seed, M, n, m, L, CK, CV, C, NK, NV)
    wR, wT, _, _, wRs, wTs, _, _ = _outline(seed, M, vessels[u, 0], vessels[u, 1], L, CK, CV, C, NK, NV)
    ex, ey, exs, eys = wR - vR_, wT - vT_, wRs - vRs, wTs - vTs
    e = math.sqrt(ex * ex + ey * ey)
    dR = pR - 0.5 * (wR + vR_)
    dT = sT - 0.5 * (wT + vT_)
    proj = dR * ex + dT * ey
    es = (ex * exs + ey * eys) / e
    gl = (-0.5 * (wRs + vRs) * ex - 0.5 * (wTs + vTs) * ey + dR * exs + dT * eys) / e - proj * es / (e * e)
    out[0] = (ex * uR + ey * vR) / e + gl * eR
    out[1] = (ex * uT + ey * vT) / e + gl * eT
    out[2] = (ex * uL + ey * vL) / e + gl * eL
    return True


@njit(**NOREF)
def _face(out, seed, M, pR, sT, L, nb, mb, ni, mi, cache, uR, uT, uL, vR, vT, vL, eR, eT, eL):
    """Balsa: the face between the nearest centre b and centre i, g = (|p − c_i|² − |p − c_b|²) /
    (2|c_i − c_b|) − (Nt_b + Nt_i)/2 (:func:`face_distance`), the centres the nodes themselves."""
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    bR, bT, bN, bRs, bTs, bNs = _node_slopes(seed, M, nb, mb, L, CK, CV, C, NK, NV)
    iR, iT, iN, iRs, iTs, iNs = _node_slopes(seed, M, ni, mi, L, CK, CV, C, NK, NV)
    ex, ey, exs, eys = iR - bR, iT - bT, iRs - bRs, iTs - bTs
    e = math.sqrt(ex * ex + ey * ey)
    D = (pR - iR) ** 2 + (sT - iT) ** 2 - (pR - bR) ** 2 - (sT - bT) ** 2
    Ds = -2.0 * ((pR - iR) * iRs + (sT - iT) * iTs) + 2.0 * ((pR - bR) * bRs + (sT - bT) * bTs)
    es = (ex * exs + ey * eys) / e
    gu = -ex / e  # ∂D/∂pR / (2e) = 2(bR − iR) / (2e)
    gv = -ey / e
    gl = Ds / (2.0 * e) - D * es / (2.0 * e * e) - 0.5 * (bNs + iNs)
    out[0] = gu * uR + gv * vR + gl * eR
    out[1] = gu * uT + gv * vT + gl * eT
    out[2] = gu * uL + gv * vL + gl * eL
    return True


@njit(**NOREF)
def _tip_wall(out, seed, M, pR, sT, L, n, m, w, cache, uR, uT, uL, vR, vT, vL, eR, eT, eL):
    """Tip wall ``w`` of fibre (n, m)'s lumen: g = |(p − c)·u − s| − Nt with s = h·(b − L)/tip and
    h = |(aR·uR, aT·uT)| (:func:`tip_walls`), c and the semi-axes those of the lumen."""
    CK, CV, EK, EV, C, NK, NV, WF, WI, WU = cache
    tip = M[TIP]
    lo, hi = _fibre_cell(seed, M, L, n, m, fibre_min_len(M), EK, EV)
    b = np.nan
    count = 0
    for side in range(2):
        bb = lo if side == 0 else hi
        if abs(L - bb) < tip:
            if count == w:
                b = bb
            count += 1
    if math.isnan(b):
        return False
    mean = M[FLEN]
    phase = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * mean
    q = np.int64(round((b - phase) / mean))
    phi = 2.0 * math.pi * uniform(seed, _rng.FIBRE_TIP, n, m, q)
    dR_, dT_ = math.cos(phi), math.sin(phi)
    cR, cT, aR, aT, cRs, cTs, aRs, aTs, Nts = _lumen(seed, M, n, m, L, CK, CV, C, NK, NV)
    h = math.sqrt(aR * aR * dR_ * dR_ + aT * aT * dT_ * dT_)
    hs = (aR * aRs * dR_ * dR_ + aT * aTs * dT_ * dT_) / h
    s = h * (b - L) / tip
    ss = (hs * (b - L) - h) / tip
    d = (pR - cR) * dR_ + (sT - cT) * dT_ - s
    sg = 1.0 if d >= 0.0 else -1.0
    gl = sg * (-cRs * dR_ - cTs * dT_ - ss) - Nts
    out[0] = sg * (dR_ * uR + dT_ * vR) + gl * eR
    out[1] = sg * (dR_ * uT + dT_ * vT) + gl * eT
    out[2] = sg * (dR_ * uL + dT_ * vL) + gl * eL
    return True


@njit(inline="always", **NOREF)
def gradient_at(R, T, L, ctx, key, cache, out):
    """:func:`gradient` in the ply holding T (``ctx``: :func:`~pipeline.microstructure.region.context_tuple`);
    a ply boundary's is +T."""
    (M, rt, plies, seeds, spans, patches, pshape, origins, lips, vessels, nvs, boxes, th, first, bsh, bptr,
     blist, _curv) = ctx
    if key[0] == P_PLY:
        out[0], out[1], out[2] = 0.0, 1.0, 0.0
        return True
    q = _ply_of(T, spans, th, first, plies.shape[0])
    return gradient(R, T, L, seeds[q], M, plies[q], patches[q, :pshape[q, 0], :pshape[q, 1]], origins[q, 0],
                    origins[q, 1], vessels[q], nvs[q], key, cache, out)
