"""The region of wood a trace needs, as the arrays :func:`~pipeline.microstructure.surface.evaluate`
reads (docs/methods.md#the-wood-as-surfaces): per ply its placement, seed, distortion grid (from
the generator's cached tiles) with the Lipschitz bound of its pull-back, and its vessels indexed
by bucket; and the phase at many points."""

import functools
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

from . import _constants as K
from ._surface_cells import new_cache
from .model import N_STATS, _patch, _plies, _tile, model_constants, tile_range
from ._surface_rows import MAX_PRIMS, N_COLS, VBUCKET, VESSEL_REACH, rates
from .surface import clearance, evaluate_at


def lipschitz_of_pull_back(patch: np.ndarray, G: float) -> float:
    """A bound of ‖∂p/∂X‖ for the bilinear pull-back p = X − d(X) on ``patch``: 1 + the largest
    Frobenius norm of ∂d/∂X over its cells (each partial derivative of a bilinear cell lies between
    its two edge differences)."""
    return _lipschitz(np.ascontiguousarray(patch, np.float64), float(G))


@njit(cache=True, nogil=True, error_model="numpy")
def _lipschitz(patch, G):
    best = 0.0
    for i in range(patch.shape[0] - 1):
        for j in range(patch.shape[1] - 1):
            s = 0.0  # ∂d/∂R²: each component the larger of its two edge differences, squared
            for c in range(2):
                x = max(abs(patch[i + 1, j, c] - patch[i, j, c]) / G, abs(patch[i + 1, j + 1, c] - patch[i, j + 1, c]) / G)
                s = x * x if c == 0 else s + x * x
            t = 0.0  # ∂d/∂T², the same
            for c in range(2):
                y = max(abs(patch[i, j + 1, c] - patch[i, j, c]) / G, abs(patch[i + 1, j + 1, c] - patch[i + 1, j, c]) / G)
                t = y * y if c == 0 else t + y * y
            best = max(best, math.sqrt(s + t))
    return (1.0 + best) * (1.0 + 1e-12)


@functools.lru_cache(maxsize=8192)
def _tile_lipschitz(seed: int, M_bytes: bytes, a: int, b: int, G: float) -> float:
    return lipschitz_of_pull_back(_tile(seed, M_bytes, a, b)[0], G)


def _patch_lipschitz(seed, M, gi0: int, gj0: int, shape, G: float) -> np.ndarray:
    """Per tile of a patch of whole tiles, :func:`lipschitz_of_pull_back` over that tile and its
    eight neighbours (each tile's computed once): a bound on the pull-back's rate within one tile
    (116 µm for birch) of any point of the tile, further than any step goes (a reach row caps
    steps at a cell pitch).  It depends on the point's tile alone, not on the region, so a ray's
    steps do not depend on the rays traced beside it."""
    a0, b0 = gi0 // K.TILE, gj0 // K.TILE
    na, nb = (shape[0] - 1) // K.TILE, (shape[1] - 1) // K.TILE
    key = M.tobytes()
    own = np.array([[_tile_lipschitz(int(seed), key, a, b, G) for b in range(b0 - 1, b0 + nb + 1)]
                    for a in range(a0 - 1, a0 + na + 1)])
    out = np.empty((na, nb))
    for i in range(na):
        for j in range(nb):
            out[i, j] = own[i:i + 3, j:j + 3].max()
    return out


# How far [grid cells] a ray's proven step may reach from its start (surface_ray.STEP_CELLS): a
# tile's curvature bound covers the cells that far around it.
CURVE_REACH = 17


@functools.lru_cache(maxsize=8192)
def _tile_curvature(seed: int, M_bytes: bytes, a: int, b: int, G: float) -> tuple:
    """(Kxx, Kyy, Kxy) of tile (a, b): the largest second differences of the distortion grid,
    along R, along T and across (a cell's four corners), as norms of their (dR, dT) over G, for
    every difference whose middle node (or cell) lies within CURVE_REACH cells of the tile.  Across
    a grid line the bilinear pull-back's slope jumps by at most Kxx (Kyy); within a cell it turns at
    most Kxy / G per µm (docs/methods.md#proven-steps-along-the-ray)."""
    t, r = K.TILE, CURVE_REACH
    grid = np.empty((3 * t + 1, 3 * t + 1, 2))
    for da in range(3):
        for db in range(3):
            grid[da * t:da * t + t + 1, db * t:db * t + t + 1] = _tile(seed, M_bytes, a + da - 1, b + db - 1)[0]
    k = _second_differences(grid[t - r - 1:2 * t + r + 2, t - r - 1:2 * t + r + 2])
    return tuple(float(x) * (1.0 + 1e-9) / G for x in k)


