"""Counter-based random numbers: every value is a hash of (seed, kind, ids).

No sequential stream exists anywhere in twray, so any entity (a node, a
fibre, a vessel tile, a ray, an aperture sample) draws its random values
alone, in any order, on any worker (docs/methods.md#random-streams).

The kinds below are the one registry of streams: two quantities that must be
independent never share a kind.
"""

import math

import numpy as np
from numba import njit

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV53 = 1.0 / 9007199254740992.0

# Stream kinds: one per independent random quantity, for the whole package.
# The microstructure generator:
NODE_R = 1
NODE_T = 2
NODE_WALL = 3
FIBRE_END = 4
FIBRE_END_PHASE = 5
DIPOLE = 6
DIPOLE_SIGN = 7
LARGE_DIPOLE = 8
VESSEL_TILE = 9
VESSEL_MEMBER = 10
RAY_COLUMN = 11
RAY_GROUP = 12
RAY_CELL_END = 13
RAY_CELL_PHASE = 14
GLOBAL_BEND = 15
PLY = 16
FIBRE_TIP = 17
# The tracer:
FRESNEL = 40  # partial reflection at an interface, per (ray, event)
BEAM = 41  # entry point of a beam's ray, per ray
# The exact reference lattices:
LATTICE_SITE = 50  # jitter of a lattice site, per (i, j)
NORMAL_NOISE = 51  # perturbation of a normal, per (ray, event)
# The virtual camera:
APERTURE = 61  # aperture samples of a pixel
# Grey-level scans of generated wood:
SCAN_NOISE = 70  # a scan's detector noise, per voxel (i, j, k)


def kinds() -> dict[str, int]:
    """Every stream kind by name (the registry above)."""
    return {k: v for k, v in globals().items() if k.isupper() and not k.startswith("_") and isinstance(v, int)}


@njit(inline="always", cache=True, error_model="numpy")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(inline="always", cache=True, error_model="numpy")
def hash5(seed, kind, a, b, c):
    """64-bit hash of (seed, kind, a, b, c); ids may be negative."""
    h = _mix(np.uint64(seed) ^ (np.uint64(kind) * _GOLD))
    h = _mix(h ^ np.uint64(np.int64(a)))
    h = _mix(h ^ (np.uint64(np.int64(b)) * _GOLD))
    return _mix(h ^ np.uint64(np.int64(c)) ^ _M2)


@njit(inline="always", cache=True, error_model="numpy")
def uniform(seed, kind, a, b, c):
    """U[0, 1) from the hash of (seed, kind, a, b, c)."""
    return float(hash5(seed, kind, a, b, c) >> _S11) * _INV53


@njit(cache=True, error_model="numpy")
def uniform_table(seed, kind, ids, n_b, c):
    """uniform(seed, kind, id, b, c) for every id of ``ids`` and b < n_b, as an (ids.size, n_b) array."""
    out = np.empty((ids.size, n_b))
    for r in range(ids.size):
        for b in range(n_b):
            out[r, b] = uniform(seed, kind, ids[r], b, c)
    return out


@njit(inline="always", cache=True, error_model="numpy")
def normal(seed, kind, a, b, c):
    """N(0, 1) by Box-Muller from two hashed uniforms."""
    u1 = uniform(seed, kind, a, b, 2 * c)
    u2 = uniform(seed, kind, a, b, 2 * c + 1)
    return math.sqrt(-2.0 * math.log(1.0 - u1)) * math.cos(2.0 * math.pi * u2)
