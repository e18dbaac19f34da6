"""The rows the surface kernels write: primitive kinds, the row layout, the margins and the rates
their clearances need (docs/methods.md#the-wood-as-surfaces)."""

import math

import numpy as np
from numba import njit

from ._constants import CTRL, JITTER, PITCH, PUSH, RAYS, RRAMP, RSQUEEZE, SCALE, T0, TIP, WALLVAR
from ._ray_cells import ray_band_width

# Primitive kinds (column 0 of a row).
P_BAND = 1  # edge of a ray band: |pT − t_r| = b (a = column k)
P_RAY_LUMEN = 2  # ray-cell lumen ellipse in (T, L) (k, sub-column, cell along L)
P_RAY_END = 3  # radial end wall of a ray cell (k, sub-column, cell, side)
P_VESSEL_OUT = 4  # vessel outline (n, m)
P_VESSEL_IN = 5  # vessel lumen (n, m)
P_VESSEL_SHARED = 6  # wall shared by cluster neighbours (n, m, side)
P_LUMEN = 7  # fibre lumen ellipse (n, m)
P_PLATE = 8  # end plate plane along L (n, m, side)
P_TIP = 9  # oblique tip wall (n, m, wall)
P_TIP_END = 10  # where a tip wall begins or ends along L (n, m, side)
P_FACE = 11  # balsa: wall along a Voronoi face (n, m, neighbour n, neighbour m)
P_PLY = 12  # ply boundary (the index of the ply above it)
P_REACH = 13  # not a surface: how far the point's candidate set is valid
# Row columns: kind, ids a-d, g, clearance; then what a ray's proven step needs
# (pipeline/microstructure/surface_ray.py): a fibre lumen's offset from its centre and its
# semi-axes in the pulled-back plane (semi-axis 0: no ellipse), a balsa face's unit normal (towards
# the neighbour) and how fast it moves with L (C_DR, C_DT, C_AR), the fibre cells' reach row's
# squeeze slope d(squeezed T)/d(pulled-back T) and the pulled-back point (R, squeezed T); and,
# written by the march, how far along the ray the lumen is surely entered (0: not known).
C_DR, C_DT, C_AR, C_AT, C_CROSS = 7, 8, 9, 10, 11
C_SQUEEZE, C_PR, C_ST = 7, 8, 9
N_COLS = 12
MAX_PRIMS = 160
VBUCKET = 8  # nodes per side of a vessel bucket
VESSEL_REACH = 24  # nodes: clusters with a member this near a listed point are listed whole
INF = 1e300

# Bound of Σ|w'(f)| of the Catmull-Rom weights over f in [0, 1]: how fast a node moves along L.
CR_SLOPE = 1.6

# Rates (context vector R, floats) the Lipschitz constants need, per wood: see rates().
R_NODE, R_WALL, R_BAND, R_SQ_L, R_SQ, R_TIP = range(6)
N_RATES = 6


def rates(M: np.ndarray) -> np.ndarray:
    """How fast the model's surfaces move with L, and how much the squeeze stretches T
    (the constants of the clearance bounds)."""
    out = np.zeros(N_RATES)
    c = M[PITCH]
    out[R_NODE] = M[JITTER] * c * CR_SLOPE / M[CTRL]
    out[R_WALL] = M[T0] * M[WALLVAR] * CR_SLOPE / M[CTRL]
    if M[RAYS] != 0.0:
        W = ray_band_width(M)
        lam = M[RSQUEEZE] * M[SCALE]
        out[R_BAND] = 0.5 * W * 1.5 / M[RRAMP]
        out[R_SQ_L] = abs(c - 0.5 * W) * 1.5 / M[RRAMP]
        out[R_SQ] = 1.0 + 3.0 * abs(c - 0.5 * W) / lam
    else:
        out[R_SQ] = 1.0
    if M[TIP] > 0.0:
        push = M[PUSH] * M[SCALE]
        w_max = 1.5 * (c + push)
        out[R_TIP] = w_max / M[TIP] + 2.0 * out[R_NODE] + 2.0 * out[R_WALL]
    return out


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _row(P, n, kind, a, b, c, d, g, clr):
    if n < P.shape[0]:
        P[n, 0] = kind
        P[n, 1] = a
        P[n, 2] = b
        P[n, 3] = c
        P[n, 4] = d
        P[n, 5] = g
        P[n, 6] = clr
        for q in range(C_DR, N_COLS):
            P[n, q] = 0.0
        return n + 1
    return n


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _row_x(P, n, kind, a, b, c, d, g, clr, x0, x1, x2, x3):
    """:func:`_row` with columns C_DR.. as well (C_CROSS 0)."""
    m = _row(P, n, kind, a, b, c, d, g, clr)
    if m > n:
        P[n, C_DR] = x0
        P[n, C_DT] = x1
        P[n, C_AR] = x2
        P[n, C_AT] = x3
    return m


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _ellipse_margin(dR, dT, aR, aT):
    """(sqrt(q) − 1)·min(a): positive outside, its modulus a lower bound on the distance to the
    ellipse of semi-axes aR, aT (the map scaling by 1/a moves points by at most 1/min(a))."""
    q = dR * dR / (aR * aR) + dT * dT / (aT * aT)
    return (math.sqrt(q) - 1.0) * min(aR, aT)


