"""The iso-surface march (Numba): rays through the level set of a grey-level volume.

The field is the trilinear interpolation of the voxel values between voxel centres (constant
beyond the outermost centres); the wall (phase 1) is where it exceeds the threshold ``iso``.
Along a ray inside one cell of the centres' grid the field is a cubic in the distance, so a
crossing is a root of a cubic: the cell's interval is cut at the roots of the cubic's derivative
into monotone pieces, and the first piece that goes from the ray's phase into the other holds the
crossing, which bisection brackets to adjacent floating-point distances.  No crossing inside a
cell is missed (two in one cell are two pieces), and a tangency (a double root, no change of
sign) is not a crossing.  The normal is the gradient of the interpolant there.

The volume is read in blocks of B³ cells (B + 1 voxels a side: a cell's eight corners lie in one
block) held in a pool; a ray that reaches a block not in the pool stops with the status
NEEDS_CHUNK and the block it wants, its whole state kept, and goes on bit for bit where it stopped
once its caller has read that block (:class:`pipeline.optics.iso.IsoVolume`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .interface import NEEDS_CHUNK, REFLECTED, SIDE, TRANSMITTED, TRAPPED, interface_event

_BIG = 1e300


@njit(cache=True, nogil=True, inline="always")
def _clamp(i, n):
    return min(max(i, 0), n - 1)


@njit(cache=True, nogil=True)
def _cubic(pool, slot, base, dims, ci, cj, ck, u0, du, iso, c):
    """Coefficients c[0..3] of F(s) = field − iso along u0 + s·du (local coordinates of cell
    (ci, cj, ck), each in [0, 1] inside it); also the eight corner values in c[4:12].  The corners,
    their indices clamped to the volume (constant beyond its centres), are read from the block in
    ``pool[slot]`` whose first voxel is ``base``."""
    for q in range(4):
        c[q] = 0.0
    for a in range(2):
        # factor along R: a ? u : 1 − u, as p0 + p1·s
        pa0 = u0[0] if a else 1.0 - u0[0]
        pa1 = du[0] if a else -du[0]
        ia = _clamp(ci + a, dims[0]) - base[0]
        for b in range(2):
            pb0 = u0[1] if b else 1.0 - u0[1]
            pb1 = du[1] if b else -du[1]
            ib = _clamp(cj + b, dims[1]) - base[1]
            ab0 = pa0 * pb0
            ab1 = pa0 * pb1 + pa1 * pb0
            ab2 = pa1 * pb1
            for e in range(2):
                pc0 = u0[2] if e else 1.0 - u0[2]
                pc1 = du[2] if e else -du[2]
                f = np.float64(pool[slot, ia, ib, _clamp(ck + e, dims[2]) - base[2]])
                c[4 + 4 * a + 2 * b + e] = f
                c[0] += f * (ab0 * pc0)
                c[1] += f * (ab0 * pc1 + ab1 * pc0)
                c[2] += f * (ab1 * pc1 + ab2 * pc0)
                c[3] += f * (ab2 * pc1)
    c[0] -= iso


@njit(cache=True, nogil=True, inline="always")
def _eval(c, s):
    return ((c[3] * s + c[2]) * s + c[1]) * s + c[0]


@njit(cache=True, nogil=True, inline="always")
def _other(value, medium):
    """Whether a value of F = field − iso lies in the phase other than ``medium``."""
    return value <= 0.0 if medium == 1 else value > 0.0


@njit(cache=True, nogil=True)
def _first_crossing(c, length, medium, at_start, cuts, out):
    """The first s in [0, length] where F passes from ``medium``'s phase into the other: the
    bracket (last point in the phase, first point out of it) in out[0:2]; returns False if there
    is none.  ``at_start``: s = 0 is where the ray left its last crossing (its phase is known
    there, whatever F's rounding says); elsewhere F out of the phase at s = 0 is a crossing on the
    cell's face."""
    f0 = _eval(c, 0.0)
    if not at_start and _other(f0, medium):
        out[0] = 0.0
        out[1] = 0.0
        return True
    # Monotone pieces: cut [0, length] at the roots of F' = c1 + 2 c2 s + 3 c3 s².
    n = 0
    cuts[n] = 0.0
    n += 1
    qa, qb, qc = 3.0 * c[3], 2.0 * c[2], c[1]
    r1, r2 = _BIG, _BIG
    if qa != 0.0:
        disc = qb * qb - 4.0 * qa * qc
        if disc > 0.0:
            sq = math.sqrt(disc)
            t = -0.5 * (qb + (sq if qb >= 0.0 else -sq))
            r1 = t / qa
            r2 = qc / t if t != 0.0 else _BIG
    elif qb != 0.0:
        r1 = -qc / qb
    if r1 > r2:
        r1, r2 = r2, r1
    if 0.0 < r1 < length:
        cuts[n] = r1
        n += 1
    if 0.0 < r2 < length and r2 != r1:
        cuts[n] = r2
        n += 1
    cuts[n] = length
    n += 1
    for p in range(n - 1):
        lo, hi = cuts[p], cuts[p + 1]
        if _other(_eval(c, lo), medium) or not _other(_eval(c, hi), medium):
            continue  # starts out of the phase (only at a segment's start) or never leaves it
        while True:  # F is monotone on [lo, hi]: one change of phase, bracketed to adjacent doubles
            mid = 0.5 * (lo + hi)
            if mid <= lo or mid >= hi:
                break
            if _other(_eval(c, mid), medium):
                hi = mid
            else:
                lo = mid
        out[0] = lo
        out[1] = hi
        return True
    return False


@njit(cache=True, nogil=True)
def march(pool, slots, block, dims, h, iso, ray_ids, n_wall, n_poly, max_events, fresnel, seed,
          X_all, D_all, med_all, ev_all, length_all, cells_all, flat_all, s0_all, idx_all, resume, status, want):
    """Trace rays through the iso-surface of a volume of ``dims`` voxels (R, T, L) of ``h`` µm, corner
    at the origin, from T = 0 to T = dims[1]·h, as far as the blocks in ``pool`` take them.

    ``slots[bi, bj, bk]``: the pool slot holding block (bi, bj, bk) (voxels from ``block``·b to
    ``block``·(b + 1), clamped to the volume), or -1.  Per ray, in and out: its position [µm] and
    unit direction, phase, interfaces, path [µm], the cells it crossed and the crossings whose
    gradient was zero (``flat``: the ray goes on undeflected there); where it stands in its segment
    (``s0``, ``idx``, used when ``resume``).  Out: ``status`` (NEEDS_CHUNK with the block in
    ``want`` when it stopped for one) and, for the others, where and how it left."""
    nr, nt, nl = dims[0], dims[1], dims[2]
    size = np.array([nr * h, nt * h, nl * h])
    c = np.empty(12)
    cuts = np.empty(4)
    br = np.empty(2)
    X = np.empty(3)
    d = np.empty(3)
    nd = np.empty(3)
    nrm = np.empty(3)
    u0 = np.empty(3)
    du = np.empty(3)
    u = np.empty(3)
    idx = np.empty(3, np.int64)
    base = np.empty(3, np.int64)
    for r in range(X_all.shape[0]):
        for q in range(3):
            X[q] = X_all[r, q]
            d[q] = D_all[r, q]
        med = np.int64(med_all[r])  # its type after `1 - med`: callees compile once
        ev = ev_all[r]
        length = length_all[r]
        ncell = cells_all[r]
        nflat = flat_all[r]
        st = 0
        again = resume[r]
        while st == 0:
            # Where the ray leaves the volume along this straight segment, and through which face.
            t_out = _BIG
            face = -1
            for q in range(3):
                if d[q] > 0.0:
                    t = (size[q] - X[q]) / d[q]
                elif d[q] < 0.0:
                    t = -X[q] / d[q]
                else:
                    continue
                if t < t_out:
                    t_out, face = t, q
            t_out = max(t_out, 0.0)
            # Walk the cells of the centres' grid (cell i spans centres i and i + 1).
            if again:  # where it stopped for a block
                s0 = s0_all[r]
                for q in range(3):
                    idx[q] = idx_all[r, q]
                again = False
            else:
                s0 = 0.0
                for q in range(3):
                    idx[q] = int(math.floor(X[q] / h - 0.5))
            crossed = False
            while s0 < t_out:
                # Until the ray has moved, its phase is the one it left its last crossing with: the
                # cells that meet at its starting point (on a face, an edge or a corner) may round F
                # to the other side there, which is no new crossing.
                at_start = s0 <= 0.0
                s1 = t_out
                for q in range(3):
                    if d[q] > 0.0:
                        s1 = min(s1, ((idx[q] + 1.5) * h - X[q]) / d[q])
                    elif d[q] < 0.0:
                        s1 = min(s1, ((idx[q] + 0.5) * h - X[q]) / d[q])
                s1 = max(s1, s0)
                bi = _clamp(idx[0], nr) // block
                bj = _clamp(idx[1], nt) // block
                bk = _clamp(idx[2], nl) // block
                slot = slots[bi, bj, bk]
                if slot < 0:  # stop here until the block is read
                    st = NEEDS_CHUNK
                    want[r, 0], want[r, 1], want[r, 2] = bi, bj, bk
                    s0_all[r] = s0
                    for q in range(3):
                        idx_all[r, q] = idx[q]
                    break
                base[0], base[1], base[2] = bi * block, bj * block, bk * block
                for q in range(3):
                    u0[q] = (X[q] + s0 * d[q]) / h - 0.5 - idx[q]
                    du[q] = d[q] / h
                _cubic(pool, slot, base, dims, idx[0], idx[1], idx[2], u0, du, iso, c)
                ncell += 1
                if _first_crossing(c, s1 - s0, med, at_start, cuts, br):
                    crossed = True
                    break
                # Into the next cell: along the axis whose boundary came first (ties: all of them).
                for q in range(3):
                    if d[q] > 0.0 and ((idx[q] + 1.5) * h - X[q]) / d[q] <= s1:
                        idx[q] += 1
                    elif d[q] < 0.0 and ((idx[q] + 0.5) * h - X[q]) / d[q] <= s1:
                        idx[q] -= 1
                s0 = s1
            if st == NEEDS_CHUNK:
                break
            if not crossed:
                length += t_out
                for q in range(3):
                    X[q] += t_out * d[q]
                if face == 1 and d[1] > 0.0:
                    st = TRANSMITTED
                elif face == 1:
                    st = REFLECTED
                else:
                    st = SIDE
                break
            # The crossing: the gradient of the interpolant at the first point in the other phase.
            s_in, s_out = s0 + br[0], s0 + br[1]
            for q in range(3):
                u[q] = u0[q] + br[1] * du[q]
            gx = gy = gz = 0.0
            for a in range(2):
                for b in range(2):
                    for e in range(2):
                        f = c[4 + 4 * a + 2 * b + e]
                        wa = u[0] if a else 1.0 - u[0]
                        wb = u[1] if b else 1.0 - u[1]
                        we = u[2] if e else 1.0 - u[2]
                        gx += f * (1.0 if a else -1.0) * wb * we
                        gy += f * wa * (1.0 if b else -1.0) * we
                        gz += f * wa * wb * (1.0 if e else -1.0)
            nrm[0], nrm[1], nrm[2] = gx / h, gy / h, gz / h
            norm = math.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2])
            if norm == 0.0:
                nflat += 1
                new_med = 1 - med
                for q in range(3):
                    nd[q] = d[q]
            else:
                for q in range(3):
                    nrm[q] /= norm
                new_med = interface_event(d, nrm, med, n_wall, n_poly, fresnel, seed, ray_ids[r], ev, nd)
            ev += 1
            # Refracted: go on from the first point out of the old phase; reflected: from the last in it.
            s_at = s_out if new_med != med else s_in
            length += s_at
            for q in range(3):
                X[q] += s_at * d[q]
                d[q] = nd[q]
            med = new_med
            if ev >= max_events:
                st = TRAPPED
        for q in range(3):
            X_all[r, q] = X[q]
            D_all[r, q] = d[q]
        status[r] = st
        resume[r] = st == NEEDS_CHUNK
        ev_all[r] = ev
        length_all[r] = length
        med_all[r] = med
        cells_all[r] = ncell
        flat_all[r] = nflat
