"""Numba kernels of the voxel methods' interface normals: the gradient of a
Gaussian-smoothed wall indicator, put on its 1/2-level surface by Newton steps
(docs/methods.md#voxel-methods).
"""

import math

import numpy as np
from numba import njit

from .._intrinsics import cttz, prefetch
from ._packing import MASK_SEG, chunk_slot, table_entry
from .interface import normalise

NEWTON_REACH = 3.0  # the crossing point moves at most this far along the ray [voxels]
NO_SURFACE = 3  # surface_normal: no 1/2-level surface along the ray (a thin sheet, a grazing ray)

PART_BITS = 5  # a mixed row's L weights are summed in parts of at most 5 window positions


@njit(inline="always", cache=True, nogil=True)
def window_size(radius):
    """Voxel centres within ±radius of a point along one axis: at most this many."""
    return 2 * np.int64(math.floor(radius)) + 2


def window_scratch(radius):
    """Scratch arrays of smoothed_wall for a window radius (allocated once per trace).

    wts: weights and moments; segs: per-axis chunk and offset tables (rows
    0-13), the window's index bounds (14, 15) and the mixed rows of an R
    plane (16, 17); slots: the chunks it reads.
    """
    n = int(window_size(radius))
    return np.zeros((14, max(n, 6))), np.zeros((18, max(n, 3)), np.int64), np.zeros((n, n, n), np.int64)


