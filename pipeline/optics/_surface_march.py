"""Numba kernel of the exact tracer on analytic surfaces (docs/methods.md#the-exact-method): the
generated wood's own and the reference lattices', one march for both.

Each point evaluation (:func:`~pipeline.optics._surface_points.surface_at`: wood or lattice,
chosen by the context's type) gives the phase and the primitives near the point, each with its
signed function g and a proven clearance.  A step may never let two primitives switch, nor pass
a regime surface (a ray band, a vessel outline, a ply) unless the rows of both its sides prove
the step (else it is cut short of the surface's root): a step is the least proven clearance,
except that inside the nearest
primitive A (its negative set, convex in the pulled-back coordinates, meets a
line in one interval) A may switch once, and the primitive crossed last is left
out of the clearance (the ray is leaving it).  A step whose end is in the other phase brackets a crossing,
refined by regula falsi on the switching primitive's g to ``tol``; its normal
is the gradient of g (:func:`surface_normal`: for wood the analytic gradient of the
primitive, for a lattice its circle's or line's own).  A clearance
below ``hit`` means the ray stands on a surface: the phase is sampled
``2·hit`` ahead.
"""

import math

import numpy as np
from numba import njit

from .._intrinsics import borrowed, carve
from ..microstructure.surface import C_CROSS, MAX_PRIMS, N_COLS, P_BAND, P_LUMEN, P_RAY_LUMEN, P_REACH
from ..microstructure.surface_ray import N_FRAME
from ._surface_march_rows import copy_rows, far_unproven, find_row, nearest, regime, same_key, switched
from ._surface_points import ray_clearances, root_guess, surface_at, surface_normal
from .interface import NEEDS_CHUNK, REFLECTED, TRANSMITTED, TRAPPED, interface_event

NEEDS_REGION = NEEDS_CHUNK  # the ray left the precomputed region: the caller widens it and traces again
# Tolerances [µm] (docs/methods.md#the-exact-method); halving them leaves the rays as they are.
HIT = 1e-9  # a clearance below this: the ray stands on a surface
TOL = 1e-9  # regula falsi narrows a crossing to this before the lattice bisection


PROBE = 1024.0  # lattice points (about 1e-9 µm) probed past a root where g and the phase part
OVERSHOOT = 1.25  # a secant step towards a surface goes this far past the secant's root, checked at its end
LATTICE = 2.0 ** -40  # [µm] crossings land on this lattice along a segment (~1e-12 µm)
ROWS = MAX_PRIMS * N_COLS
# What each point evaluation of the march was for, counted in its work buffer (docs/performance.md):
# a segment's first point, a step's end, cutting a regime step short, regula falsi on a crossing,
# the lattice point guessed from its root, the lattice bisection where the guess failed, the normal.
PURPOSES = ("start", "step", "regime_root", "root", "lattice_guess", "lattice_bisection", "normal")
# What set each step's length, counted after the purposes (docs/performance.md, "What bounds the
# steps"): A's own clearance and why no longer step was taken, the others' (the reach row's among
# them), the longer steps, the probe, and long steps that failed their check and were taken again.
STEP_BOUNDS = ("own", "own_free", "own_past_others", "own_again", "others", "others_reach", "secant", "away",
               "regime", "inside", "probe", "again", "cross")
(B_OWN, B_FREE, B_PAST, B_AGAIN_OWN, B_OTHERS, B_REACH, B_SECANT, B_AWAY, B_REGIME, B_INSIDE, B_PROBE, B_AGAIN,
 B_CROSS) = range(len(STEP_BOUNDS))
COUNTS = 3 * ROWS + 6 * 3 + 5 * 5  # after three row tables, six vectors and five keys: the counts
BOUNDS = COUNTS + len(PURPOSES)
FRAME = BOUNDS + len(STEP_BOUNDS)  # a ray's frame at a point (surface_ray.ray_frame)
WORK = FRAME + N_FRAME


def new_work() -> np.ndarray:
    """The march's work arrays, one buffer per thread; the caller owns it while the march runs.
    Its evaluations by purpose (:data:`PURPOSES`, from :data:`COUNTS` on) and its steps by what
    bounded them (:data:`STEP_BOUNDS`, from :data:`BOUNDS` on) start at zero and add up over the
    marches it serves."""
    work = np.empty(WORK)
    work[COUNTS:FRAME] = 0.0
    return work


