"""Kernels of the vessels: a stationary, hashed, Matérn-II-thinned cluster process
(docs/methods.md#vessels)."""

import math

import numpy as np
from numba import njit

from .. import rng as _rng
from ..rng import uniform
from ._constants import VESSELS, VHARD_R, VHARD_T, VPAIR, VPROB, VRAY_CLEAR, VTILE_R, VTILE_T, VTRIPLE
from ._ray_cells import near_ray

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
        if near_ray(seed, M, mem_m[i], np.int64(VRAY_CLEAR)):  # not a literal: near_ray compiles once
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
def member_of(vessels, nv, n, m):
    for v in range(nv):
        if abs(n - vessels[v, 0]) <= 2 and abs(m - vessels[v, 1]) <= 2:
            return True
    return False