@njit(inline="always", cache=True, nogil=True)
def _prefetch_window(bits, masks, table, box, cs, shape, start, n):
    """Start loading the words and row masks of a window, in the one or two
    chunks it spans along R and along T (the words of its first L chunk).

    The rows of a window are read after its weights are computed; asked for
    here, they arrive meanwhile instead of stalling the row loop.
    """
    i0, j0, k0 = start
    if i0 < 0 or j0 < 0 or j0 + n > shape[1] or (shape[0] > 0 and i0 + n > shape[0]):
        return
    ci = i0 // cs[0]
    cj = j0 // cs[1]
    ck = k0 // cs[2]
    oi0 = i0 - ci * cs[0]
    oj0 = j0 - cj * cs[1]
    ok = k0 - ck * cs[2]
    seg = min(max(ok, 0) // MASK_SEG, masks.shape[2] - 1)
    word = ok >> 6
    step = max(1, 8 // bits.shape[3])  # rows per 64-byte line
    ta = min(n, cs[1] - oj0)  # rows in the first T chunk; the others in the next
    tb = n - ta
    s00 = chunk_slot(table, box, ci, cj, ck)
    s01 = chunk_slot(table, box, ci, cj + 1, ck) if tb > 0 else -1
    s10 = -1
    s11 = -1
    if oi0 + n > cs[0]:
        s10 = chunk_slot(table, box, ci + 1, cj, ck)
        s11 = chunk_slot(table, box, ci + 1, cj + 1, ck) if tb > 0 else -1
    for q in range(n):
        oi = oi0 + q
        sa = s00
        sb = s01
        if oi >= cs[0]:
            oi -= cs[0]
            sa = s10
            sb = s11
        if sa >= 0:
            prefetch(masks, (sa, oi, seg, 0, oj0 >> 6))
            for r in range(0, ta + step - 1, step):
                prefetch(bits, (sa, oi, oj0 + min(r, ta - 1), word))
        if sb >= 0:
            prefetch(masks, (sb, oi, seg, 0, 0))
            for r in range(0, tb + step - 1, step):
                prefetch(bits, (sb, oi, min(r, tb - 1), word))


@njit(inline="always", cache=True, nogil=True)
def _mask_run(masks, slot, oi, g0, g1, kind, o0):
    """Bits o0, o0 + 1, ... of the row mask ``kind`` of R plane ``oi`` of a slot, from bit 0,
    over L segments g0 to g1: a row counts where it does in every one."""
    w = o0 >> 6
    sh = o0 & 63
    out = np.uint64(0xFFFFFFFFFFFFFFFF)
    for g in range(g0, g1 + 1):
        v = masks[slot, oi, g, kind, w] >> np.uint64(sh)
        if sh and w + 1 < masks.shape[4]:
            v |= masks[slot, oi, g, kind, w + 1] << np.uint64(64 - sh)
        out &= v
    return out


@njit(inline="always", cache=True, nogil=True)
def _add_rows(q0, q1, q2, q3, q4, q5, wy, dy, d2y, sl, sdl, s2l):
    """An R plane's sums plus rows of T weights wy, a·wy, a²·wy whose L sums are sl, sdl, s2l."""
    return (q0 + wy * sl, q1 + dy * sl, q2 + wy * sdl, q3 + d2y * sl, q4 + wy * s2l, q5 + dy * sdl)


@njit(inline="always", cache=True, nogil=True)
def smoothed_wall(bits, masks, table, box, cs, shape, x, sigma, radius, grad, hess, wts, segs, slots):
    """S(x) = (G_σ * χ_wall)(x) / ΣG, its gradient (into ``grad``) and Hessian.

    ``hess`` receives the Hessian's RR, TT, LL, RT, RL, TL components.
    The sum runs over the voxels within ``radius`` of x with separable
    weights; indices beyond the volume are clamped (replicated border).
    Voxels are read as rows along L from the bit-packed chunks (pack_chunks).
    Wood is nearly uniform along its fibres, so most rows are all wall or
    all polymer: the chunks' row ``masks`` (pack_chunks) name many of them
    without a read, the others cost one word read, and the few mixed ones
    are summed over their set bits.
    ``wts``, ``segs`` and ``slots`` are scratch (window_scratch).
    Returns S in [0, 1], or -1.0 when a needed chunk is not resident.
    """
    n = window_size(radius)
    start = (np.int64(math.ceil(x[0] - 0.5 - radius)), np.int64(math.ceil(x[1] - 0.5 - radius)),
             np.int64(math.ceil(x[2] - 0.5 - radius)))
    _prefetch_window(bits, masks, table, box, cs, shape, start, n)
    # Gaussian weights w, a·w and a²·w along each axis (a: voxel centre minus
    # x; rows 0-2, 3-5, 6-8 of wts), by the recurrence
    # w(a + 1) = w(a) · exp(-(2a + 1) / 2σ²), and their sums (rows 9-11).
    inv2s2 = 0.5 / (sigma * sigma)
    step2 = math.exp(-2.0 * inv2s2)
    sw = wts[9]
    sd = wts[10]
    s2w = wts[11]
    for ax in range(3):
        a0 = start[ax] + 0.5 - x[ax]
        w = math.exp(-a0 * a0 * inv2s2)
        ratio = math.exp(-(2.0 * a0 + 1.0) * inv2s2)
        s = 0.0
        m = 0.0
        m2 = 0.0
        for q in range(n):
            a = a0 + q
            wq = w if abs(a) <= radius else 0.0
            wts[ax, q] = wq
            wts[3 + ax, q] = a * wq
            wts[6 + ax, q] = a * a * wq
            s += wq
            m += a * wq
            m2 += a * a * wq
            w *= ratio
            ratio *= step2
        sw[ax] = s
        sd[ax] = m
        s2w[ax] = m2
    # The window's indices with a non-zero weight, lo[ax] to hi[ax] (its last
    # one or two positions lie beyond the radius): only their chunks are read.
    lo = segs[14]
    hi = segs[15]
    for ax in range(3):
        q = 0
        while q < n - 1 and wts[ax, q] == 0.0:
            q += 1
        lo[ax] = q
        q = n - 1
        while q > lo[ax] and wts[ax, q] == 0.0:
            q -= 1
        hi[ax] = q
    # Most windows lie in one chunk, inside the volume: their tables are
    # filled directly (the same entries the general case makes for them).
    single = True
    for ax in range(3):
        a0 = start[ax] + lo[ax]
        a1 = start[ax] + hi[ax]
        if (shape[ax] > 0 and (a0 < 0 or a1 >= shape[ax])) or a0 // cs[ax] != a1 // cs[ax]:
            single = False
    if single:
        ch0 = (start[0] + lo[0]) // cs[0]
        ch1 = (start[1] + lo[1]) // cs[1]
        ch2 = (start[2] + lo[2]) // cs[2]
        slot = chunk_slot(table, box, ch0, ch1, ch2)
        if slot == -1:
            return -1.0
        slots[0, 0, 0] = slot
        off0 = start[0] + lo[0] - ch0 * cs[0]
        for q in range(lo[0], hi[0] + 1):
            segs[1, q] = off0 + q - lo[0]
            segs[10, q] = 0
        segs[3, lo[1]] = start[1] + lo[1] - ch1 * cs[1]
        segs[3, hi[1]] = segs[3, lo[1]] + hi[1] - lo[1]
        segs[7, 0] = start[2] + lo[2] - ch2 * cs[2]
        segs[8, 0] = hi[2] - lo[2] + 1
        nseg = 1
        nch0 = 1
        nch1 = 1
    else:
        # Chunk (relative to the table) and offset of every window index along
        # each axis, clamped where the volume ends, one division per axis:
        # segs rows 0-1 (R), 2-3 (T), 4-5 (L).
        for ax in range(3):
            prev = np.int64(0)
            ch = np.int64(0)
            off = np.int64(0)
            for q in range(n):
                i = start[ax] + q
                if shape[ax] > 0:
                    i = min(max(i, 0), shape[ax] - 1)
                if q == 0:
                    ch = i // cs[ax]
                    off = i - ch * cs[ax]
                elif i == prev + 1:
                    off += 1
                    if off == cs[ax]:
                        off = 0
                        ch += 1
                prev = i
                segs[2 * ax, q] = ch - box[ax]
                segs[2 * ax + 1, q] = off
        # The L indices as runs of consecutive voxels in one chunk: segs rows 6-9
        # (chunk, offset, length, window position).
        nseg = 0
        for q in range(lo[2], hi[2] + 1):
            if (nseg > 0 and segs[4, q] == segs[6, nseg - 1]
                    and segs[5, q] == segs[7, nseg - 1] + segs[8, nseg - 1]):
                segs[8, nseg - 1] += 1
            else:
                segs[6, nseg] = segs[4, q]
                segs[7, nseg] = segs[5, q]
                segs[8, nseg] = 1
                segs[9, nseg] = q
                nseg += 1
        # Ordinal of each R and T index's chunk (rows 10, 11; the first index of
        # each ordinal in rows 12, 13), and the slot of every (L run, R chunk,
        # T chunk) the window touches; a chunk that is not resident stops here,
        # before any voxel is read.
        nch0 = 0
        nch1 = 0
        for ax in range(2):
            u = -1
            for q in range(lo[ax], hi[ax] + 1):
                if q == lo[ax] or segs[2 * ax, q] != segs[2 * ax, q - 1]:
                    u += 1
                    segs[12 + ax, u] = q
                segs[10 + ax, q] = u
            if ax == 0:
                nch0 = u + 1
            else:
                nch1 = u + 1
        for sg in range(nseg):
            tc = segs[6, sg]
            for ua in range(nch0):
                ta = segs[0, segs[12, ua]]
                for ub in range(nch1):
                    slot = table_entry(table, ta, segs[2, segs[13, ub]], tc)
                    if slot == -1:
                        return -1.0
                    slots[sg, ua, ub] = slot
    # Rows that are neither all wall nor all polymer are summed over their set
    # bits in parts of ``width`` window positions: that order of the sums is part
    # of the voxel methods' results, bit for bit.
    parts = (n + PART_BITS - 1) // PART_BITS
    width = (n + parts - 1) // parts
    pmask = np.uint64((1 << width) - 1)
    full = ((np.uint64(1) << np.uint64(hi[2] + 1)) - np.uint64(1)) & ~((np.uint64(1) << np.uint64(lo[2]))
                                                                       - np.uint64(1))
    if nseg == 1:
        ok = segs[7, 0]
        word = ok >> 6
        sh = np.uint64(ok & 63)
        two = (ok & 63) + segs[8, 0] > 64
        back = np.uint64(64 - (ok & 63)) if two else np.uint64(0)
        run = (np.uint64(1) << np.uint64(segs[8, 0])) - np.uint64(1)
        at = np.uint64(lo[2])
    # Moments of the wall voxels: m0 = Σχw, m1 = Σχ a w, m2 = Σχ a aᵀ w
    # (axes R, T, L = x, y, z), gathered over the rows (a, b) along L.
    m0 = 0.0
    m1x = 0.0
    m1y = 0.0
    m1z = 0.0
    mxx = 0.0
    myy = 0.0
    mzz = 0.0
    mxy = 0.0
    mxz = 0.0
    myz = 0.0
    # Common case: one L run and the window's T rows consecutive (not clamped)
    # in one chunk, so the rows of an R plane follow each other in one slot.
    simple = nseg == 1 and nch1 == 1 and segs[3, hi[1]] - segs[3, lo[1]] == hi[1] - lo[1]
    oj0 = segs[3, lo[1]] - lo[1]
    rows_all = (np.uint64(1) << np.uint64(hi[1] - lo[1] + 1)) - np.uint64(1)
    # The L segments of the row masks that the window's one L run meets.
    g0 = segs[7, 0] // MASK_SEG
    g1 = (segs[7, 0] + segs[8, 0] - 1) // MASK_SEG
    mword = segs[3, lo[1]] >> 6
    msh = np.uint64(segs[3, lo[1]] & 63)
    mtwo = (segs[3, lo[1]] & 63) + hi[1] - lo[1] + 1 > 64
    mback = np.uint64(64 - (segs[3, lo[1]] & 63)) if mtwo else np.uint64(0)
    for a in range(lo[0], hi[0] + 1):
        wx = wts[0, a]
        oi = segs[1, a]
        ua = segs[10, a]
        # Sums over the rows of this R plane.
        q0 = 0.0  # Σ wy·sl
        q1 = 0.0  # Σ dy·sl
        q2 = 0.0  # Σ wy·sdl
        q3 = 0.0  # Σ d2y·sl
        q4 = 0.0  # Σ wy·s2l
        q5 = 0.0  # Σ dy·sdl
        fw = 0.0  # Σ wy, Σ dy, Σ d2y over the all-wall rows
        fd = 0.0
        fd2 = 0.0
        nmix = 0
        # The rows to visit, as bits b - lo[1]; in the common case the chunk's
        # row masks tell which are all polymer (skipped) or all wall over the
        # chunk (added unread), so only the others are read.
        todo = rows_all
        known = np.uint64(0)
        if simple:
            slot = slots[0, ua, 0]
            if slot < 0:  # -2: outside a finite volume, not wall
                continue
            known = rows_all
            poly = rows_all
            for g in range(g0, g1 + 1):
                kw = masks[slot, oi, g, 0, mword] >> msh
                pw = masks[slot, oi, g, 1, mword] >> msh
                if mtwo:
                    kw |= masks[slot, oi, g, 0, mword + 1] << mback
                    pw |= masks[slot, oi, g, 1, mword + 1] << mback
                known &= kw
                poly &= pw
            todo &= ~poly
            known &= todo
        else:
            # Across chunks: the masks of each T chunk's run of rows, a row
            # counting as all wall (all polymer) where it is so in every L run.
            poly = np.uint64(0)
            for ub in range(nch1):
                p0 = segs[13, ub]
                p1 = segs[13, ub + 1] - 1 if ub + 1 < nch1 else hi[1]
                o0 = segs[3, p0]
                if segs[3, p1] - o0 != p1 - p0:
                    continue  # rows clamped at the volume's T faces: read them
                lm = (np.uint64(1) << np.uint64(p1 - p0 + 1)) - np.uint64(1)
                kw = lm
                pw = lm
                for sg in range(nseg):
                    slot = slots[sg, ua, ub]
                    if slot < 0:  # -2: outside a finite volume, reads as polymer
                        kw = np.uint64(0)
                        continue
                    g0 = segs[7, sg] // MASK_SEG
                    g1 = (segs[7, sg] + segs[8, sg] - 1) // MASK_SEG
                    kw &= _mask_run(masks, slot, oi, g0, g1, 0, o0)
                    pw &= _mask_run(masks, slot, oi, g0, g1, 1, o0)
                known |= kw << np.uint64(p0 - lo[1])
                poly |= pw << np.uint64(p0 - lo[1])
            todo &= ~poly
            known &= todo
        while todo:
            tz = cttz(todo)
            todo &= todo - np.uint64(1)
            b = lo[1] + np.int64(tz)
            if (known >> tz) & np.uint64(1):
                fw += wts[1, b]
                fd += wts[4, b]
                fd2 += wts[7, b]
                continue
            if nseg == 1:
                if simple:
                    oj = oj0 + b
                else:
                    slot = slots[0, ua, segs[11, b]]
                    if slot < 0:
                        continue
                    oj = segs[3, b]
                pat = bits[slot, oi, oj, word] >> sh
                if two:
                    pat |= bits[slot, oi, oj, word + 1] << back
                pat = (pat & run) << at
            else:
                pat = np.uint64(0)
                oj = segs[3, b]
                ub = segs[11, b]
                for sg in range(nseg):
                    slot = slots[sg, ua, ub]
                    if slot >= 0:
                        okq = segs[7, sg]
                        ln = segs[8, sg]
                        wq = okq >> 6
                        shq = okq & 63
                        v = bits[slot, oi, oj, wq] >> np.uint64(shq)
                        if shq + ln > 64:
                            v |= bits[slot, oi, oj, wq + 1] << np.uint64(64 - shq)
                        v &= (np.uint64(1) << np.uint64(ln)) - np.uint64(1)
                        pat |= v << np.uint64(segs[9, sg])
            if pat == 0:
                continue
            if pat == full:
                # An all-wall row: its L sums are the window's, added per plane below.
                fw += wts[1, b]
                fd += wts[4, b]
                fd2 += wts[7, b]
                continue
            # A mixed row (rare): summed below, out of this loop.
            segs[16, nmix] = b
            segs[17, nmix] = np.int64(pat)
            nmix += 1
        for e in range(nmix):
            b = segs[16, e]
            pat = np.uint64(segs[17, e])
            sl = 0.0
            sdl = 0.0
            s2l = 0.0
            for t in range(parts):
                part = (pat >> np.uint64(t * width)) & pmask
                p0 = 0.0
                p1 = 0.0
                p2 = 0.0
                while part:
                    q = t * width + np.int64(cttz(part))
                    part &= part - np.uint64(1)
                    p0 += wts[2, q]
                    p1 += wts[5, q]
                    p2 += wts[8, q]
                sl += p0
                sdl += p1
                s2l += p2
            q0, q1, q2, q3, q4, q5 = _add_rows(q0, q1, q2, q3, q4, q5, wts[1, b], wts[4, b], wts[7, b],
                                               sl, sdl, s2l)
        # The all-wall rows, whose L sums are the window's (sw, sd, s2w).
        q0, q1, q2, q3, q4, q5 = _add_rows(q0, q1, q2, q3, q4, q5, fw, fd, fd2, sw[2], sd[2], s2w[2])
        dx = wts[3, a]
        m0 += wx * q0
        m1x += dx * q0
        m1y += wx * q1
        m1z += wx * q2
        mxx += wts[6, a] * q0
        myy += wx * q3
        mzz += wx * q4
        mxy += dx * q1
        mxz += dx * q2
        myz += wx * q5
    # The same moments of the whole window (separable), then S = N / D with
    # N = Σχw, D = Σw, differentiated through the weights:
    # ∇w = a w / σ², ∇∇w = (a aᵀ / σ² − I) w / σ².
    # ∇S = (∇N − S ∇D) / D: the second term cancels what the finite window
    # adds, so a structure uniform along an axis has no gradient along it.
    D = sw[0] * sw[1] * sw[2]
    S = m0 / D
    is2 = 1.0 / (sigma * sigma)
    dD0 = sd[0] * sw[1] * sw[2] * is2
    dD1 = sw[0] * sd[1] * sw[2] * is2
    dD2 = sw[0] * sw[1] * sd[2] * is2
    grad[0] = (m1x * is2 - S * dD0) / D
    grad[1] = (m1y * is2 - S * dD1) / D
    grad[2] = (m1z * is2 - S * dD2) / D
    # H_S = (H_N − S H_D − ∇S ∇Dᵀ − ∇D ∇Sᵀ) / D
    hN = (mxx * is2 - m0, myy * is2 - m0, mzz * is2 - m0, mxy * is2, mxz * is2, myz * is2)
    hD = ((s2w[0] * is2 - sw[0]) * sw[1] * sw[2], sw[0] * (s2w[1] * is2 - sw[1]) * sw[2],
          sw[0] * sw[1] * (s2w[2] * is2 - sw[2]), sd[0] * sd[1] * sw[2] * is2,
          sd[0] * sw[1] * sd[2] * is2, sw[0] * sd[1] * sd[2] * is2)
    gD = (dD0, dD1, dD2)
    pairs = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    for e in range(6):
        p, q = pairs[e]
        hess[e] = (hN[e] * is2 - S * hD[e] * is2 - grad[p] * gD[q] - gD[p] * grad[q]) / D
    return S


@njit(inline="always", cache=True, nogil=True)
def _hess_dot(h, v):
    """H·v for a symmetric 3 × 3 H stored as (RR, TT, LL, RT, RL, TL)."""
    return (h[0] * v[0] + h[3] * v[1] + h[4] * v[2], h[3] * v[0] + h[1] * v[1] + h[5] * v[2],
            h[4] * v[0] + h[5] * v[1] + h[2] * v[2])


@njit(inline="always", cache=True, nogil=True)
def _sheet_normal(h, out, valley):
    """Replace the unit vector ``out`` by the axis across a thin sheet, where the
    Hessian h (RR, TT, LL, RT, RL, TL) curves down most, signed like ``out``;
    ``out`` is kept where h has no such single axis."""
    a00, a11, a22, a01, a02, a12 = h
    if valley:  # a sheet of polymer: S curves up most across it
        a00, a11, a22, a01, a02, a12 = -a00, -a11, -a22, -a01, -a02, -a12
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    if not p2 > 0.0:
        return
    p = math.sqrt(p2 / 6.0)
    b00 = (a00 - q) / p
    b11 = (a11 - q) / p
    b22 = (a22 - q) / p
    b01 = a01 / p
    b02 = a02 / p
    b12 = a12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    phi = math.acos(min(max(r, -1.0), 1.0)) / 3.0
    lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)  # the lowest eigenvalue
    mid = 3.0 * q - lo - (q + 2.0 * p * math.cos(phi))
    if not (lo < 0.0 and mid - lo > 0.5 * abs(lo)):
        return  # no ridge, or no single axis across it (a thin rod, say)
    # Its eigenvector: the longest cross product of two rows of h - lo·I.
    r0 = (a00 - lo, a01, a02)
    r1 = (a01, a11 - lo, a12)
    r2 = (a02, a12, a22 - lo)
    best = 0.0
    e = (0.0, 0.0, 0.0)
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        c = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
        m = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
        if m > best:
            best = m
            e = c
    if not best > 0.0:
        return
    sgn = 1.0 if e[0] * out[0] + e[1] * out[1] + e[2] * out[2] >= 0.0 else -1.0
    inv = sgn / math.sqrt(best)
    for k in range(3):
        out[k] = e[k] * inv


@njit(inline="always", cache=True, nogil=True)
def surface_normal(bits, masks, table, box, cs, shape, xf, d, sigma, radius, newton, refit, out, wts, segs,
                   slots):
    """Normal where the ray meets the smoothed wall surface S = 1/2 near face point xf.

    Up to ``newton`` Newton steps along the ray (at most NEWTON_REACH from xf)
    move the point onto the iso-surface, so rays crossing one staircase face
    at different places get the normals of the surface they really meet.
    The first ``refit`` steps evaluate the window again at the new point; the
    others step on the second-order model around the last evaluation
    (S + s ∇S·d + s² dᵀHd / 2), whose gradient ∇S + s H d is the normal.
    Where the model along the ray has no root the normal is the gradient at
    xf, or, across a sheet thinner than the smoothing (the model along that
    gradient never reaches 1/2), the axis across the sheet from the Hessian
    at xf (_sheet_normal).
    Returns 1 on success, NO_SURFACE for that fallback, 0 for a one-phase
    neighbourhood, -1 for a missing chunk.
    """
    x = wts[12]
    hess = wts[13]
    for q in range(3):
        x[q] = xf[q]
    t = 0.0  # where the point is along the ray
    te = 0.0  # where the window was last evaluated
    it = 0
    evaluate = True
    g0 = (0.0, 0.0, 0.0)
    h0 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    thin0 = False
    s0 = 0.0
    while True:
        if evaluate:  # one call site: smoothed_wall is inlined once
            S = smoothed_wall(bits, masks, table, box, cs, shape, x, sigma, radius, out, hess, wts, segs,
                              slots)
            if S < 0.0:
                return -1
            te = t
            gd = out[0] * d[0] + out[1] * d[1] + out[2] * d[2]
            hd0, hd1, hd2 = _hess_dot(hess, d)
            dhd = d[0] * hd0 + d[1] * hd1 + d[2] * hd2
            if it == 0:  # the face point: kept for a sheet's normal
                s0 = S
                g0 = (out[0], out[1], out[2])
                h0 = (hess[0], hess[1], hess[2], hess[3], hess[4], hess[5])
                # Along the gradient the model S + s|g| + s²ĝᵀHĝ/2 never reaches
                # 1/2 (whatever the ray's direction): a sheet of either phase
                # thinner than the smoothing.
                hg0, hg1, hg2 = _hess_dot(hess, out)
                gg = out[0] * out[0] + out[1] * out[1] + out[2] * out[2]
                ghg = out[0] * hg0 + out[1] * hg1 + out[2] * hg2
                thin0 = gg * gg - 2.0 * ghg * (S - 0.5) < 0.0
            evaluate = False
        if it >= newton:
            break
        u = t - te
        val = S + u * gd + 0.5 * u * u * dhd
        slope = gd + u * dhd
        if abs(val - 0.5) < 1e-6 or abs(slope) < 1e-3:
            break
        t_new = min(max(t - (val - 0.5) / slope, -NEWTON_REACH), NEWTON_REACH)
        if t_new == t:
            break
        t = t_new
        if it < refit:
            for q in range(3):
                x[q] = xf[q] + t * d[q]
            evaluate = True
        it += 1
    if thin0 or gd * gd - 2.0 * dhd * (S - 0.5) < 0.0:
        # No surface S = 1/2 to meet along the ray: the steps above wander to
        # their reach, where the model's gradient is an extrapolation.  Then
        # the normal is the gradient at xf; and across a sheet of either phase
        # thinner than the smoothing (thin0: S peaks or dips short of 1/2) the
        # axis across the sheet, along which S's Hessian at xf curves most:
        # the same on both faces of a flat sheet, wherever the ray crosses
        # them (so a thin flat wall leaves a ray parallel to itself), and
        # radial in a thin tube (its deflection: docs/methods.md#exact-references).  Taking that
        # axis also where only the model along the ray misses 1/2 (grazing
        # rays) moved birch's FWHM_R at ΔRI < 0 away from its value at half
        # the voxel size (by 10-16 %), so it is not.
        for q in range(3):
            out[q] = g0[q]
        if normalise(out) < 1e-12:
            return 0
        if thin0:
            _sheet_normal(h0, out, s0 > 0.5)
        return NO_SURFACE
    u = t - te
    out[0] += u * hd0
    out[1] += u * hd1
    out[2] += u * hd2
    if normalise(out) < 1e-12:
        return 0
    return 1