@njit(inline="always", cache=True, nogil=True)
def _face(X, d, thickness):
    """Distance along d from X to the T face the ray heads for (1e300 along the faces)."""
    if d[1] > 0.0:
        return (thickness - X[1]) / d[1]
    if d[1] < 0.0:
        return -X[1] / d[1]
    return 1e300


@njit(cache=True, nogil=True)
def _before_root(X, d, s, s_end, g_lo, g_hi, key, lq, ctx, Pw, Pb, cache, every, tol):
    """Regula falsi (Illinois) on primitive ``key``'s g, whose sign differs at s and s_end: the
    last point found on s's side within ``tol`` of its root.  Returns (found, that point, its
    phase, its rows copied into Pb and their number, evaluations)."""
    lo = s
    hi = s_end
    ph_lo = np.uint8(0)
    n_lo = 0
    k = 0
    side = 0
    neg = g_lo < 0.0
    while hi - lo > tol:
        mid = lo + (hi - lo) * g_lo / (g_lo - g_hi)
        if not (lo < mid < hi) or hi - lo < 4.0 * tol:
            mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        ph, nm = surface_at(X[0] + mid * d[0], X[1] + mid * d[1], X[2] + mid * d[2], lq, ctx, Pw, cache, every)
        k += 1
        i = find_row(Pw, nm, key) if ph != 255 else -1
        if i < 0:
            return False, s, ph_lo, 0, k
        gm = Pw[i, 5]
        if (gm < 0.0) == neg:
            lo = mid
            g_lo = gm
            ph_lo = ph
            n_lo = nm
            copy_rows(Pb, Pw, nm)
            if side == -1:
                g_hi *= 0.5
            side = -1
        else:
            hi = mid
            g_hi = gm
            if side == 1:
                g_lo *= 0.5
            side = 1
    return lo > s, lo, ph_lo, n_lo, k


@njit(inline="always", cache=True, nogil=True)
def _at_lattice(X, d, k, lq, ctx, P, cache, every):
    """surface_at of lattice point k of the segment X + s·d (s = k·LATTICE).  Inlined: as a call it
    was given the context and the cache, some 190 words copied at every lattice point."""
    return surface_at(X[0] + k * LATTICE * d[0], X[1] + k * LATTICE * d[1], X[2] + k * LATTICE * d[2], lq, ctx, P,
                      cache, every)


@njit(cache=True, nogil=True)
def _lattice_bracket(X, d, s, s_end, lo, hi, med, single, lq, ctx, P, Pa, Pb, cache, every, ne):
    """The crossing in (lo, hi] (within the step (s, s_end], whose end is in the other phase) as
    adjacent lattice points klo, khi: the last in phase ``med`` and the first in the other, by
    bisection of the phase, their rows in Pa and Pb.  Where the phase has not changed at hi:
    if one primitive switched there (``single``), the phase is probed up to PROBE lattice points
    further (its g and the phase may part within rounding of its root); unchanged there too, the
    primitive changed no phase (a lumen entered inside its end wall) and the step is ``passed``
    with khi that last probe.  Otherwise the bisection runs to the step's end.  Returns (klo,
    khi, rows at klo, rows at khi, evaluations, passed)."""
    klo = math.floor(lo / LATTICE)
    khi = max(math.ceil(hi / LATTICE), klo + 1.0)
    pl, na = _at_lattice(X, d, klo, lq, ctx, Pa, cache, every)
    ph_hi, nb = _at_lattice(X, d, khi, lq, ctx, Pb, cache, every)
    ne += 2
    if pl != med:
        klo = math.floor(s / LATTICE)
        pl, na = _at_lattice(X, d, klo, lq, ctx, Pa, cache, every)
        ne += 1
    if ph_hi == med and single:
        jump = 1.0
        while ph_hi == med and jump <= PROBE:
            kp = khi + jump
            php, npp = _at_lattice(X, d, kp, lq, ctx, P, cache, every)
            ne += 1
            if php == med:  # the new lower end
                klo = khi
                na = nb
                copy_rows(Pa, Pb, nb)
            else:
                ph_hi = php
            khi = kp
            nb = npp
            copy_rows(Pb, P, npp)
            jump *= 2.0
        if ph_hi == med:
            return klo, khi, na, nb, ne, True
    if ph_hi == med:
        khi = max(math.ceil(s_end / LATTICE), klo + 1.0)
        ph_hi, nb = _at_lattice(X, d, khi, lq, ctx, Pb, cache, every)
        ne += 1
    while khi - klo > 1.0:
        kmid = math.floor(0.5 * (klo + khi))
        phm, nm = _at_lattice(X, d, kmid, lq, ctx, P, cache, every)
        ne += 1
        if phm == med:
            klo = kmid
            na = nm
            copy_rows(Pa, P, nm)
        else:
            khi = kmid
            nb = nm
            copy_rows(Pb, P, nm)
    return klo, khi, na, nb, ne, False


