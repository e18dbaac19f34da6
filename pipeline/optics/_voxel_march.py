"""Numba kernel of the voxel tracer: every ray marched through resident chunks.

The sample spans T ∈ [0, nT) voxels; a ray leaving through T = nT is
transmitted, through T = 0 it is reflected back out.  A ray that needs a
chunk that is not resident pauses (status NEEDS_CHUNK) with its full state
saved, so resuming it later gives bit-identical results whatever was
resident when (docs/methods.md#voxel-methods).
"""

import math

import numpy as np
from numba import njit

from ._normals import NEWTON_REACH, NO_SURFACE, surface_normal
from ._packing import MISSING, OUTSIDE, chunk_of, chunk_slot, voxel_at
from .interface import (ACTIVE, NEEDS_CHUNK, NEEDS_NORMAL, REFLECTED, SIDE, TRANSMITTED, TRAPPED,
                        interface_event)

# How a voxel method marches (not the method `exact`, which traces surfaces, not voxels).
FIXED_STEPS = 0  # the paper's: fixed steps, crossing at the midpoint, SVM normal (computed in Python)
TRAVERSAL = 1  # fast/accurate: voxel traversal, crossing on the voxel face, Gaussian-gradient normal



@njit(cache=True, nogil=True)
def march_voxels(pos, dirs, medium, vox, status, events, path, fallbacks, request, normals,
                 ray_ids, bits, masks, table, box, cs, shape, method, step, sigma, radius, newton, refit,
                 n_wall, n_poly, fresnel, seed, max_events, wts, segs, slots):
    """Advance every ACTIVE / paused ray as far as the resident chunks allow.

    Per ray: pos (3) float64, dirs (3) unit float64, medium 0/1, vox (3) int64
    current voxel (TRAVERSAL), status, events (interfaces met), path length
    [voxels], fallbacks (3): degenerate normals, (TRAVERSAL) events whose new
    direction disagreed with the crossed voxel face, and (TRAVERSAL) normals taken
    at the face point for want of a 1/2-level surface (thin walls).  ``request`` receives the chunk a
    NEEDS_CHUNK ray waits for, or (paper mode) the crossing point of a
    NEEDS_NORMAL ray, whose normal arrives in ``normals``.
    bits, masks, table, box : the resident chunks, bit-packed (pack_chunks), their
    row masks (pack_chunks) and the table of their slots (ChunkCache);
    wts, segs, slots : smoothed_wall's
    scratch (window_scratch).
    shape : (nR, nT, nL); nR or nL = 0 means unbounded along that axis.
    """
    newd = np.empty(3)
    nrm = np.empty(3)
    d = np.empty(3)
    x = np.empty(3)
    for r in range(pos.shape[0]):
        st = status[r]
        if st == NEEDS_NORMAL:
            # Resume a paper-mode ray with the SVM normal Python computed.
            for q in range(3):
                d[q] = dirs[r, q]
                nrm[q] = normals[r, q]
            if normals[r, 3] == 0.0:
                fallbacks[r, 0] += 1
                for q in range(3):
                    nrm[q] = -d[q]
            medium[r] = interface_event(d, nrm, medium[r], n_wall, n_poly, fresnel, seed, ray_ids[r],
                                   events[r], newd)
            events[r] += 1
            for q in range(3):
                dirs[r, q] = newd[q]
            status[r] = ACTIVE
        elif st == NEEDS_CHUNK:
            status[r] = ACTIVE
        elif st != ACTIVE:
            continue
        while status[r] == ACTIVE:
            if events[r] >= max_events:
                status[r] = TRAPPED
                break
            for q in range(3):
                d[q] = dirs[r, q]
                x[q] = pos[r, q]
            if method == TRAVERSAL:
                _march(r, pos, dirs, medium, vox, status, events, path, fallbacks, request, ray_ids,
                       bits, masks, table, box, cs, shape, sigma, radius, newton, refit, n_wall, n_poly,
                       fresnel, seed, max_events, wts, segs, slots, d, x, newd, nrm)
                break
            else:
                # Paper: fixed steps; a phase change between two samples is an
                # interface at their midpoint.
                for q in range(3):
                    x[q] = pos[r, q] + step * d[q]
                i = np.int64(math.floor(x[0]))
                j = np.int64(math.floor(x[1]))
                k = np.int64(math.floor(x[2]))
                if x[1] >= shape[1] or x[1] < 0.0:
                    # The exit plane lies within this step: go straight to it.
                    plane = shape[1] if x[1] >= shape[1] else 0.0
                    t = (plane - pos[r, 1]) / d[1]
                    _advance(pos, r, d, t, path)
                    pos[r, 1] = plane
                    status[r] = TRANSMITTED if plane > 0.0 else REFLECTED
                    break
                v = voxel_at(bits, table, box, cs, shape, i, j, k)
                if _stops(v, pos, r, d, step, path, status, request, cs, i, j, k):
                    break
                if v == medium[r]:
                    _advance(pos, r, d, step, path)
                    continue
                if n_wall == n_poly:
                    # Index-matched: the interface is counted, nothing deflects.
                    _advance(pos, r, d, step, path)
                    medium[r] = v
                    events[r] += 1
                    continue
                for q in range(3):
                    pos[r, q] = pos[r, q] + 0.5 * step * d[q]
                path[r] += 0.5 * step
                status[r] = NEEDS_NORMAL
                break


