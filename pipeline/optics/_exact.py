"""Numba kernels of the exact references (docs/methods.md#exact-references): lattices of circular tubes and
polygonal honeycombs, extruded along L, traced with exact ray-circle and
ray-line intersections.

Geometry is 2-D in the R-T plane [µm]; rays are 3-D (the L component of a
direction is conserved, as the normals lie in the R-T plane).  Sites of the
lattice are s(i, j) = origin + i·a1 + j·a2 + jitter(i, j), the jitter a
counter-based hash of (seed, i, j), so the geometry is defined everywhere and
any region can be voxelised alone.

geo (float64 array): a1 (0-1), a2 (2-3), origin (4-5), jitter amplitude [µm]
(6), inverse of [a1 a2] (7-10), then per family
- TUBES: outer radius (11), inner radius (12): wall where a point lies in
  some site's outer disc and in no site's inner disc (touching or
  overlapping tubes merge their walls);
- CELLS: half wall (11): the lumen of site c is its Voronoi cell shrunk by
  the half wall, {x : (x − m_ck)·e_ck ≤ −w/2 for every neighbour k}, with m_ck
  the midpoint and e_ck the unit vector from s_c to s_k; wall elsewhere.
"""

import math

import numpy as np
from numba import njit

from .. import rng
from ..rng import normal, uniform
from .interface import REFLECTED, TRANSMITTED, TRAPPED, refract

TUBES = 0
CELLS = 1
SITE_KIND = rng.LATTICE_SITE
NOISE_KIND = rng.NORMAL_NOISE
REACH = 3  # lattice indices searched on each side of a point
HIT_EPS = 1e-9  # [µm] a crossing this close to the last one is the same one


@njit(inline="always", cache=True, nogil=True)
def site(geo, seed, i, j):
    jit = geo[6]
    x = geo[4] + i * geo[0] + j * geo[2]
    y = geo[5] + i * geo[1] + j * geo[3]
    if jit > 0.0:
        x += jit * (2.0 * uniform(seed, SITE_KIND, i, j, 0) - 1.0)
        y += jit * (2.0 * uniform(seed, SITE_KIND, i, j, 1) - 1.0)
    return x, y


@njit(inline="always", cache=True, nogil=True)
def lattice_index(geo, x, y):
    """The lattice indices (i, j) of the unjittered site nearest (x, y) in lattice coordinates."""
    dx = x - geo[4]
    dy = y - geo[5]
    u = geo[7] * dx + geo[8] * dy
    v = geo[9] * dx + geo[10] * dy
    return np.int64(math.floor(u + 0.5)), np.int64(math.floor(v + 0.5))


@njit(cache=True, nogil=True)
def phase_at(geo, kind, seed, x, y):
    """1 (wall) or 0 (polymer) at (x, y) [µm]."""
    i0, j0 = lattice_index(geo, x, y)
    if kind == TUBES:
        ro2 = geo[11] * geo[11]
        ri2 = geo[12] * geo[12]
        in_outer = False
        for i in range(i0 - REACH, i0 + REACH + 1):
            for j in range(j0 - REACH, j0 + REACH + 1):
                sx, sy = site(geo, seed, i, j)
                r2 = (x - sx) ** 2 + (y - sy) ** 2
                if r2 < ri2:
                    return np.uint8(0)
                if r2 < ro2:
                    in_outer = True
        return np.uint8(1) if in_outer else np.uint8(0)
    # CELLS: inside the nearest site's lumen, or wall.
    tab = np.empty((9, 9, 2))
    _fill_sites(geo, seed, i0, j0, tab)
    best = 1e300
    ca = 4
    cb = 4
    for a in range(3, 6):
        for b in range(3, 6):
            r2 = (x - tab[a, b, 0]) ** 2 + (y - tab[a, b, 1]) ** 2
            if r2 < best:
                best = r2
                ca = a
                cb = b
    t_in, nix, niy, t_out, nox, noy = _lumen_clip(tab, ca, cb, geo[11], x, y, 1.0, 0.0)
    return np.uint8(0) if t_in < 0.0 < t_out else np.uint8(1)