@njit(cache=True, nogil=True, error_model="numpy")
def _second_differences(E):
    """The largest norms of E's (n, n, 2) second differences along axis 0, along axis 1 (middle
    nodes off the border) and across (each cell's four corners)."""
    kxx = kyy = kxy = 0.0
    n0, n1 = E.shape[0], E.shape[1]
    for i in range(n0 - 1):
        for j in range(n1 - 1):
            a = b = c = 0.0
            for q in range(2):
                x = E[i + 1, j + 1, q] - E[i, j + 1, q] - E[i + 1, j, q] + E[i, j, q]
                c += x * x
                if 0 < i and 0 < j:
                    y = E[i + 1, j, q] - 2.0 * E[i, j, q] + E[i - 1, j, q]
                    z = E[i, j + 1, q] - 2.0 * E[i, j, q] + E[i, j - 1, q]
                    a += y * y
                    b += z * z
            kxx = max(kxx, a)
            kyy = max(kyy, b)
            kxy = max(kxy, c)
    return math.sqrt(kxx), math.sqrt(kyy), math.sqrt(kxy)


def _patch_curvature(seed, M, gi0: int, gj0: int, shape, G: float) -> np.ndarray:
    """Per tile of a patch of whole tiles, :func:`_tile_curvature`: (tiles along R, along T, 3)."""
    a0, b0 = gi0 // K.TILE, gj0 // K.TILE
    na, nb = (shape[0] - 1) // K.TILE, (shape[1] - 1) // K.TILE
    key = M.tobytes()
    return np.array([[_tile_curvature(int(seed), key, a0 + i, b0 + j, G) for j in range(nb)] for i in range(na)])


def _warm_tiles(seed, M, tiles, G: float, threads: int) -> None:
    """Compute the distortion tiles ``tiles`` [(a, b)] and their pull-back bounds into their caches
    on ``threads`` threads (the tile kernel releases the GIL); the same values as one by one."""
    if threads > 1 and len(tiles) > 1:
        key = M.tobytes()
        with ThreadPoolExecutor(min(threads, len(tiles))) as pool:
            list(pool.map(lambda ab: _tile_lipschitz(int(seed), key, ab[0], ab[1], G), tiles))