@njit(inline="always", cache=True, nogil=True)
def _face_t(v, s, x, d):
    """Distance along the ray from coordinate x to the face voxel v leaves by (direction sign s)."""
    if d == 0.0:
        return 1e300
    return (v + (1 if s > 0 else 0) - x) / d


@njit(inline="always", cache=True, nogil=True)
def _step(v, o, c, s, n):
    """One voxel along an axis: the voxel index, its offset in its chunk of n, the chunk index,
    and whether the chunk changed."""
    v += s
    o += s
    if o < 0 or o >= n:
        return v, o - s * n, c + s, True
    return v, o, c, False


@njit(cache=True, nogil=True)
def _march(r, pos, dirs, medium, vox, status, events, path, fallbacks, request, ray_ids,
           bits, masks, table, box, cs, shape, sigma, radius, newton, refit, n_wall, n_poly, fresnel,
           seed, max_events, wts, segs, slots, d, x, newd, nrm):
    """Exact voxel traversal of ray r until it leaves, pauses or is trapped.

    A straight segment runs from pos[r] (the last interface, or the entry
    point) along dirs[r]; vox[r] is the voxel the ray is in.  The distance to
    each next face is computed from the segment's origin and the current
    voxel alone, so a ray that pauses for a chunk resumes with the same
    numbers, whatever was resident when.  pos and path change only at
    interfaces and where the ray stops.
    """
    while True:
        if events[r] >= max_events:
            status[r] = TRAPPED
            return
        for q in range(3):
            d[q] = dirs[r, q]
            x[q] = pos[r, q]
        v0 = vox[r, 0]
        v1 = vox[r, 1]
        v2 = vox[r, 2]
        # Distance along the segment to the next face on each axis.
        s0 = 1 if d[0] > 0.0 else -1
        s1 = 1 if d[1] > 0.0 else -1
        s2 = 1 if d[2] > 0.0 else -1
        t0 = _face_t(v0, s0, x[0], d[0])
        t1 = _face_t(v1, s1, x[1], d[1])
        t2 = _face_t(v2, s2, x[2], d[2])
        # The current voxel's chunk, its slot and the offsets in it.
        c0 = v0 // cs[0]
        c1 = v1 // cs[1]
        c2 = v2 // cs[2]
        o0 = v0 - c0 * cs[0]
        o1 = v1 - c1 * cs[1]
        o2 = v2 - c2 * cs[2]
        slot = chunk_slot(table, box, c0, c1, c2)
        while True:
            # Step into the next voxel across the nearest face (ties: lowest axis).
            if t0 <= t1 and t0 <= t2:
                axis = 0
                tmin = t0
                sgn = s0
                v0, o0, c0, moved = _step(v0, o0, c0, s0, cs[0])
                if moved:
                    slot = chunk_slot(table, box, c0, c1, c2)
            elif t1 <= t2:
                axis = 1
                tmin = t1
                sgn = s1
                v1, o1, c1, moved = _step(v1, o1, c1, s1, cs[1])
                # Leaving the sample through a T face.
                if v1 >= shape[1] or v1 < 0:
                    for q in range(3):
                        pos[r, q] = x[q] + tmin * d[q]
                    pos[r, 1] = shape[1] if v1 >= shape[1] else 0.0
                    path[r] += tmin
                    status[r] = TRANSMITTED if v1 >= shape[1] else REFLECTED
                    return
                if moved:
                    slot = chunk_slot(table, box, c0, c1, c2)
            else:
                axis = 2
                tmin = t2
                sgn = s2
                v2, o2, c2, moved = _step(v2, o2, c2, s2, cs[2])
                if moved:
                    slot = chunk_slot(table, box, c0, c1, c2)
            if slot == -1:
                status[r] = _pause_for_chunk(request, r, cs, v0, v1, v2)
                return
            if (slot == -2 or (shape[0] > 0 and (v0 < 0 or v0 >= shape[0]))
                    or (shape[2] > 0 and (v2 < 0 or v2 >= shape[2]))):
                # Leaving a finite volume through a side.
                for q in range(3):
                    pos[r, q] = x[q] + tmin * d[q]
                path[r] += tmin
                status[r] = SIDE
                return
            v = np.uint8((bits[slot, o0, o1, o2 >> 6] >> np.uint64(o2 & 63)) & np.uint64(1))
            if v == medium[r]:
                vox[r, 0] = v0
                vox[r, 1] = v1
                vox[r, 2] = v2
                if axis == 0:
                    t0 = _face_t(v0, s0, x[0], d[0])
                elif axis == 1:
                    t1 = _face_t(v1, s1, x[1], d[1])
                else:
                    t2 = _face_t(v2, s2, x[2], d[2])
                continue
            # An interface on the face between vox[r] and voxel (v0, v1, v2).
            face = vox[r, axis] + (1 if sgn > 0 else 0)
            for q in range(3):
                x[q] = x[q] + tmin * d[q]
            x[axis] = face
            if n_wall == n_poly:
                # Index-matched: every interface is invisible, no normal needed.
                ok = 2
            else:
                ok = surface_normal(bits, masks, table, box, cs, shape, x, d, sigma, radius, newton, refit,
                                    nrm, wts, segs, slots)
            if ok < 0:
                if not _request_neighbourhood(bits, table, box, cs, shape, x, d, radius, request, r):
                    raise RuntimeError("normal window needs a chunk the request cannot name")
                status[r] = NEEDS_CHUNK
                return
            if ok == 0:
                fallbacks[r, 0] += 1
                for q in range(3):
                    nrm[q] = 0.0
                nrm[axis] = -sgn
            elif ok == NO_SURFACE:
                fallbacks[r, 2] += 1
            if ok == 2:
                new_medium = 1 - medium[r]
                for q in range(3):
                    newd[q] = d[q]
            else:
                new_medium = interface_event(d, nrm, medium[r], n_wall, n_poly, fresnel, seed,
                                        ray_ids[r], events[r], newd)
            events[r] += 1
            path[r] += tmin
            for q in range(3):
                pos[r, q] = x[q]
                dirs[r, q] = newd[q]
            # Physics sets the direction, the voxel face the medium: a new
            # direction through the face enters the next voxel.  With a
            # smoothed normal the two can disagree near grazing incidence;
            # following the face avoids bouncing on it forever.
            forward = newd[axis] * sgn > 0.0
            if forward != (new_medium != medium[r]):
                fallbacks[r, 1] += 1
            if forward:
                vox[r, 0] = v0
                vox[r, 1] = v1
                vox[r, 2] = v2
                medium[r] = v
            break



