"""Numba kernels of the ray tracer (SPEC.md §5).

Coordinates are continuous voxel coordinates along [R, T, L]: voxel
(i, j, k) occupies [i, i+1) × [j, j+1) × [k, k+1).  The sample spans
T ∈ [0, nT); a ray leaving through T = nT is transmitted, through T = 0 it
is reflected back out.  Voxels are read through a table of resident chunks;
a ray that needs a chunk that is not resident pauses (status NEEDS_CHUNK)
with its full state saved, so resuming it later gives bit-identical results
whatever was resident when.
"""

import math

import numpy as np
from numba import njit

from ..microstructure._rng import uniform

# Ray status.
ACTIVE = 0
TRANSMITTED = 1
REFLECTED = 2  # left back through the entrance face
SIDE = 3  # left through a side of a finite volume
TRAPPED = 4  # hit the event cap
NEEDS_CHUNK = 10
NEEDS_NORMAL = 11  # paper mode: waiting for the SVM normal

# Voxel lookup results besides 0 (polymer) and 1 (wall).
MISSING = 254
OUTSIDE = 253

# Methods.
PAPER = 0  # fixed steps, crossing at the midpoint, SVM normal (computed in Python)
EXACT = 1  # voxel traversal, crossing on the voxel face, Gaussian-gradient normal

FRESNEL_KIND = 40  # random-stream kind for partial reflection
NEWTON_REACH = 3.0  # the crossing point moves at most this far along the ray [voxels]


@njit(inline="always", cache=True, nogil=True)
def voxel_at(pool, table, box, cs, i, j, k):
    """Phase of voxel (i, j, k): 0/1, MISSING if its chunk is not resident, OUTSIDE."""
    ci = i // cs[0]
    cj = j // cs[1]
    ck = k // cs[2]
    a = ci - box[0]
    b = cj - box[1]
    c = ck - box[2]
    if a < 0 or b < 0 or c < 0 or a >= table.shape[0] or b >= table.shape[1] or c >= table.shape[2]:
        return MISSING
    s = table[a, b, c]
    if s == -2:
        return OUTSIDE
    if s < 0:
        return MISSING
    return pool[s, i - ci * cs[0], j - cj * cs[1], k - ck * cs[2]]


@njit(inline="always", cache=True, nogil=True)
def chunk_of(cs, i, j, k):
    return i // cs[0], j // cs[1], k // cs[2]


# --------------------------------------------------------------------------
# Interface physics
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def refract(d, n, n1, n2, out):
    """Snell refraction or total internal reflection (SPEC.md eq. 1-4).

    d : unit incident direction; n : unit normal facing the incoming ray
    (n·d < 0); n1, n2 : indices before and after.  Writes the new direction
    into ``out`` and returns True for total internal reflection.
    """
    if n1 == n2:
        # Index matched: the ray goes straight, exactly.
        for q in range(3):
            out[q] = d[q]
        return False
    cos_i = -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2])
    eta = n1 / n2
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        for q in range(3):
            out[q] = d[q] + 2.0 * cos_i * n[q]
        return True
    f = eta * cos_i - math.sqrt(1.0 - sin2_t)
    for q in range(3):
        out[q] = eta * d[q] + f * n[q]
    return False