@njit(cache=True, nogil=True)
def phase_grid(geo, kind, seed, xs, ys, out):
    """out[a, b] = phase_at(xs[a], ys[b]): a voxelised R-T section."""
    for a in range(xs.size):
        for b in range(ys.size):
            out[a, b] = phase_at(geo, kind, seed, xs[a], ys[b])


@njit(cache=True, nogil=True)
def _next_tube_crossing(geo, seed, px, py, dx, dy, medium, t_end, last_i, last_j, last_c):
    """The first boundary of the wall along p + t·(dx, dy), 0 < t <= t_end, of a tube lattice:
    (t, nx, ny, i, j, circle) with (nx, ny) the outward normal of the circle, t = -1 if none.

    Crossings of a circle that do not change the phase (an outer circle inside
    another tube's wall) are passed over."""
    a = dx * dx + dy * dy
    mx = px + 0.5 * t_end * dx
    my = py + 0.5 * t_end * dy
    i0, j0 = lattice_index(geo, mx, my)
    best_t = 1e300
    bnx = 0.0
    bny = 0.0
    bi = 0
    bj = 0
    bc = -1
    # Candidates in increasing t: repeat the search above the last refused one.
    t_low = 0.0
    while True:
        best_t = 1e300
        for i in range(i0 - REACH, i0 + REACH + 1):
            for j in range(j0 - REACH, j0 + REACH + 1):
                sx, sy = site(geo, seed, i, j)
                ox = px - sx
                oy = py - sy
                b = ox * dx + oy * dy
                c0 = ox * ox + oy * oy
                for circ in range(2):
                    r = geo[11 + circ]
                    if r <= 0.0:
                        continue
                    disc = b * b - a * (c0 - r * r)
                    if disc <= 0.0:
                        continue
                    sq = math.sqrt(disc)
                    for sgn in (-1.0, 1.0):
                        t = (-b + sgn * sq) / a
                        if t <= t_low or t > t_end or t >= best_t:
                            continue
                        if i == last_i and j == last_j and circ == last_c and t < HIT_EPS:
                            continue
                        best_t = t
                        bnx = (ox + t * dx) / r
                        bny = (oy + t * dy) / r
                        bi = i
                        bj = j
                        bc = circ
        if bc < 0 or best_t > t_end:
            return -1.0, 0.0, 0.0, 0, 0, -1
        # A real boundary: the phase just beyond differs from the ray's.
        q = best_t + HIT_EPS * 10.0
        if phase_at(geo, np.int64(TUBES), seed, px + q * dx, py + q * dy) != medium:  # not a literal: one compile
            return best_t, bnx, bny, bi, bj, bc
        t_low = best_t
        bc = -1


@njit(inline="always", cache=True, nogil=True)
def _fill_sites(geo, seed, i0, j0, tab):
    """tab[a, b] = site (i0 - H + a, j0 - H + b), H = tab.shape[0] // 2."""
    half = tab.shape[0] // 2
    for a in range(tab.shape[0]):
        for b in range(tab.shape[1]):
            x, y = site(geo, seed, i0 - half + a, j0 - half + b)
            tab[a, b, 0] = x
            tab[a, b, 1] = y


