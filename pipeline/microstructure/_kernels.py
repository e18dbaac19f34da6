"""Numba kernels of the wood microstructure model (GENERATOR.md).

The phase at a point is a pure function of (constants, seed, position):

    output X ──dipole pull-back──► p1 ──ray band? / ray squeeze──► p ──lattice──► phase

All lengths are in µm.  Nothing here depends on the block being generated,
only on global coordinates, so any block (chunk) can be generated alone and
the voxels are identical whatever the chunking.  The Python in ``model.py``
validates inputs and shapes the arrays around these kernels.
"""

import math

import numpy as np
from numba import njit

from .._intrinsics import any_inside4
from . import _rng
from ._rng import normal, uniform

# Indices into the model-constant vector ``M`` (float64).  Lengths in µm.
PITCH, SCALE, T0, WALLVAR, JITTER, PUSH, CTRL, FLEN, FLEN_SD, PLATE, ENDS, SHAPE = range(12)
VESSELS, VPROB, VPAIR, VTRIPLE, VWALL = range(12, 17)
RAYS, RSPACE, RJIT, RSER, RWIDTH, RHEIGHT, RLEN, RLEN_SD, RGROUP, RGROUP_SD, RSQUEEZE, RRAMP = range(17, 29)
DIST, LARGE_P, BEND_A, BEND_WL, TIP = range(29, 34)
N_CONSTANTS = 34

WALL = np.uint8(1)
POLYMER = np.uint8(0)

# Fixed structure of the stationary layouts (in lattice nodes / cell heights).
VTILE_R = 12  # vessel tile size along R [nodes]
VTILE_T = 10  # ... along T [nodes]
VHARD_R = 8  # hard-core box between vessels of different clusters [nodes]
VHARD_T = 8  # also keeps the lookup cells of two clusters apart
VRAY_CLEAR = 5  # vessels stay this many nodes away from ray rows
VESSEL_AXIS_R = 3.2 / 3.0  # outline semi-axis along R relative to the 3-node span
RAY_PERIOD = 26  # L slot per ray group [cell heights]; one group per slot
RAY_MIN_GAP = 6  # minimum gap between groups [cell heights]
GRID_PER_PITCH = 8  # distortion grid nodes per lattice pitch
TILE = 64  # distortion grid cells per tile side

# Stats counters (a cost model: equal counters mean equal work).
ST_NODES, ST_VOXELS, ST_DIPOLES, ST_LATTICE, ST_TILES = range(5)


# --------------------------------------------------------------------------
# Lattice nodes
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _spline(L, spacing):
    """Control index k and Catmull-Rom weights of the control values k-1 .. k+2 at L."""
    x = L / spacing
    k = math.floor(x)
    f = x - k
    f2 = f * f
    f3 = f2 * f
    w0 = 0.5 * (-f + 2.0 * f2 - f3)
    w1 = 0.5 * (2.0 - 5.0 * f2 + 3.0 * f3)
    w2 = 0.5 * (f + 4.0 * f2 - 3.0 * f3)
    w3 = 0.5 * (f3 - f2)
    return np.int64(k), w0, w1, w2, w3


@njit(inline="always", cache=True, error_model="numpy")
def _controls(seed, n, m, k, out):
    """The three control values (R, T, wall) of node (n, m) at control slice k, in [-1, 1)."""
    out[0] = 2.0 * uniform(seed, _rng.NODE_R, n, m, k) - 1.0
    out[1] = 2.0 * uniform(seed, _rng.NODE_T, n, m, k) - 1.0
    out[2] = 2.0 * uniform(seed, _rng.NODE_WALL, n, m, k) - 1.0


@njit(inline="always", cache=True, error_model="numpy")
def _node_from(M, n, m, w0, w1, w2, w3, C0, C1, C2, C3):
    """Node position and inset from the control values C0..C3 (k-1 .. k+2) and weights."""
    c = M[PITCH]
    r = 0.0
    t = 0.0
    w = 0.0
    for q in range(4):
        wq = w0 if q == 0 else (w1 if q == 1 else (w2 if q == 2 else w3))
        C = C0 if q == 0 else (C1 if q == 1 else (C2 if q == 2 else C3))
        r += wq * C[0]
        t += wq * C[1]
        w += wq * C[2]
    return n * c + M[JITTER] * c * r, m * c + M[JITTER] * c * t, M[T0] * (1.0 + M[WALLVAR] * w)


@njit(cache=True, nogil=True, error_model="numpy")
def node_state(seed, M, n, m, L):
    """Jittered position (R, T) [µm] and wall inset t [µm] of node (n, m) at L.

    Control values every ``M[CTRL]`` µm along L are interpolated with a local
    Catmull-Rom spline, so a node at any L needs only four control values.
    """
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    C = np.empty((4, 3))
    for q in range(4):
        _controls(seed, n, m, k + q - 1, C[q])
    return _node_from(M, n, m, w0, w1, w2, w3, C[0], C[1], C[2], C[3])