def region_context(params, seed: int, thickness_um: float, r_range, l_range, t_range=None, *,
                   threads: int = 1) -> dict:
    """What :func:`evaluate` needs for the slab T ∈ [0, thickness] (or its part ``t_range``) over
    R ∈ r_range, L ∈ l_range [µm]: per ply its placement, seed, distortion grid (assembled from the
    generator's cached tiles, computed on ``threads`` threads), pull-back bound and vessels; arrays
    padded to the largest ply.  Every ply of the slab is listed (a point's rows name the plies around
    it), each with its grid over the part of ``t_range`` it holds (none: a point there is outside the
    region)."""
    from ._vessels import vessels_in_region

    M = model_constants(params)
    c = params.node_pitch_um
    G = c / K.GRID_PER_PITCH
    stats = np.zeros(N_STATS, np.int64)
    plies = _ply_extents(params, seed, thickness_um, r_range, l_range, t_range)
    rows, seeds, spans, patches, origins, lams, curves, ves, nvs, boxes = [], [], [], [], [], [], [], [], [], []
    for (_, cs, sn, oR, oT, oL, _, t0, t1), pseed, r_lo, r_hi, tt_lo, tt_hi in plies:
        _warm_tiles(pseed, M, _tiles_read(M, r_lo, r_hi, tt_lo, tt_hi), G, threads)
        patch, gi0, gj0 = _patch(pseed, M, r_lo - 1.0, r_hi + 1.0, tt_lo - 1.0, tt_hi + 1.0, stats)
        dmax = float(np.abs(patch).max())
        box = (math.floor((r_lo - dmax) / c) - 2, math.ceil((r_hi + dmax) / c) + 2,
               math.floor((tt_lo - dmax - 80.0 * params.scale) / c) - 2,
               math.ceil((tt_hi + dmax + 80.0 * params.scale) / c) + 2)
        vessels = np.empty((8192, 5), np.int64)
        nv = vessels_in_region(pseed, M, box[0] - VESSEL_REACH, box[1] + VESSEL_REACH,
                               box[2] - VESSEL_REACH, box[3] + VESSEL_REACH, vessels)
        rows.append((cs, sn, oR, oT, oL))
        seeds.append(pseed)
        spans.append((t0, t1))
        patches.append(patch)
        origins.append((gi0, gj0))
        lams.append(_patch_lipschitz(pseed, M, gi0, gj0, patch.shape, G))
        curves.append(_patch_curvature(pseed, M, gi0, gj0, patch.shape, G))
        ves.append(vessels[:nv])
        nvs.append(nv)
        boxes.append(box)
    buckets = [_vessel_buckets(v, box) for v, box in zip(ves, boxes)]
    nptr = max(len(b[1]) for b in buckets)
    nlist = max(1, max(len(b[2]) for b in buckets))
    BP = np.zeros((len(plies), nptr), np.int64)
    BL = np.zeros((len(plies), nlist), np.int64)
    for q, (_, ptr, lst) in enumerate(buckets):
        BP[q, :len(ptr)] = ptr
        BL[q, :len(lst)] = lst
    ni = max(p.shape[0] for p in patches)
    nj = max(p.shape[1] for p in patches)
    LT = np.zeros((len(plies), max(t.shape[0] for t in lams), max(t.shape[1] for t in lams)))
    for q, t in enumerate(lams):
        LT[q, :t.shape[0], :t.shape[1]] = t
    CT = np.zeros(LT.shape + (3,))
    for q, t in enumerate(curves):
        CT[q, :t.shape[0], :t.shape[1]] = t
    P = np.zeros((len(plies), ni, nj, 2))
    for q, p in enumerate(patches):
        P[q, :p.shape[0], :p.shape[1]] = p
    V = np.zeros((len(plies), max(1, max(nvs)), 5), np.int64)
    for q, v in enumerate(ves):
        V[q, :len(v)] = v
    return {
        "M": M, "rates": rates(M), "plies": np.array(rows, np.float64), "seeds": np.array(seeds, np.uint64),
        "spans": np.array(spans, np.float64), "patches": P,
        "patch_shape": np.array([p.shape[:2] for p in patches], np.int64),
        "origins": np.array(origins, np.int64), "lipschitz": LT, "vessels": V,
        "n_vessels": np.array(nvs, np.int64), "boxes": np.array(boxes, np.int64),
        "ply_thickness": float(params.ply_thickness_um) if params.laminate is not None else math.inf,
        "first_ply": int(plies[0][0][0]), "bucket_shape": np.array([b[0] for b in buckets], np.int64),
        "bucket_ptr": BP, "bucket_list": BL, "curvature": CT,
    }


def _ply_extents(params, seed: int, thickness_um: float, r_range, l_range, t_range) -> list:
    """Per ply of the slab T ∈ [0, thickness] (:func:`~pipeline.microstructure.model._plies`), its
    tuple, seed and the box (R lo, R hi, T lo, T hi) [µm, the ply's own axes] the region
    R ∈ r_range, L ∈ l_range, T ∈ t_range (None: the slab) covers in it."""
    t_range = (0.0, thickness_um) if t_range is None else t_range
    out = []
    for ply in _plies(params, seed, 0.0, thickness_um):
        _, cs, sn, oR, oT, _, ply_seed, t0, t1 = ply
        if not (t0 < thickness_um or ply[0] == 0):
            continue
        corners = [cs * r + sn * l + oR for r in r_range for l in l_range]
        tt_lo, tt_hi = max(t0, 0.0, t_range[0]) + oT, min(t1, thickness_um, t_range[1]) + oT
        out.append((ply, np.uint64(ply_seed), min(corners), max(corners), tt_lo, max(tt_hi, tt_lo)))
    return out