@njit(cache=True, nogil=True)
def march(pos, dirs, ray_ids, thickness, n_wall, n_poly, max_events, fresnel, fseed, ctx,
               hit, tol, step_scale, along, out_pos, out_dir, status, events, path, evals, passes, medium_out, log, cache,
               resume, skips, stop, work):
    """Trace rays from ``pos`` (N, 3) [µm] with unit ``dirs`` through the wood between T = 0 and
    T = ``thickness``; writes the exit point and direction, status, interfaces, path length [µm],
    the number of point evaluations and of surfaces passed without a phase change, and the phase
    each ray ends in.  ``log`` (N, E, 12) or empty: per ray its first E interfaces, (point,
    primitive key, normal, phase after).

    A ray that leaves the region (status NEEDS_REGION) ends where its last straight segment began,
    with the state it had there (interfaces, path, evaluations, passes, phase, the primitive
    crossed last in ``skips``), and ``stop`` the point outside the region its step needed (or where
    it stood); traced again from there with
    ``resume`` 1 (its state read from the same arrays) in a region that holds it, it goes on
    exactly as if the region had held it all along (255 in ``medium_out``: it stopped before its
    first phase was known, and starts afresh).

    Each step: A, the primitive of least clearance, and the least clearance of the others.  Outside
    A the step is A's clearance; inside A's negative set, as far as the others allow (it meets a
    line in one interval: A switches at most once), unless the primitive crossed last is still free
    to switch (one free primitive per step).  The phase at the step's end tells whether a primitive
    switched; a switch is then bracketed by regula falsi on its g and put on the lattice.

    ``along``: each step's clearances are first raised to the bounds proven along d where the
    medium has them (:func:`~pipeline.microstructure.surface_ray.along_clearances`), and a step may
    go across a lumen's root to where the ray is surely inside it (docs/methods.md#proven-steps-along-the-ray).
    """
    # The caller owns every array throughout: borrowed and carved, they carry no reference counts
    # (an atomic add and a call wherever one is passed on).
    ctx = borrowed(ctx)
    cache = borrowed(cache)
    cnt = carve(work, COUNTS, (len(PURPOSES),))
    bnd = carve(work, BOUNDS, (len(STEP_BOUNDS),))
    frame = carve(work, FRAME, (N_FRAME,))
    P = carve(work, 0, (MAX_PRIMS, N_COLS))
    Pa = carve(work, ROWS, (MAX_PRIMS, N_COLS))
    Pb = carve(work, 2 * ROWS, (MAX_PRIMS, N_COLS))
    v0 = 3 * ROWS
    X = carve(work, v0, (3,))
    d = carve(work, v0 + 3, (3,))
    nd = carve(work, v0 + 6, (3,))
    nrm = carve(work, v0 + 9, (3,))
    base = carve(work, v0 + 12, (3,))
    e = carve(work, v0 + 15, (3,))
    k0 = v0 + 18
    key = carve(work, k0, (5,))
    skip = carve(work, k0 + 5, (5,))
    every = carve(work, k0 + 10, (5,))
    prev_key = carve(work, k0 + 15, (5,))
    seg_skip = carve(work, k0 + 20, (5,))
    for q in range(5):
        key[q] = 0.0
        skip[q] = 0.0
        every[q] = 0.0
        prev_key[q] = 0.0
        seg_skip[q] = 0.0
    lq = 0.0
    for r in range(pos.shape[0]):
        # The ray is X0 + s·d on each straight segment: points are never accumulated step by
        # step, so where a crossing lands depends on the surfaces, not on the steps taken.
        for q in range(3):
            X[q] = pos[r, q]
            d[q] = dirs[r, q]
        skip[0] = 0.0
        ev = 0
        ne = 0
        npass = 0
        length = 0.0
        again = resume[r] != 0 and medium_out[r] != 255
        if again:
            ev = events[r]
            ne = evals[r]
            npass = passes[r]
            length = path[r]
            for q in range(5):
                skip[q] = skips[r, q]
        # The state at the start of the current segment, for a ray that leaves the region.
        seg_ne = ne
        seg_npass = npass
        for q in range(5):
            seg_skip[q] = skip[q]
        st = 0
        s = 0.0
        s_stop = -1.0  # where the ray left: the point it needed (else where it stood)
        ph0, n = surface_at(X[0], X[1], X[2], lq, ctx, P, cache, every)
        med = np.uint8(medium_out[r]) if again else ph0
        ne += 1
        cnt[0] += 1.0
        if ph0 == 255:
            st = NEEDS_REGION
        t_face = _face(X, d, thickness)
        have = True  # P holds the rows at s (the previous step's end, or the start)
        relax_ok = True
        prev_ok = False  # prev_key's g was prev_g at prev_s on this segment
        prev_g = 0.0
        force_free = False  # the primitive passed last is entered, whatever its g's rounding
        prev_s = 0.0
        while st == 0:
            if not have:
                ph, n = surface_at(X[0] + s * d[0], X[1] + s * d[1], X[2] + s * d[2], lq, ctx, P, cache, every)
                ne += 1
                cnt[1] += 1.0
                if ph == 255:
                    st = NEEDS_REGION
                    break
            have = False
            if along:
                # The rows' balls, raised to proven steps along d where the medium has them.
                ray_clearances(X[0] + s * d[0], X[1] + s * d[1], X[2] + s * d[2], d, ctx, P, n, frame,
                               find_row(P, n, skip) if skip[0] > 0.0 else -1)
            a, other, o = nearest(P, n, skip, key)
            # The primitive crossed last is free to switch once more only from inside its
            # negative set (a line that left a convex set does not come back to it).
            skip_free = force_free
            force_free = False
            if skip[0] > 0.0 and not skip_free:
                i = find_row(P, n, skip)
                skip_free = i >= 0 and P[i, 5] < 0.0
            g_a = 0.0
            relax = False
            bound = B_OTHERS
            why = -1
            if a < 0:
                step = other
                prev_ok = False
            else:
                g_a = P[a, 5]
                if skip_free or g_a > 0.0 or regime(P[a, 0]):
                    # Approached from outside, A keeps its proven clearance; so it does while the
                    # primitive crossed last is free (one free primitive per step).  A regime
                    # surface is passed only where the rows of its far side prove the part of the
                    # step beyond it free (checked at the step's end).
                    step = min(P[a, 6], other)
                    if P[a, 6] <= other:
                        bound = B_OWN
                        if not relax_ok:
                            why = B_AGAIN_OWN
                        elif skip_free and not regime(P[a, 0]):
                            why = B_FREE
                    if relax_ok and g_a < 0.0 and regime(P[a, 0]) and P[a, 6] < other:
                        # Inside a regime surface's negative set (convex in the pulled-back
                        # coordinates, like a lumen): as far as the others allow.
                        step = other
                        relax = True
                        bound = B_REGIME
                    # Over-relaxed steps, kept only if the step's end is in the other phase (a
                    # crossing, bracketed: A, entered once, switched first) or A's g is still
                    # positive there and the clearance balls of both ends cover the step (no chord
                    # of A between them; inside A other primitives apply).  Approaching A (g
                    # falling since the last step): past the secant's root of g.  Leaving it (g
                    # rising): as far as the balls would cover were g to keep rising at most 0.8
                    # times as fast.  A regime surface's steps are checked at the end as below.
                    # A primitive with a proven step along the ray (along: fibre and ray-cell lumens,
                    # ray bands) takes that step, and the crossing below, instead.
                    if (relax_ok and (not skip_free or regime(P[a, 0])) and g_a > 0.0 and P[a, 6] < other
                            and prev_ok and same_key(P, a, prev_key) and prev_g != g_a
                            and not (along and (P[a, 0] == P_LUMEN or P[a, 0] == P_RAY_LUMEN or P[a, 0] == P_BAND))):
                        c_a = P[a, 6]
                        if prev_g > g_a:
                            root = OVERSHOOT * g_a * (s - prev_s) / (prev_g - g_a)
                            if c_a < root <= other:
                                step = root
                                relax = True
                                bound = B_SECANT
                            elif root > other:
                                why = B_PAST
                        else:
                            rise = 0.8 * (g_a - prev_g) / (s - prev_s) * c_a / g_a  # per µm, in clearance
                            step = min(2.0 * c_a / (1.0 - rise) if rise < 0.9 else 20.0 * c_a, 20.0 * c_a, other)
                            relax = True
                            bound = B_AWAY
                    if (along and relax_ok and not skip_free and g_a > 0.0 and (P[a, 0] == P_LUMEN or P[a, 0] == P_RAY_LUMEN)
                            and P[a, 6] < P[a, C_CROSS] <= other):
                        # Across a fibre or ray-cell lumen's root, to where the ray is surely inside it
                        # (surface_ray.lumen_step), checked at the end as a secant step is.
                        step = P[a, C_CROSS]
                        relax = True
                        bound = B_CROSS
                    prev_ok = g_a > 0.0
                    if prev_ok:
                        for q in range(5):
                            prev_key[q] = P[a, q]
                        prev_s = s
                        prev_g = g_a
                else:
                    step = other
                    prev_ok = False
                    bound = B_INSIDE
            relax_ok = True
            step *= step_scale
            near = step <= hit
            if near:
                step = 2.0 * hit
                bound = B_PROBE
            bnd[bound] += 1.0
            if bound == B_OWN and why >= 0:
                bnd[why] += 1.0
            elif bound == B_OTHERS and o >= 0 and P[o, 0] == P_REACH:
                bnd[B_REACH] += 1.0
            s_end = s + step
            at_face = s_end >= t_face
            if at_face:
                s_end = t_face
            phb, nb = surface_at(X[0] + s_end * d[0], X[1] + s_end * d[1], X[2] + s_end * d[2], lq, ctx, Pb, cache,
                                  every)
            ne += 1
            cnt[1] += 1.0
            if phb == 255:
                # The point the step needs is the one the next region must hold: a step inside a
                # regime surface with nothing else listed may reach for the far face.
                st = NEEDS_REGION
                s_stop = s_end
                break
            if relax and not near and regime(P[a, 0]):
                # A long step from a regime surface A: kept where it is proven, else cut short of
                # A's root (then only the near side's rows apply), else taken again on A's own
                # clearance.
                i = find_row(Pb, nb, key)
                if i >= 0 and (Pb[i, 5] < 0.0) != (g_a < 0.0):
                    if skip_free or far_unproven(Pb, nb, i, skip, s_end - s):
                        ok, lo, phb, nb, k = _before_root(X, d, s, s_end, g_a, Pb[i, 5], key, lq, ctx, Pa, Pb, cache,
                                                           every, tol)
                        ne += k
                        cnt[2] += k
                        if ok:
                            s_end = lo
                            at_face = False
                        else:
                            i = -1
                    elif phb == med:
                        npass += 1  # a regime surface passed with no phase change
                elif i >= 0 and g_a > 0.0 and P[a, 6] + Pb[i, 6] < s_end - s:
                    i = -1  # A approached from outside may hold a chord between the ends
                if i < 0:
                    have = True
                    relax_ok = False
                    bnd[B_AGAIN] += 1.0
                    continue
            elif phb == med and relax and not near:
                i = find_row(Pb, nb, key)
                if i < 0 or Pb[i, 5] <= 0.0 or P[a, 6] + Pb[i, 6] < s_end - s:
                    # A may hold a chord between the ends, or was entered with no phase change
                    # (inside it other primitives apply): from s again, on A's own clearance.
                    have = True
                    relax_ok = False
                    bnd[B_AGAIN] += 1.0
                    continue
            if phb == med:
                if near:
                    npass += 1
                if at_face:
                    for q in range(3):
                        X[q] += t_face * d[q]
                    length += t_face
                    X[1] = thickness if d[1] > 0.0 else 0.0
                    st = TRANSMITTED if d[1] > 0.0 else REFLECTED
                    break
                s = s_end
                n = nb
                copy_rows(P, Pb, nb)
                have = True
                continue
            if ev >= max_events:
                st = TRAPPED
                break
            # A crossing in (s, s_end].  Only A or the primitive crossed last can switch there,
            # unless the step was the 2·hit probe: the one whose sign differs at the ends is the one.
            lo = s
            hi = s_end
            single = False
            j = -1
            j0 = -1
            g_lo = np.nan
            # The step as taken, not s_end - s: that may round one ulp above a step that was the
            # others' clearance, and the phase would be bisected over the whole step.
            if step <= other:
                for cand in range(2):
                    kk = key if cand == 0 else skip
                    if kk[0] <= 0.0 or (cand == 0 and a < 0):
                        continue
                    i0 = find_row(P, n, kk)
                    i1 = find_row(Pb, nb, kk)
                    if i0 >= 0 and i1 >= 0 and (P[i0, 5] < 0.0) != (Pb[i1, 5] < 0.0):
                        if single:
                            single = False  # both switched: bisect the phase
                            break
                        single = True
                        j = i1
                        j0 = i0
                        g_lo = P[i0, 5]
                        if cand == 1:
                            for q in range(5):
                                key[q] = skip[q]
            g_hi = Pb[j, 5] if j >= 0 else np.nan
            t_lo = g_lo  # the true g at lo and hi (Illinois halves its copies)
            t_hi = g_hi
            # With steps along the ray, A's root as its frame sees it is the first point tried, and
            # then the secant's root through the last two points tried, nudged 0.05·tol past it, so
            # that two points close the bracket to tol once the secant is that good (at most 4).
            guess = s + root_guess(frame, P, j0, ctx) if along and single else -1.0
            x_prev = lo
            g_prev = g_lo
            nudges = 4 if along else 0
            if single:
                # Regula falsi (Illinois) on the sign of g: the root of the primitive itself.
                side = 0
                while hi - lo > tol:
                    mid = lo + (hi - lo) * g_lo / (g_lo - g_hi)
                    if not (lo < mid < hi) or hi - lo < 4.0 * tol:
                        mid = 0.5 * (lo + hi)
                    if lo < guess < hi:
                        mid = guess
                    guess = -1.0
                    if mid <= lo or mid >= hi:
                        break
                    phm, nm = surface_at(X[0] + mid * d[0], X[1] + mid * d[1], X[2] + mid * d[2], lq, ctx, P, cache,
                                          key)
                    ne += 1
                    cnt[3] += 1.0
                    i = find_row(P, nm, key)
                    if i < 0:
                        single = False
                        lo = s
                        hi = s_end
                        break
                    gm = P[i, 5]
                    if nudges > 0 and gm != g_prev:
                        nudges -= 1
                        x_sec = mid - gm * (mid - x_prev) / (gm - g_prev)
                        guess = x_sec + (0.05 * tol if x_sec > mid else -0.05 * tol)
                    x_prev = mid
                    g_prev = gm
                    if (gm < 0.0) == (g_lo < 0.0):
                        lo = mid
                        g_lo = gm
                        t_lo = gm
                        if side == -1:
                            g_hi *= 0.5
                        side = -1
                    else:
                        hi = mid
                        g_hi = gm
                        t_hi = gm
                        if side == 1:
                            g_lo *= 0.5
                        side = 1
            # The crossing on the lattice of LATTICE µm along the segment: the first lattice point
            # in the new phase, whatever bracket led there.  First a guess: the lattice points
            # either side of the secant's root of g in the bracket.
            guessed = False
            if single and t_lo != t_hi:
                root = min(max(lo + (hi - lo) * t_lo / (t_lo - t_hi), lo), hi)
                klo = math.floor(root / LATTICE)
                khi = klo + 1.0
                pl, na = _at_lattice(X, d, klo, lq, ctx, Pa, cache, every)
                ne += 1
                cnt[4] += 1.0
                if pl == med:
                    ph_hi, nb = _at_lattice(X, d, khi, lq, ctx, Pb, cache, every)
                    ne += 1
                    cnt[4] += 1.0
                    guessed = ph_hi != med
            if not guessed:
                cnt[5] -= ne
                # med and single typed as they end up (int64, bool), not as first seen (uint8, the
                # literal False): _lattice_bracket would compile for those too (20 s a fresh install).
                klo, khi, na, nb, ne, passed = _lattice_bracket(X, d, s, s_end, lo, hi, np.int64(med), bool(single),
                                                                lq, ctx, P, Pa, Pb, cache, every, ne)
                cnt[5] += ne
                if passed:
                    # The primitive switched without changing the phase (a lumen entered inside its
                    # end wall, the edge of a ray band between two walls): go past it, inside it
                    # whatever the rounding of its g says; what changes the phase lies further on.
                    npass += 1
                    for q in range(5):
                        skip[q] = 0.0 if regime(key[0]) else key[q]
                    force_free = not regime(key[0])
                    s = khi * LATTICE
                    continue
            lo = klo * LATTICE
            hi = khi * LATTICE
            # The normal: the gradient of the switching primitive at the crossing.
            ok = switched(Pa, na, Pb, nb, key)
            for q in range(3):
                base[q] = X[q] + hi * d[q]
            found, k = surface_normal(base, lq, ctx, P, key, cache, nrm)
            if not found:  # the primitive's surface ends at hi (a ray-cell row, a closing lumen): lo's
                for q in range(3):
                    e[q] = X[q] + lo * d[q]
                found, k2 = surface_normal(e, lq, ctx, P, key, cache, nrm)
                k += k2
            ne += k
            cnt[6] += k
            ok = ok and found
            s2 = math.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2])
            if not ok or s2 == 0.0:  # no surface to refract on (none listed): counted, passed
                npass += 1
                s = hi
                med = 1 - med
                skip[0] = 0.0
                continue
            for q in range(3):
                nrm[q] /= s2
            new = interface_event(d, nrm, med, n_wall, n_poly, fresnel, fseed, ray_ids[r], ev, nd)
            if log.shape[0] > r and ev < log.shape[1]:
                for q in range(3):
                    log[r, ev, q] = base[q]
                    log[r, ev, 8 + q] = nrm[q]
                for q in range(5):
                    log[r, ev, 3 + q] = key[q]
                log[r, ev, 11] = new
            ev += 1
            t_go = hi if new != med else lo
            for q in range(3):
                X[q] += t_go * d[q]
            length += t_go
            s = 0.0
            # The new segment starts at the lattice point it left from, whose rows are at hand
            # (X + 0·d is that point bit for bit, so they are the rows an evaluation would give).
            if new != med:
                n = nb
                copy_rows(P, Pb, nb)
            else:
                n = na
                copy_rows(P, Pa, na)
            have = True
            med = new
            prev_ok = False  # a new segment
            for q in range(3):
                d[q] = nd[q]
            t_face = _face(X, d, thickness)
            for q in range(5):
                skip[q] = key[q]
            if regime(key[0]):
                # A regime surface is left out only from its positive side (outside its convex
                # negative set, which a line moving away never re-enters).
                j = find_row(Pb, nb, key) if t_go == hi else find_row(Pa, na, key)
                if j < 0 or (Pb[j, 5] if t_go == hi else Pa[j, 5]) <= 0.0:
                    skip[0] = 0.0
            seg_ne = ne - 1  # the rows at hand count as the segment's first evaluation (resumed, it makes it)
            seg_npass = npass
            for q in range(5):
                seg_skip[q] = skip[q]
        for q in range(3):
            out_pos[r, q] = X[q]
            out_dir[r, q] = d[q]
            stop[r, q] = X[q] + (s_stop if s_stop >= 0.0 else s) * d[q]
        status[r] = st
        events[r] = ev
        path[r] = length
        evals[r] = ne
        passes[r] = npass
        medium_out[r] = med
        if st == NEEDS_REGION:  # the segment's start: the caller's next region holds the rest
            evals[r] = seg_ne
            passes[r] = seg_npass
            for q in range(5):
                skips[r, q] = seg_skip[q]