@njit(cache=True, nogil=True, error_model="numpy")
def node_states(seed, M, L, n_lo, m_lo, NR, NT, Nt, CV, CF, cn, ck):
    """:func:`node_state` of the window's nodes, their control values kept in ``CV``.

    CV[n - cn, m - m_lo, k - ck] holds the control values of node (n, m) at
    control slice k once CF (same index) is 1; the slices of one block share
    them (control slices are tens of µm apart), so each is hashed once.
    """
    k, w0, w1, w2, w3 = _spline(L, M[CTRL])
    nn, nm = NR.shape
    for i in range(nn):
        a = np.uint64(n_lo + i - cn)
        for j in range(nm):
            for q in range(4):
                z = np.uint64(k + q - 1 - ck)
                if CF[a, j, z] == 0:
                    _controls(seed, n_lo + i, m_lo + j, k + q - 1, CV[a, j, z])
                    CF[a, j, z] = 1
            NR[i, j], NT[i, j], Nt[i, j] = _node_from(
                M, n_lo + i, m_lo + j, w0, w1, w2, w3,
                CV[a, j, k - 1 - ck], CV[a, j, k - ck], CV[a, j, k + 1 - ck], CV[a, j, k + 2 - ck])


@njit(inline="always", cache=True, error_model="numpy")
def is_centre(n, m):
    """Fibre centres: every second node column, alternate columns shifted by one node."""
    return m % 2 == 0 and (n - m // 2) % 2 == 0


# --------------------------------------------------------------------------
# Stationary 1-D renewal chains (fibre ends along L, ray cells along R)
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _boundary(seed, kind, a, b, q, phase, mean, sd, emax):
    e = normal(seed, kind, a, b, q) * sd * 0.7071067811865476
    if e > emax:
        e = emax
    elif e < -emax:
        e = -emax
    return q * mean + phase + e


@njit(cache=True, nogil=True, error_model="numpy")
def chain_interval(x, seed, kind, a, b, phase, mean, sd, min_len):
    """The cell (lo, hi) of a jittered-lattice chain that contains x.

    Boundaries sit at q·mean + phase + e_q with e_q ~ N(0, sd²/2) clipped to
    ±(mean − min_len)/2, so lengths are ≈ N(mean, sd²), never below min_len,
    and finding the cell at any x costs O(1) (no walk from an origin).
    """
    emax = max(0.0, 0.5 * (mean - min_len))
    q0 = np.int64(math.floor((x - phase) / mean))
    b0 = _boundary(seed, kind, a, b, q0, phase, mean, sd, emax)
    if x < b0:
        return _boundary(seed, kind, a, b, q0 - 1, phase, mean, sd, emax), b0
    b1 = _boundary(seed, kind, a, b, q0 + 1, phase, mean, sd, emax)
    if x < b1:
        return b0, b1
    return b1, _boundary(seed, kind, a, b, q0 + 2, phase, mean, sd, emax)


# --------------------------------------------------------------------------
# Ray columns and groups
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def ray_row(seed, M, k):
    """Node row (even T index) of ray column k."""
    x = k * M[RSPACE] + (2.0 * uniform(seed, _rng.RAY_COLUMN, k, 0, 0) - 1.0) * M[RJIT]
    return np.int64(2 * round(0.5 * x))


@njit(cache=True, nogil=True, error_model="numpy")
def near_ray(seed, M, m, dist):
    """True when node row m is within ``dist`` rows of a ray column.

    Ray columns are a property of the lattice: they are where they are whether or
    not ray cells are drawn (``M[RAYS]``), so that switching ray cells off changes
    the ray tissue and its squeeze alone, and leaves the vessels (placed away from
    ray columns) and the fibres' distortion where they were.
    """
    kc = np.int64(round(m / M[RSPACE]))
    for k in range(kc - 1, kc + 2):
        if abs(m - ray_row(seed, M, k)) < dist:
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def ray_group(seed, M, k, L):
    """Ray group of column k around L: (L0, L1, slot); L0 = nan when none.

    Each slot of RAY_PERIOD cell heights holds one group of N(mean, sd)
    cells at a random offset, leaving at least RAY_MIN_GAP cells of gap.
    """
    h = M[RHEIGHT]
    period = RAY_PERIOD * h
    phase = uniform(seed, _rng.RAY_GROUP, k, 1, 0) * period
    g = np.int64(math.floor((L - phase) / period))
    ncell = round(M[RGROUP] + M[RGROUP_SD] * normal(seed, _rng.RAY_GROUP, k, 3, g))
    lo = max(1.0, min(5.0, round(M[RGROUP])))
    ncell = min(max(ncell, lo), RAY_PERIOD - RAY_MIN_GAP)
    off = math.floor(uniform(seed, _rng.RAY_GROUP, k, 4, g) * (RAY_PERIOD - RAY_MIN_GAP - ncell + 1))
    L0 = g * period + phase + off * h
    L1 = L0 + ncell * h
    if L < L0 or L > L1:
        return math.nan, math.nan, g
    return L0, L1, g


@njit(inline="always", cache=True, error_model="numpy")
def ray_band_width(M):
    return M[RSER] * (M[RWIDTH] + 2.0 * M[T0])


@njit(cache=True, nogil=True, error_model="numpy")
def ray_slice_tables(seed, M, L, rays, nr, RC):
    """What the ray cells of the active ray rows share on the slice at L.

    RC[r, s] for sub-column s of row r: (open, Tc, aT, dL², layer id, row id,
    chain phase), where ``open`` is 0 when the slice misses the sub-column's
    cells or they have no lumen, Tc and aT are the lumen's centre and
    semi-axis along T, and dL the slice's offset from the lumen centre over
    its semi-axis along L; RC[r, 0, 7] is the sub-columns' width along T.
    Everything here depends on L, not on the point.
    """
    ns = np.int64(M[RSER])
    h = M[RHEIGHT]
    mean = M[RLEN]
    for r in range(nr):
        t_r = rays[r, 0]
        b = rays[r, 1]
        L0 = rays[r, 2]
        L1 = rays[r, 3]
        k = np.int64(rays[r, 4])
        g = np.int64(rays[r, 5])
        sw = 2.0 * b / ns
        RC[r, 0, 7] = sw
        for s in range(ns):
            RC[r, s, 0] = 0.0
            Tc = t_r - b + (s + 0.5) * sw
            off = 0.5 * h * (s % 2)  # biseriate: the second column is offset by half a cell
            ell = np.int64(math.floor((L - L0 - off) / h))
            if ell < 0 or L0 + off + (ell + 1) * h > L1 + 1e-9:
                continue
            aT = 0.5 * sw - M[T0]
            aL = 0.5 * h - M[T0]
            if aT <= 0.0 or aL <= 0.0:
                continue
            Lc = L0 + off + (ell + 0.5) * h
            dL = (L - Lc) / aL
            ida = k * 8 + s
            RC[r, s, 0] = 1.0
            RC[r, s, 1] = Tc
            RC[r, s, 2] = aT
            RC[r, s, 3] = dL * dL
            RC[r, s, 4] = ida
            RC[r, s, 5] = g * 64 + ell
            RC[r, s, 6] = uniform(seed, _rng.RAY_CELL_PHASE, ida, 0, 0) * mean + 0.5 * mean * (ell % 2)


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def ray_cell_phase(seed, M, pR, pT, r, rays, RC, memo):
    """Phase at (pR, pT) inside the band of active ray row r (tables: :func:`ray_slice_tables`).

    memo : float64[8, 4], per sub-column s the last radial cell found, (layer
        id, row id, lo, hi); a point of the same layer and row inside [lo, hi)
        reuses it (the cell containing a point is unique, so the result is the
        same).  Start it with NaNs.
    """
    ns = np.int64(M[RSER])
    s0 = np.int64(math.floor((pT - (rays[r, 0] - rays[r, 1])) / RC[r, 0, 7]))
    s = np.uint64(min(max(s0, 0), ns - 1))
    if RC[r, s, 0] == 0.0:
        return WALL
    Tc = RC[r, s, 1]
    aT = RC[r, s, 2]
    if abs(pT - Tc) >= aT:  # then (dT)² >= 1 exactly
        return WALL
    dT = (pT - Tc) / aT
    if dT * dT + RC[r, s, 3] >= 1.0:
        return WALL
    # Radial cells along R; successive layers staggered by half a cell length.
    mem = memo[s]
    if mem[0] == RC[r, s, 4] and mem[1] == RC[r, s, 5] and mem[2] <= pR < mem[3]:
        lo = mem[2]
        hi = mem[3]
    else:
        mean = M[RLEN]
        lo, hi = chain_interval(pR, seed, _rng.RAY_CELL_END, np.int64(RC[r, s, 4]),
                                np.int64(RC[r, s, 5]), RC[r, s, 6], mean, M[RLEN_SD], 0.4 * mean)
        mem[0] = RC[r, s, 4]
        mem[1] = RC[r, s, 5]
        mem[2] = lo
        mem[3] = hi
    end_wall = 0.5 * M[SCALE]
    if pR - lo < end_wall or hi - pR < end_wall:
        return WALL
    return POLYMER


# --------------------------------------------------------------------------
# Vessels: a stationary, hashed, Matérn-II-thinned cluster process
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def vessel_proposal(seed, M, a, b, mem_n, mem_m):
    """Cluster proposed by vessel tile (a, b): number of members (0 = none)."""
    if uniform(seed, _rng.VESSEL_TILE, a, b, 0) >= M[VPROB]:
        return 0
    n = a * VTILE_R + np.int64(math.floor(uniform(seed, _rng.VESSEL_TILE, a, b, 1) * VTILE_R))
    m = b * VTILE_T + np.int64(math.floor(uniform(seed, _rng.VESSEL_TILE, a, b, 2) * VTILE_T))
    m = 2 * (m // 2)
    if (n - m // 2) % 2 != 0:
        n += 1
    u = uniform(seed, _rng.VESSEL_TILE, a, b, 3)
    size = 1
    if u < M[VTRIPLE]:
        size = 3
    elif u < M[VTRIPLE] + M[VPAIR]:
        size = 2
    mem_n[0] = n
    mem_m[0] = m
    for i in range(1, size):
        r = uniform(seed, _rng.VESSEL_MEMBER, a, b, i)
        dn, dm = 6, 0
        if r >= 0.5:
            q = np.int64(math.floor((r - 0.5) * 8.0))  # 0..3
            dn = 5 if q < 2 else 7
            dm = 2 if q % 2 == 0 else -2
        mem_n[i] = mem_n[i - 1] + dn
        mem_m[i] = mem_m[i - 1] + dm
    for i in range(size):
        if near_ray(seed, M, mem_m[i], VRAY_CLEAR):
            return 0
    return size


@njit(cache=True, nogil=True, error_model="numpy")
def _vessel_kept(seed, M, a, b, size, mem_n, mem_m):
    pri = uniform(seed, _rng.VESSEL_TILE, a, b, 9)
    qn = np.empty(3, np.int64)
    qm = np.empty(3, np.int64)
    for a2 in range(a - 2, a + 3):
        for b2 in range(b - 2, b + 3):
            if a2 == a and b2 == b:
                continue
            qs = vessel_proposal(seed, M, a2, b2, qn, qm)
            if qs == 0:
                continue
            conflict = False
            for i in range(size):
                for j in range(qs):
                    if abs(mem_n[i] - qn[j]) < VHARD_R and abs(mem_m[i] - qm[j]) < VHARD_T:
                        conflict = True
            if not conflict:
                continue
            pri2 = uniform(seed, _rng.VESSEL_TILE, a2, b2, 9)
            if pri2 > pri or (pri2 == pri and (a2 > a or (a2 == a and b2 > b))):
                return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def vessels_in_region(seed, M, n_lo, n_hi, m_lo, m_hi, out):
    """Vessel members whose 7-fibre footprint may touch nodes [n_lo, n_hi] × [m_lo, m_hi].

    ``out`` rows: (n, m, cluster id, index in cluster, cluster size).  Members
    of one cluster are consecutive.  Returns the number of rows written.
    """
    if M[VESSELS] == 0.0:
        return 0
    mem_n = np.empty(3, np.int64)
    mem_m = np.empty(3, np.int64)
    count = 0
    cluster = 0
    a_lo = (n_lo - 24) // VTILE_R - 1
    a_hi = (n_hi + 4) // VTILE_R + 1
    b_lo = (m_lo - 12) // VTILE_T - 1
    b_hi = (m_hi + 12) // VTILE_T + 1
    for a in range(a_lo, a_hi + 1):
        for b in range(b_lo, b_hi + 1):
            size = vessel_proposal(seed, M, a, b, mem_n, mem_m)
            if size == 0:
                continue
            touches = False
            for i in range(size):
                if (n_lo - 5 <= mem_n[i] <= n_hi + 5) and (m_lo - 5 <= mem_m[i] <= m_hi + 5):
                    touches = True
            if not touches or not _vessel_kept(seed, M, a, b, size, mem_n, mem_m):
                continue
            if count + size > out.shape[0]:
                raise ValueError("too many vessels in region; enlarge the buffer")
            for i in range(size):
                out[count, 0] = mem_n[i]
                out[count, 1] = mem_m[i]
                out[count, 2] = cluster
                out[count, 3] = i
                out[count, 4] = size
                count += 1
            cluster += 1
    return count


@njit(inline="always", cache=True, error_model="numpy")
def _member_of(vessels, nv, n, m):
    for v in range(nv):
        if abs(n - vessels[v, 0]) <= 2 and abs(m - vessels[v, 1]) <= 2:
            return True
    return False


# --------------------------------------------------------------------------
# Distortion: dipoles and the global bend, tabulated per tile on a grid
# --------------------------------------------------------------------------
@njit(inline="always", cache=True, error_model="numpy")
def _sig(x):
    return 1.0 / (1.0 + math.exp(-x))


@njit(cache=True, nogil=True, error_model="numpy")
def _add_dipole(out, gR, gT, R0, T0_, k1, k2, k3, k4, sign, rv, acut, bcut):
    """Add one dipole (GENERATOR.md §5) to the tile grid ``out``.

    d(a, b) = [σ(k1 a) − σ(k2 a)]·(k4/k2)·exp(−b²/(2 (k3/k2)²)), in reference
    voxels; u uses (a, b) = (R, T), v uses (T, R).  Separable, so the grid
    costs O(n) exponentials per dipole.
    """
    n = gR.shape[0]
    w = k3 / k2
    amp = sign * k4 / k2 * rv
    AR = np.zeros(n)
    BR = np.zeros(n)
    AT = np.zeros(n)
    BT = np.zeros(n)
    anyR = False
    anyT = False
    for i in range(n):
        a = (gR[i] - R0) / rv
        if abs(a) <= acut:
            AR[i] = (_sig(k1 * a) - _sig(k2 * a)) * amp
            anyR = True
        if abs(a) <= bcut:
            BR[i] = math.exp(-a * a / (2.0 * w * w))
        b = (gT[i] - T0_) / rv
        if abs(b) <= acut:
            AT[i] = (_sig(k1 * b) - _sig(k2 * b)) * amp
            anyT = True
        if abs(b) <= bcut:
            BT[i] = math.exp(-b * b / (2.0 * w * w))
    if not (anyR or anyT):
        return 0
    for i in range(n):
        for j in range(n):
            out[i, j, 0] += AR[i] * BT[j]
            out[i, j, 1] += AT[j] * BR[i]
    return 1


@njit(cache=True, nogil=True, error_model="numpy")
def distortion_tile(seed, M, a, b, out, stats):
    """Displacement d = (dR, dT) [µm] on the (TILE+1)² grid of tile (a, b).

    Grid node (i, j) of the tile sits at ((a·TILE + i)·G, (b·TILE + j)·G)
    with G = pitch / GRID_PER_PITCH.  Each dipole's contribution to a node
    depends only on the pair, and dipoles are added in a fixed global order,
    so nodes shared by two tiles get identical values.
    """
    c = M[PITCH]
    G = c / GRID_PER_PITCH
    rv = 0.5 * M[SCALE]  # a reference voxel [µm]
    n = TILE + 1
    gR = np.empty(n)
    gT = np.empty(n)
    for i in range(n):
        gR[i] = (a * TILE + i) * G
        gT[i] = (b * TILE + i) * G
    out[:, :, :] = 0.0
    amp = M[DIST]
    # Fibre and vessel dipoles: support ±250 reference voxels.
    halo = 250.0 * rv
    n_lo = np.int64(math.floor((gR[0] - halo) / c)) - 1
    n_hi = np.int64(math.ceil((gR[n - 1] + halo) / c)) + 1
    m_lo = np.int64(math.floor((gT[0] - halo) / c)) - 1
    m_hi = np.int64(math.ceil((gT[n - 1] + halo) / c)) + 1
    vessels = np.empty((4096, 5), np.int64)
    nv = vessels_in_region(seed, M, n_lo, n_hi, m_lo, m_hi, vessels)
    terms = 0
    if amp > 0.0:
        for m in range(m_lo, m_hi + 1):
            for nn in range(n_lo, n_hi + 1):
                if not is_centre(nn, m) or _member_of(vessels, nv, nn, m):
                    continue
                k3 = 2.0 + uniform(seed, _rng.DIPOLE, nn, m, 0)
                k4 = (1.0 + uniform(seed, _rng.DIPOLE, nn, m, 1)) * amp
                if near_ray(seed, M, m, 5):
                    k4 *= 0.3
                sign = 1.0 if uniform(seed, _rng.DIPOLE_SIGN, nn, m, 0) < 0.5 else -1.0
                terms += _add_dipole(out, gR, gT, nn * c, m * c, 0.08, 0.06, k3, k4, sign,
                                     rv, 250.0, 4.0 * k3 / 0.06)
        for v in range(nv):
            terms += _add_dipole(out, gR, gT, vessels[v, 0] * c, vessels[v, 1] * c,
                                 0.06, 0.055, 2.0, 15.0 * amp, 1.0, rv, 250.0, 4.0 * 2.0 / 0.055)
        # Rare large-scale dipoles: support ±1200 reference voxels.
        if M[LARGE_P] > 0.0:
            halo = 1200.0 * rv
            for m in range(np.int64(math.floor((gT[0] - halo) / c)),
                           np.int64(math.ceil((gT[n - 1] + halo) / c)) + 1):
                for nn in range(np.int64(math.floor((gR[0] - halo) / c)),
                                np.int64(math.ceil((gR[n - 1] + halo) / c)) + 1):
                    if not is_centre(nn, m) or uniform(seed, _rng.LARGE_DIPOLE, nn, m, 0) >= M[LARGE_P]:
                        continue
                    k3 = 1.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 1))
                    k4 = 0.5 * (1.0 + uniform(seed, _rng.LARGE_DIPOLE, nn, m, 2)) * amp
                    sign = 1.0 if uniform(seed, _rng.LARGE_DIPOLE, nn, m, 3) < 0.5 else -1.0
                    terms += _add_dipole(out, gR, gT, nn * c, m * c, 0.01, 0.008, k3, k4, sign,
                                         rv, 1200.0, 3.0 * k3 / 0.008)
    # Stationary global bend of the radial files (random phases).
    A = M[BEND_A]
    if A > 0.0:
        lam = M[BEND_WL]
        ph1 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 0)
        ph2 = 2.0 * math.pi * uniform(seed, _rng.GLOBAL_BEND, 0, 0, 1)
        for i in range(n):
            for j in range(n):
                out[i, j, 1] += A * math.sin(2.0 * math.pi * gR[i] / lam + ph1)
                out[i, j, 0] += 0.5 * A * math.sin(2.0 * math.pi * gT[j] / (1.618 * lam) + ph2)
    stats[ST_DIPOLES] += terms
    stats[ST_TILES] += 1