@njit(inline="always", cache=True, nogil=True)
def _lumen_clip(tab, a, b, h, px, py, dx, dy):
    """Where the line p + t·d is inside the lumen of site tab[a, b] (Cyrus-Beck against the
    half-planes of its neighbours tab[a ± 2, b ± 2]): (t_in, nx_in, ny_in, t_out, nx_out, ny_out),
    each with the outward normal of its face; t_in > t_out if the line misses the lumen."""
    cx = tab[a, b, 0]
    cy = tab[a, b, 1]
    t_in = -1e300
    t_out = 1e300
    nix = 0.0
    niy = 0.0
    nox = 0.0
    noy = 0.0
    for i in range(a - 2, a + 3):
        for j in range(b - 2, b + 3):
            if i == a and j == b:
                continue
            ex = tab[i, j, 0] - cx
            ey = tab[i, j, 1] - cy
            n = math.sqrt(ex * ex + ey * ey)
            ex /= n
            ey /= n
            den = dx * ex + dy * ey
            # Inside where (x - m)·e <= -h: den·t <= num.
            num = -h - ((px - 0.5 * (cx + tab[i, j, 0])) * ex + (py - 0.5 * (cy + tab[i, j, 1])) * ey)
            if den == 0.0:
                if num < 0.0:
                    return 1.0, 0.0, 0.0, -1.0, 0.0, 0.0
                continue
            t = num / den
            if den < 0.0:
                if t > t_in:
                    t_in = t
                    nix = ex
                    niy = ey
            elif t < t_out:
                t_out = t
                nox = ex
                noy = ey
    return t_in, nix, niy, t_out, nox, noy


@njit(cache=True, nogil=True)
def _next_cell_crossing(geo, seed, px, py, dx, dy, medium, t_end, tab):
    """The first lumen face along p + t·(dx, dy), HIT_EPS < t <= t_end, of a honeycomb:
    (t, nx, ny), t = -1 if none.  In a lumen: the face it leaves by; in the wall:
    the nearest lumen it enters (lumens are disjoint convex polygons)."""
    h = geo[11]
    half = tab.shape[0] // 2
    if medium == 0:
        i0, j0 = lattice_index(geo, px, py)
        _fill_sites(geo, seed, i0, j0, tab)
        best = 1e300
        ca = half
        cb = half
        for a in range(half - 1, half + 2):
            for b in range(half - 1, half + 2):
                r2 = (px - tab[a, b, 0]) ** 2 + (py - tab[a, b, 1]) ** 2
                if r2 < best:
                    best = r2
                    ca = a
                    cb = b
        t_in, nix, niy, t_out, nox, noy = _lumen_clip(tab, ca, cb, h, px, py, dx, dy)
        if t_out <= t_end:
            return max(t_out, 0.0), nox, noy
        return -1.0, 0.0, 0.0
    a2 = dx * dx + dy * dy
    mx = px + 0.5 * t_end * dx
    my = py + 0.5 * t_end * dy
    i0, j0 = lattice_index(geo, mx, my)
    _fill_sites(geo, seed, i0, j0, tab)
    # A lumen lies within this distance of its site
    pitch = math.sqrt(geo[0] ** 2 + geo[1] ** 2)
    # (the covering radius of the lattice, 0.71 pitch at most, plus the jitter).
    reach = 0.71 * pitch + 1.42 * geo[6]
    best = -1.0
    bnx = 0.0
    bny = 0.0
    for a in range(half - REACH, half + REACH + 1):
        for b in range(half - REACH, half + REACH + 1):
            ox = tab[a, b, 0] - px
            oy = tab[a, b, 1] - py
            s = min(max((ox * dx + oy * dy) / a2, 0.0), t_end)
            if (ox - s * dx) ** 2 + (oy - s * dy) ** 2 > reach * reach:
                continue
            t_in, nix, niy, t_out, nox, noy = _lumen_clip(tab, a, b, h, px, py, dx, dy)
            if t_in < t_out and t_in > HIT_EPS and t_in <= t_end and (best < 0.0 or t_in < best):
                best = t_in
                bnx = nix
                bny = niy
    return best, bnx, bny