def _tiles_read(M, r_lo, r_hi, tt_lo, tt_hi) -> list:
    """The distortion tiles (a, b) a ply's box reads: its patch's and their neighbours (the
    pull-back bounds read them)."""
    a0, a1, b0, b1 = tile_range(M, r_lo - 1.0, r_hi + 1.0, tt_lo - 1.0, tt_hi + 1.0)
    return [(a, b) for a in range(a0 - 1, a1 + 2) for b in range(b0 - 1, b1 + 2)]


def warm_regions(params, seed: int, thickness_um: float, regions, threads: int) -> None:
    """Compute the distortion tiles (and pull-back bounds) that the regions ``regions`` [(r_range,
    l_range, t_range)] read, all at once on ``threads`` threads, so that building them finds every
    tile cached; the same values as :func:`region_context` computes one by one."""
    M = model_constants(params)
    G = params.node_pitch_um / K.GRID_PER_PITCH
    todo = {}
    for r, l, t in regions:
        for _, pseed, *box in _ply_extents(params, seed, thickness_um, r, l, t):
            todo.setdefault(int(pseed), set()).update(_tiles_read(M, *box))
    for pseed, tiles in todo.items():
        _warm_tiles(np.uint64(pseed), M, sorted(tiles), G, threads)


def _vessel_buckets(vessels: np.ndarray, box) -> tuple:
    """Per bucket of VBUCKET² nodes over ``box``, the starts of the clusters with a member within
    12 nodes of the bucket (ascending), as (grid shape, pointers, starts)."""
    nb = ((box[1] - box[0]) // VBUCKET + 1, (box[3] - box[2]) // VBUCKET + 1)
    lists = [[] for _ in range(nb[0] * nb[1])]
    v = 0
    while v < len(vessels):
        size = int(vessels[v, 4])
        mem = vessels[v:v + size, :2]
        i0 = max(0, (int(mem[:, 0].min()) - 12 - box[0]) // VBUCKET)
        i1 = min(nb[0] - 1, (int(mem[:, 0].max()) + 12 - box[0]) // VBUCKET)
        j0 = max(0, (int(mem[:, 1].min()) - 12 - box[2]) // VBUCKET)
        j1 = min(nb[1] - 1, (int(mem[:, 1].max()) + 12 - box[2]) // VBUCKET)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                lists[i * nb[1] + j].append(v)
        v += size
    ptr = np.zeros(len(lists) + 1, np.int64)
    ptr[1:] = np.cumsum([len(x) for x in lists])
    flat = np.array([v for x in lists for v in x], np.int64)
    return np.array(nb, np.int64), ptr, flat


def context_tuple(ctx: dict) -> tuple:
    """The arrays of :func:`region_context` in the order the kernels take them."""
    return (ctx["M"], ctx["rates"], ctx["plies"], ctx["seeds"], ctx["spans"], ctx["patches"],
            ctx["patch_shape"], ctx["origins"], ctx["lipschitz"], ctx["vessels"], ctx["n_vessels"],
            ctx["boxes"], ctx["ply_thickness"], ctx["first_ply"], ctx["bucket_shape"], ctx["bucket_ptr"],
            ctx["bucket_list"], ctx["curvature"])


@njit(cache=True, nogil=True, error_model="numpy")
def _phases(points, lq, ctx, cache, clr):
    out = np.empty(points.shape[0], np.uint8)
    P = np.empty((MAX_PRIMS, N_COLS))
    every = np.zeros(5)
    for i in range(points.shape[0]):
        out[i], n = evaluate_at(points[i, 0], points[i, 1], points[i, 2], lq, ctx, P, cache, every)
        if clr.shape[0] > 0:  # a full row table may have lost rows: no ball is proven
            clr[i] = clearance(P, n) if n < MAX_PRIMS else 0.0
    return out


def phases(points, lq, ctx, *, clearances: np.ndarray | None = None, cache=None) -> np.ndarray:
    """Phase at each of ``points`` (N, 3) [µm] (255: outside the context's region); with
    ``clearances`` (N floats), each point's clearance [µm] written there (the radius of a ball in
    which the phase cannot change; :func:`~pipeline.microstructure.surface.clearance`).  ``cache``:
    a :func:`~pipeline.microstructure._surface_cells.new_cache` to reuse (one a thread)."""
    clr = np.empty(0) if clearances is None else clearances
    return _phases(np.ascontiguousarray(points, np.float64), float(lq), ctx,
                   new_cache() if cache is None else cache, clr)