@njit(inline="always", cache=True, error_model="numpy")
def pull_back(patch, gi0, gj0, G, R, T):
    """p1 = X − d(X), d bilinear on the global distortion grid (indices from global coords)."""
    x = R / G
    y = T / G
    ix = math.floor(x)
    iy = math.floor(y)
    fx = x - ix
    fy = y - iy
    i = np.uint64(np.int64(ix) - gi0)
    j = np.uint64(np.int64(iy) - gj0)
    i1 = i + np.uint64(1)
    j1 = j + np.uint64(1)
    dR = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 0] + fy * patch[i, j1, 0])
          + fx * ((1.0 - fy) * patch[i1, j, 0] + fy * patch[i1, j1, 0]))
    dT = ((1.0 - fx) * ((1.0 - fy) * patch[i, j, 1] + fy * patch[i, j1, 1])
          + fx * ((1.0 - fy) * patch[i1, j, 1] + fy * patch[i1, j1, 1]))
    return R - dR, T - dT


# --------------------------------------------------------------------------
# One slice (fixed L in ply coordinates): tables, then the per-point phase
@njit(cache=True, nogil=True, error_model="numpy")
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
    push = M[PUSH] * M[SCALE]
    polygon = M[SHAPE] == 1.0
    plate = 0.5 * M[PLATE]
    tip = M[TIP]
    min_len = min(50.0, 0.5 * M[FLEN])
    if tip > 0.0:
        min_len = max(min_len, min(tip, 0.5 * M[FLEN]))  # a cell holds its two tips only
    for i in range(1, nn - 1):
        for j in range(1, nm - 1):
            n = n_lo + i
            m = m_lo + j
            if not is_centre(n, m):
                continue
            flag = 0
            lo = np.nan
            hi = np.nan
            aR = 0.0
            aT = 0.0
            if _member_of(vessels, nv, n, m):
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
                if tip == 0.0 and (L - lo < plate or hi - L < plate):
                    flag = 1
            if polygon:
                FE[i, j, 0] = NR[i, j]
                FE[i, j, 1] = NT[i, j]
            else:
                aR = 0.5 * (NR[i + 1, j] - NR[i - 1, j]) - Nt[i, j]
                aT = 0.5 * (NT[i, j + 1] - NT[i, j - 1]) + push - Nt[i, j]
                if aR <= 0.0 or aT <= 0.0:
                    if flag == 0:
                        flag = 1
                    aR = 1.0
                    aT = 1.0
                FE[i, j, 0] = 0.5 * (NR[i + 1, j] + NR[i - 1, j])
                FE[i, j, 1] = 0.5 * (NT[i, j + 1] + NT[i, j - 1])
                FE[i, j, 2] = 1.0 / (aR * aR)
                FE[i, j, 3] = 1.0 / (aT * aT)
            FE[i, j, 4] = 0.0 if flag == 0 else 1e300
            FF[i, j] = flag
            FJ[i, j, 0] = 0.0
            if tip > 0.0 and flag == 0 and not polygon and not math.isnan(lo):
                ph = uniform(seed, _rng.FIBRE_END_PHASE, n, m, 0) * M[FLEN]
                tip_walls(seed, n, m, L, lo, hi, tip, ph, M[FLEN], aR, aT, FJ[i, j])
    for v in range(nv):
        n = vessels[v, 0]
        m = vessels[v, 1]
        rl, _, _ = node_state(seed, M, n - 3, m, L)
        rr, _, _ = node_state(seed, M, n + 3, m, L)
        _, td, _ = node_state(seed, M, n, m - 3, L)
        _, tu, _ = node_state(seed, M, n, m + 3, L)
        VG[v, 0] = 0.5 * (rl + rr)
        VG[v, 1] = 0.5 * (td + tu)
        VG[v, 2] = 0.5 * (rr - rl) * VESSEL_AXIS_R
        VG[v, 3] = 0.5 * (tu - td)
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
            x = min(L - L0, L1 - L) / M[RRAMP]
            x = min(max(x, 0.0), 1.0)
            taper = x * x * (3.0 - 2.0 * x)
            if taper <= 0.0:
                continue
            rays[nr, 0] = row * c
            rays[nr, 1] = 0.5 * W * taper
            rays[nr, 2] = L0
            rays[nr, 3] = L1
            rays[nr, 4] = k
            rays[nr, 5] = g
            rays[nr, 6] = taper
            nr += 1
    return nr


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
    """Ray band test and squeeze pull-back.  Returns (pT after squeeze, ray row or -1)."""
    for r in range(nr):
        if abs(pT - rays[np.uint64(r), 0]) < rays[np.uint64(r), 1]:
            return pT, r
    for rs in range(nr):
        ru = np.uint64(rs)
        d = pT - rays[ru, 0]
        x = abs(d) - rays[ru, 1]
        if x < lam:
            # Pull-back of the squeeze: the band edge maps to the removed row's edge.
            q = 1.0 - x / lam
            shift = rays[ru, 6] * (c - W2) * q * q * q
            pT = pT + shift if d > 0 else pT - shift
    return pT, -1


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
        if q == best:
            continue
        ii = cand_i[q]
        jj = cand_j[q]
        ex = FE[ii, jj, 0] - FE[bi, bj, 0]
        ey = FE[ii, jj, 1] - FE[bi, bj, 1]
        dR = pR - FE[ii, jj, 0]
        dT = pT - FE[ii, jj, 1]
        dist = (dR * dR + dT * dT - bd) / (2.0 * math.sqrt(ex * ex + ey * ey))
        if dist < 0.5 * (Nt[bi, bj] + Nt[ii, jj]):
            return WALL
    return POLYMER


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
                 FJ, CIJ):
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
            if rotated:
                pR, pT = pull_back(patch, gi0, gj0, G, Rp[i, k], Tp[j])
            else:
                pR = P1[i, j, 0]
                pT = P1[i, j, 1]
            if reuse:
                sT = SQ[i, j]
                r = SR[i, j]
            else:
                sT, r = _squeeze_and_classify(pT, c, W2, lam, rays, nr)
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