@njit(inline="always", cache=True, nogil=True)
def _pause_for_chunk(request, r, cs, i, j, k):
    """Record the chunk of voxel (i, j, k) as the one ray r waits for."""
    ci, cj, ck = chunk_of(cs, i, j, k)
    request[r, 0] = ci
    request[r, 1] = cj
    request[r, 2] = ck
    return NEEDS_CHUNK


@njit(inline="always", cache=True, nogil=True)
def _stops(v, pos, r, d, t, path, status, request, cs, i, j, k):
    """Stop ray r if the next voxel (i, j, k) is outside the volume or not resident."""
    if v == OUTSIDE:
        _advance(pos, r, d, t, path)
        status[r] = SIDE
        return True
    if v == MISSING:
        status[r] = _pause_for_chunk(request, r, cs, i, j, k)
        return True
    return False


@njit(inline="always", cache=True, nogil=True)
def _advance(pos, r, d, t, path):
    for q in range(3):
        pos[r, q] += t * d[q]
    path[r] += t


@njit(cache=True, nogil=True)
def _request_neighbourhood(bits, table, box, cs, shape, x, d, radius, request, r):
    """Record one missing chunk that the normal at face point x may read.

    The box is the union of smoothed_wall's windows (the voxel centres within
    ``radius``) at both ends of the Newton search, x ± NEWTON_REACH·d; a
    voxel more on each side is looked at only if that box lacks nothing, in
    case rounding put a window's edge one voxel further.
    """
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for margin in range(2):
        for q in range(3):
            a = np.int64(math.ceil(x[q] - NEWTON_REACH * abs(d[q]) - 0.5 - radius)) - margin
            b = np.int64(math.floor(x[q] + NEWTON_REACH * abs(d[q]) - 0.5 + radius)) + margin
            if shape[q] > 0:
                a = min(max(a, 0), shape[q] - 1)
                b = min(max(b, 0), shape[q] - 1)
            lo[q] = a
            hi[q] = b
        if _first_missing(bits, table, box, cs, shape, lo, hi, request, r):
            return True
    return False


@njit(cache=True, nogil=True)
def _first_missing(bits, table, box, cs, shape, lo, hi, request, r):
    """Record for ray r the first chunk of voxel box [lo, hi] that is not resident."""
    # Steps of one chunk from lo to hi (and hi itself) meet every chunk the box
    # spans, also when the window is wider than two chunks.
    i = lo[0]
    while True:
        j = lo[1]
        while True:
            k = lo[2]
            while True:
                if voxel_at(bits, table, box, cs, shape, i, j, k) == MISSING:
                    _pause_for_chunk(request, r, cs, i, j, k)
                    return True
                if k == hi[2]:
                    break
                k = min(k + cs[2], hi[2])
            if j == hi[1]:
                break
            j = min(j + cs[1], hi[1])
        if i == hi[0]:
            break
        i = min(i + cs[0], hi[0])
    return False