@njit(cache=True, nogil=True)
def trace_lattice(geo, kind, seed, pos, dirs, n_wall, n_poly, thickness, max_events, seg_len, noise,
                  out_dir, out_pos, status, events, path_out, medium_out, normals_out):
    """Trace rays (pos (N, 3) [µm] on T = 0, unit dirs (N, 3) with dirs[:, 1] > 0) through the
    lattice between T = 0 and T = thickness, exactly.

    Writes the final direction and point, the status (TRANSMITTED, REFLECTED,
    TRAPPED), the number of interfaces met and the path length [µm].  ``seg_len`` [µm]: the
    search for the next crossing looks one segment of this length ahead
    (about a pitch).  ``normals_out`` (N, 2): the normal of the first
    interface each ray meets (for tests).  ``noise`` [radian] > 0 turns each
    normal in the R-T plane by a normal deviate of that standard deviation
    (hashed per ray and interface): how much a normal estimator's error moves
    what a study reports.
    """
    d = np.empty(3)
    nd = np.empty(3)
    nrm = np.zeros(3)
    tab = np.empty((11, 11, 2))
    for r in range(pos.shape[0]):
        px = pos[r, 0]
        py = pos[r, 1]
        pz = pos[r, 2]
        for q in range(3):
            d[q] = dirs[r, q]
        med = np.int64(phase_at(geo, kind, seed, px, py))  # its type after `1 - med`: callees compile once
        ev = 0
        st = 0
        path = 0.0
        li = np.int64(-(1 << 40))
        lj = np.int64(0)
        lc = np.int64(-1)
        normals_out[r, 0] = 0.0
        normals_out[r, 1] = 0.0
        while st == 0:
            if ev >= max_events:
                st = TRAPPED
                break
            dx = d[0]
            dy = d[1]
            a2 = math.sqrt(dx * dx + dy * dy)
            # Along the 3-D ray: one segment of the R-T projection (half of it for cells).
            t_seg = (seg_len if kind == TUBES else 0.5 * seg_len) / a2
            # The T faces bound the segment.
            t_face = 1e300
            if dy > 0.0:
                t_face = (thickness - py) / dy
            elif dy < 0.0:
                t_face = -py / dy
            t_end = min(t_seg, t_face)
            if kind == TUBES:
                t, nx, ny, bi, bj, bc = _next_tube_crossing(geo, seed, px, py, dx, dy, med, t_end, li, lj, lc)
            else:
                bi = np.int64(0)
                bj = np.int64(0)
                bc = 0
                t, nx, ny = _next_cell_crossing(geo, seed, px, py, dx, dy, med, t_end, tab)
            if t < 0.0:
                px += t_end * dx
                py += t_end * dy
                pz += t_end * d[2]
                path += t_end
                if t_end == t_face:
                    st = TRANSMITTED if dy > 0.0 else REFLECTED
                    py = thickness if dy > 0.0 else 0.0
                continue
            px += t * dx
            py += t * dy
            pz += t * d[2]
            path += t
            # Orient the normal against the ray, then Snell or total reflection.
            if nx * dx + ny * dy > 0.0:
                nx = -nx
                ny = -ny
            n1 = n_wall if med == 1 else n_poly
            n2 = n_poly if med == 1 else n_wall
            if noise > 0.0:
                a = noise * normal(seed, NOISE_KIND, r, ev, 0)
                ca = math.cos(a)
                sa = math.sin(a)
                nx, ny = ca * nx - sa * ny, sa * nx + ca * ny
            if ev == 0:
                normals_out[r, 0] = nx
                normals_out[r, 1] = ny
            nrm[0] = nx
            nrm[1] = ny
            reflected = refract(d, nrm, n1, n2, nd)
            s = math.sqrt(nd[0] * nd[0] + nd[1] * nd[1] + nd[2] * nd[2])
            for q in range(3):
                d[q] = nd[q] / s
            if not reflected:
                med = 1 - med
            ev += 1
            li = bi
            lj = bj
            lc = bc
            if kind == CELLS:
                # Off the face by a hair, so the next search starts on the right side of it.
                px += HIT_EPS * d[0]
                py += HIT_EPS * d[1]
                pz += HIT_EPS * d[2]
                path += HIT_EPS
        for q in range(3):
            out_dir[r, q] = d[q]
        out_pos[r, 0] = px
        out_pos[r, 1] = py
        out_pos[r, 2] = pz
        status[r] = st
        events[r] = ev
        path_out[r] = path
        medium_out[r] = med