# --------------------------------------------------------------------------
# A block of voxels for one ply
# --------------------------------------------------------------------------
@njit(cache=True, nogil=True, error_model="numpy")
def fill_block(out, seed, M, gstart, origin, voxel, j_lo, j_hi, ply, patch, gi0, gj0, dmax,
               vessels, nv, stats):
    """Fill ``out[R, T, L]`` for T indices [j_lo, j_hi) of the block from one ply.

    ply : (cos θ, sin θ, ΔR, ΔT, ΔL), the rotation of the ply in the L-R plane and
    its offset.  Ply coordinates: R' = cos·R + sin·L + ΔR, T' = T + ΔT,
    L' = −sin·R + cos·L + ΔL.  An unrotated ply is evaluated slice by slice at the
    exact L; a rotated one on the global L' lattice of spacing voxel/2.
    """
    nR, nT, nL = out.shape
    cs, sn, oR, oT, oL = ply[0], ply[1], ply[2], ply[3], ply[4]
    c = M[PITCH]
    G = c / GRID_PER_PITCH
    rotated = sn != 0.0
    polygon = M[SHAPE] == 1.0
    tips = M[TIP] > 0.0 and M[ENDS] != 0.0 and not polygon
    q = 0.5 * voxel
    # Ply coordinates of each (R, L) pair, and its slice key.
    Rp = np.empty((nR, nL))
    Lp = np.empty((nR, nL))
    key = np.empty(nR * nL, np.int64)
    for i in range(nR):
        R = origin[0] + (gstart[0] + i + 0.5) * voxel
        for k in range(nL):
            L = origin[2] + (gstart[2] + k + 0.5) * voxel
            Rp[i, k] = cs * R + sn * L + oR
            Lp[i, k] = -sn * R + cs * L + oL
            if rotated:
                key[i * nL + k] = np.int64(round(Lp[i, k] / q))
            else:
                key[i * nL + k] = k
    Tp = np.empty(nT)
    for j in range(nT):
        Tp[j] = origin[1] + (gstart[1] + j + 0.5) * voxel + oT
    order = np.argsort(key, kind="mergesort")
    # Unrotated plies: the pre-image of each (R, T) column is the same on every slice.
    P1 = np.empty((nR if not rotated else 0, nT, 2))
    if not rotated:
        for i in range(nR):
            for j in range(j_lo, j_hi):
                a, b = pull_back(patch, gi0, gj0, G, Rp[i, 0], Tp[j])
                P1[i, j, 0] = a
                P1[i, j, 1] = b
    W2 = 0.5 * ray_band_width(M) if M[RAYS] != 0.0 else 0.0
    t_margin = dmax + max(c, W2) + 1.0
    m_lo = np.int64(math.floor((Tp[j_lo] - t_margin) / c)) - 5
    m_hi = np.int64(math.ceil((Tp[j_hi - 1] + t_margin) / c)) + 5
    nm = m_hi - m_lo + 1
    VG = np.empty((max(nv, 1), 4))
    VB = np.empty((max(nv, 1), 2, 6))
    rays = np.empty((64, 7))
    RC = np.empty((64, 6, 8))
    # Control values and fibre cells shared by the slices (see build_slice); their
    # window spans every slice's node window.
    cn = np.int64(math.floor((Rp.min() - dmax - 1.0) / c)) - 4
    cn_hi = np.int64(math.ceil((Rp.max() + dmax + 1.0) / c)) + 4
    l_lo, l_hi = Lp.min() - q, Lp.max() + q  # a rotated ply's slices sit on the L' lattice
    ck = np.int64(math.floor(l_lo / M[CTRL])) - 1
    nk = np.int64(math.floor(l_hi / M[CTRL])) + 3 - ck
    CV = np.empty((cn_hi - cn + 1, nm, nk, 3))
    CF = np.zeros((cn_hi - cn + 1, nm, nk), np.uint8)
    ENDS_ = np.full((cn_hi - cn + 1, nm, 2), np.nan)
    # An unrotated ply's slices read the same (R, T) points: one whose ray table
    # equals the last slice's squeezes and classifies them as it did (SQ, SR).
    SQ = np.empty((nR if not rotated else 0, nT))
    SR = np.empty((nR if not rotated else 0, nT), np.int64)
    last = np.empty((64, 7))
    n_last = -1
    start = 0
    total = nR * nL
    while start < total:
        kb = key[order[start]]
        stop = start
        rmin = 1e300
        rmax = -1e300
        while stop < total and key[order[stop]] == kb:
            idx = order[stop]
            r = Rp[idx // nL, idx % nL]
            rmin = min(rmin, r)
            rmax = max(rmax, r)
            stop += 1
        if rotated:
            L = kb * q
        else:
            L = Lp[0, kb]
        n_lo = np.int64(math.floor((rmin - dmax - 1.0) / c)) - 4
        n_hi = np.int64(math.ceil((rmax + dmax + 1.0) / c)) + 4
        nn = n_hi - n_lo + 1
        NR = np.empty((nn, nm))
        NT = np.empty((nn, nm))
        Nt = np.empty((nn, nm))
        FE = np.zeros((nn, nm, 5))
        FE[:, :, 4] = 1e300
        FF = np.ones((nn, nm), np.uint8)
        FJ = np.zeros((nn, nm, 7))
        VIDX = np.empty((nn, nm), np.int64)
        nr = build_slice(seed, M, L, n_lo, m_lo, NR, NT, Nt, FE, FF, FJ, vessels, nv, VG, VB, VIDX,
                         rays, stats, CV, CF, cn, ck, ENDS_)
        ray_slice_tables(seed, M, L, rays, nr, RC)
        reuse = not rotated and nr == n_last
        for r in range(nr):
            for f in range(7):
                reuse = reuse and rays[r, f] == last[r, f]
                last[r, f] = rays[r, f]
        n_last = nr
        nb = ((m_lo + nm - 1) >> 1) - (m_lo >> 1) + 1
        C4 = np.empty((nn, nb, 5, 4))
        CIJ = np.empty((nn if tips else 0, nb, 4, 2), np.int64)
        if not polygon:
            candidate_table(FE, n_lo, m_lo, C4, FJ, CIJ)
        _eval_bucket(out, order, start, stop, nL, j_lo, j_hi, rotated, Rp, Tp, P1, patch, gi0,
                     gj0, G, seed, M, n_lo, m_lo, FE, FF, Nt, vessels[:nv], VG, VB, VIDX, rays, nr, RC,
                     C4, SQ, SR, reuse, FJ, CIJ)
        stats[ST_VOXELS] += (stop - start) * (j_hi - j_lo)
        start = stop