@njit(cache=True, nogil=True)
def fresnel_reflectance(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance; 1 beyond the critical angle."""
    eta = n1 / n2
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs * rs + rp * rp)


@njit(cache=True, nogil=True)
def _normalise(v):
    s = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if s > 0.0:
        v[0] /= s
        v[1] /= s
        v[2] /= s
    return s


# --------------------------------------------------------------------------
# Normal estimation: gradient of the Gaussian-smoothed wall indicator
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _window_across_chunks(pool, table, box, cs, shape, n, i0, j0, k0, wx, wy, wz, dx, dy, dz):
    """smoothed_wall's sums for a window that crosses chunks (or the volume's T faces).

    Returns (flag, the three gradient sums, the weight sum); flag -1.0 when a
    chunk is not resident.
    The sums run in the same order as the one-chunk loop, so both give the same bits.
    """
    gx = 0.0
    gy = 0.0
    gz = 0.0
    ssum = 0.0
    # Voxel indices of the window along each axis (clamped where the volume
    # ends), split into chunk index and offset.  Each row of the sum reads a
    # few runs of voxels (one per chunk it crosses, usually one) from the
    # pool, and the chunk table is consulted once per run.
    ci = np.empty(n, np.int64)
    oi = np.empty(n, np.int64)
    cj = np.empty(n, np.int64)
    oj = np.empty(n, np.int64)
    ck = np.empty(n, np.int64)
    ok = np.empty(n, np.int64)
    for q in range(n):
        i = min(max(i0 + q, 0), shape[0] - 1) if shape[0] > 0 else i0 + q
        j = min(max(j0 + q, 0), shape[1] - 1)
        k = min(max(k0 + q, 0), shape[2] - 1) if shape[2] > 0 else k0 + q
        ci[q] = i // cs[0]
        oi[q] = i - ci[q] * cs[0]
        cj[q] = j // cs[1]
        oj[q] = j - cj[q] * cs[1]
        ck[q] = k // cs[2]
        ok[q] = k - ck[q] * cs[2]
    run_end = np.empty(n, np.int64)  # end of the run of equal chunk index along R
    run_end[n - 1] = n
    for q in range(n - 2, -1, -1):
        run_end[q] = run_end[q + 1] if ci[q + 1] == ci[q] else q + 1
    for c in range(n):
        if wz[c] == 0.0:
            continue
        tc = ck[c] - box[2]
        for b in range(n):
            if wy[b] == 0.0:
                continue
            tb = cj[b] - box[1]
            sx = 0.0
            sdx = 0.0
            lo = 0
            while lo < n:
                hi = run_end[lo]
                ta = ci[lo] - box[0]
                if (ta < 0 or tb < 0 or tc < 0 or ta >= table.shape[0] or tb >= table.shape[1]
                        or tc >= table.shape[2]):
                    return -1.0, 0.0, 0.0, 0.0, 0.0
                slot = table[ta, tb, tc]
                if slot == -1:
                    return -1.0, 0.0, 0.0, 0.0, 0.0
                if slot >= 0:  # -2: outside a finite volume, not wall
                    for a in range(lo, hi):
                        if pool[slot, oi[a], oj[b], ok[c]] == 1:
                            sx += wx[a]
                            sdx += dx[a]
                lo = hi
            gx += sdx * wy[b] * wz[c]
            gy += sx * dy[b] * wz[c]
            gz += sx * wy[b] * dz[c]
            ssum += sx * wy[b] * wz[c]
    return 0.0, gx, gy, gz, ssum


@njit(cache=True, nogil=True)
def smoothed_wall(pool, table, box, cs, shape, x, sigma, radius, grad):
    """S(x) = (G_σ * χ_wall)(x) / ΣG and its gradient direction (into ``grad``).

    The sum runs over the voxels within ``radius`` of x with separable
    weights; indices beyond the volume are clamped (replicated border).
    Returns S in [0, 1], or -1.0 when a needed chunk is not resident.
    """
    # Voxel centres within ±radius of x along each axis: a window centred on x,
    # so truncation does not tilt the gradient.
    n = 2 * np.int64(math.floor(radius)) + 2
    i0 = np.int64(math.ceil(x[0] - 0.5 - radius))
    j0 = np.int64(math.ceil(x[1] - 0.5 - radius))
    k0 = np.int64(math.ceil(x[2] - 0.5 - radius))
    wx = np.zeros(n)
    wy = np.zeros(n)
    wz = np.zeros(n)
    dx = np.zeros(n)
    dy = np.zeros(n)
    dz = np.zeros(n)
    inv2s2 = 0.5 / (sigma * sigma)
    sw = np.zeros(3)
    for q in range(n):
        ax = i0 + q + 0.5 - x[0]
        ay = j0 + q + 0.5 - x[1]
        az = k0 + q + 0.5 - x[2]
        if abs(ax) <= radius:
            wx[q] = math.exp(-ax * ax * inv2s2)
        if abs(ay) <= radius:
            wy[q] = math.exp(-ay * ay * inv2s2)
        if abs(az) <= radius:
            wz[q] = math.exp(-az * az * inv2s2)
        dx[q] = ax * wx[q]
        dy[q] = ay * wy[q]
        dz[q] = az * wz[q]
        sw[0] += wx[q]
        sw[1] += wy[q]
        sw[2] += wz[q]
    gx = 0.0
    gy = 0.0
    gz = 0.0
    ssum = 0.0
    # Usually the whole window lies in one resident chunk: read the pool directly.
    slot = -1
    ci0, cj0, ck0 = chunk_of(cs, i0, j0, k0)
    if (ci0 == (i0 + n - 1) // cs[0] and cj0 == (j0 + n - 1) // cs[1] and ck0 == (k0 + n - 1) // cs[2]
            and j0 >= 0 and j0 + n <= shape[1]
            and (shape[0] == 0 or (i0 >= 0 and i0 + n <= shape[0]))
            and (shape[2] == 0 or (k0 >= 0 and k0 + n <= shape[2]))):
        a_ = ci0 - box[0]
        b_ = cj0 - box[1]
        c_ = ck0 - box[2]
        if (0 <= a_ < table.shape[0] and 0 <= b_ < table.shape[1] and 0 <= c_ < table.shape[2]):
            slot = table[a_, b_, c_]
    if slot >= 0:
        oi0 = i0 - ci0 * cs[0]
        oj0 = j0 - cj0 * cs[1]
        ok0 = k0 - ck0 * cs[2]
        for c in range(n):
            if wz[c] == 0.0:
                continue
            for b in range(n):
                if wy[b] == 0.0:
                    continue
                sx = 0.0
                sdx = 0.0
                for a in range(n):
                    if pool[slot, oi0 + a, oj0 + b, ok0 + c] == 1:
                        sx += wx[a]
                        sdx += dx[a]
                gx += sdx * wy[b] * wz[c]
                gy += sx * dy[b] * wz[c]
                gz += sx * wy[b] * dz[c]
                ssum += sx * wy[b] * wz[c]
    else:
        flag, gx, gy, gz, ssum = _window_across_chunks(pool, table, box, cs, shape, n, i0, j0, k0,
                                                       wx, wy, wz, dx, dy, dz)
        if flag < 0.0:
            return -1.0
    W = sw[0] * sw[1] * sw[2]
    S = ssum / W
    # ∇S = (Σ χ ∇w − S ∇W) / W: the second term cancels what the finite window
    # adds, so a structure uniform along an axis has no gradient along it.
    sd0 = 0.0
    sd1 = 0.0
    sd2 = 0.0
    for q in range(n):
        sd0 += dx[q]
        sd1 += dy[q]
        sd2 += dz[q]
    s2 = sigma * sigma
    grad[0] = (gx - S * sd0 * sw[1] * sw[2]) / (W * s2)
    grad[1] = (gy - S * sw[0] * sd1 * sw[2]) / (W * s2)
    grad[2] = (gz - S * sw[0] * sw[1] * sd2) / (W * s2)
    return S


@njit(cache=True, nogil=True)
def surface_normal(pool, table, box, cs, shape, xf, d, sigma, radius, newton, out):
    """Normal where the ray meets the smoothed wall surface S = 1/2 near face point xf.

    Up to ``newton`` Newton steps along the ray (at most NEWTON_REACH from xf)
    move the point onto the iso-surface, so rays crossing one staircase face
    at different places get the normals of the surface they really meet.
    Returns 1 on success, 0 for a one-phase neighbourhood, -1 for a missing chunk.
    """
    x = np.empty(3)
    for q in range(3):
        x[q] = xf[q]
    t = 0.0
    for it in range(newton + 1):
        S = smoothed_wall(pool, table, box, cs, shape, x, sigma, radius, out)
        if S < 0.0:
            return -1
        if it == newton:
            break
        slope = out[0] * d[0] + out[1] * d[1] + out[2] * d[2]
        if abs(S - 0.5) < 1e-6 or abs(slope) < 1e-3:
            break
        t_new = min(max(t - (S - 0.5) / slope, -NEWTON_REACH), NEWTON_REACH)
        if t_new == t:
            break
        t = t_new
        for q in range(3):
            x[q] = xf[q] + t * d[q]
    if _normalise(out) < 1e-12:
        return 0
    return 1


# --------------------------------------------------------------------------
# The tracer
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _interface(d, nrm, medium, n_wall, n_poly, fresnel, seed, ray_id, event, newd):
    """Apply one interface event; returns the medium after it."""
    # Orient the normal to face the incoming ray.
    if nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2] > 0.0:
        for q in range(3):
            nrm[q] = -nrm[q]
    n1 = n_wall if medium == 1 else n_poly
    n2 = n_poly if medium == 1 else n_wall
    tir = refract(d, nrm, n1, n2, newd)
    if n1 == n2:
        return 1 - medium
    if not tir and fresnel:
        cos_i = -(nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2])
        if uniform(seed, FRESNEL_KIND, ray_id, event, 0) < fresnel_reflectance(cos_i, n1, n2):
            for q in range(3):
                newd[q] = d[q] + 2.0 * cos_i * nrm[q]
            tir = True
    _normalise(newd)
    return medium if tir else 1 - medium


@njit(cache=True, nogil=True)
def trace(pos, dirs, medium, vox, status, events, path, fallbacks, request, normals,
          ray_ids, pool, table, box, cs, shape, method, step, sigma, radius, newton,
          n_wall, n_poly, fresnel, seed, max_events):
    """Advance every ACTIVE / paused ray as far as the resident chunks allow.

    Per ray: pos (3) float64, dirs (3) unit float64, medium 0/1, vox (3) int64
    current voxel (EXACT mode), status, events (interfaces met), path length
    [voxels], fallbacks (2): degenerate normals, and (EXACT) events whose new
    direction disagreed with the crossed voxel face.  ``request`` receives the chunk a
    NEEDS_CHUNK ray waits for, or (paper mode) the crossing point of a
    NEEDS_NORMAL ray, whose normal arrives in ``normals``.
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
            medium[r] = _interface(d, nrm, medium[r], n_wall, n_poly, fresnel, seed, ray_ids[r],
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
            if method == EXACT:
                # Distance to the next voxel face along each axis.
                tmin = 1e300
                axis = -1
                for q in range(3):
                    if d[q] > 0.0:
                        t = (vox[r, q] + 1 - x[q]) / d[q]
                    elif d[q] < 0.0:
                        t = (vox[r, q] - x[q]) / d[q]
                    else:
                        t = 1e300
                    if t < tmin:
                        tmin = t
                        axis = q
                sgn = 1 if d[axis] > 0.0 else -1
                nv0 = vox[r, 0] + (sgn if axis == 0 else 0)
                nv1 = vox[r, 1] + (sgn if axis == 1 else 0)
                nv2 = vox[r, 2] + (sgn if axis == 2 else 0)
                # Leaving the sample through a T face or a side.
                if nv1 >= shape[1]:
                    _advance(pos, r, d, tmin, path)
                    pos[r, 1] = shape[1]
                    status[r] = TRANSMITTED
                    break
                if nv1 < 0:
                    _advance(pos, r, d, tmin, path)
                    pos[r, 1] = 0.0
                    status[r] = REFLECTED
                    break
                v = voxel_at(pool, table, box, cs, nv0, nv1, nv2)
                if _stops(v, pos, r, d, tmin, path, status, request, cs, nv0, nv1, nv2):
                    break
                if v == medium[r]:
                    _advance(pos, r, d, tmin, path)
                    pos[r, axis] = vox[r, axis] + (1 if sgn > 0 else 0)
                    vox[r, 0] = nv0
                    vox[r, 1] = nv1
                    vox[r, 2] = nv2
                    continue
                # An interface on the face between vox and the next voxel.
                for q in range(3):
                    x[q] = pos[r, q] + tmin * d[q]
                x[axis] = vox[r, axis] + (1 if sgn > 0 else 0)
                if n_wall == n_poly:
                    # Index-matched: every interface is invisible, no normal needed.
                    ok = 2
                else:
                    ok = surface_normal(pool, table, box, cs, shape, x, d, sigma, radius, newton, nrm)
                if ok < 0:
                    if not _request_neighbourhood(pool, table, box, cs, shape, x, d, radius,
                                                  request, r):
                        raise RuntimeError("normal window needs a chunk the request cannot name")
                    status[r] = NEEDS_CHUNK
                    break
                if ok == 0:
                    fallbacks[r, 0] += 1
                    for q in range(3):
                        nrm[q] = 0.0
                    nrm[axis] = -sgn
                if ok == 2:
                    new_medium = 1 - medium[r]
                    for q in range(3):
                        newd[q] = d[q]
                else:
                    new_medium = _interface(d, nrm, medium[r], n_wall, n_poly, fresnel, seed,
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
                    vox[r, 0] = nv0
                    vox[r, 1] = nv1
                    vox[r, 2] = nv2
                    medium[r] = v
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
                v = voxel_at(pool, table, box, cs, i, j, k)
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
def _request_neighbourhood(pool, table, box, cs, shape, x, d, radius, request, r):
    """Record one missing chunk that the normal at face point x may read.

    The box is the union of smoothed_wall's windows at both ends of the
    Newton search (x ± NEWTON_REACH·d), computed exactly as it computes them.
    """
    n = 2 * np.int64(math.floor(radius)) + 2
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for q in range(3):
        a = np.int64(math.ceil(x[q] - NEWTON_REACH * abs(d[q]) - 0.5 - radius))
        b = np.int64(math.ceil(x[q] + NEWTON_REACH * abs(d[q]) - 0.5 - radius)) + n - 1
        if shape[q] > 0:
            a = min(max(a, 0), shape[q] - 1)
            b = min(max(b, 0), shape[q] - 1)
        lo[q] = a
        hi[q] = b
    # Steps of one chunk from lo to hi (and hi itself) meet every chunk the box
    # spans, also when the window is wider than two chunks.
    i = lo[0]
    while True:
        j = lo[1]
        while True:
            k = lo[2]
            while True:
                if voxel_at(pool, table, box, cs, i, j, k) == MISSING:
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
