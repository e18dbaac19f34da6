"""The wood microstructure as a pure function of (parameters, seed, position).

:func:`generate_block` evaluates any box of voxels of the infinite,
stationary wood field.  It is what every chunk of a volume calls; the bytes
of a voxel depend only on its global position, never on the box around it.
"""

from __future__ import annotations

import collections
import functools
import math
import threading

import numpy as np

from ..params import Grid, WoodParams
from . import _constants as K
from ._block import fill_block
from ._distortion import distortion_tile, large_dipoles_in, large_range
from ._vessels import vessels_in_region
from .. import rng as _rng

N_STATS = 5
STAT_NAMES = ("node_states", "voxels", "dipole_terms", "chain_lookups", "distortion_tiles")


def model_constants(p: WoodParams) -> np.ndarray:
    """The float64 constant vector the kernels read (lengths in µm)."""
    M = np.zeros(K.N_CONSTANTS)
    M[K.PITCH] = p.node_pitch_um
    M[K.SCALE] = p.scale
    M[K.T0] = p.wall_thickness_um / 2.0
    M[K.WALLVAR] = p.wall_variation
    M[K.JITTER] = p.node_jitter
    M[K.PUSH] = p.lumen_elongation_um
    M[K.CTRL] = p.control_spacing_um
    M[K.FLEN] = p.fibre_length_um
    M[K.FLEN_SD] = p.fibre_length_sd_um
    M[K.PLATE] = p.wall_thickness_um
    M[K.ENDS] = float(p.end_plates)
    M[K.TIP] = p.fibre_tip_um
    M[K.SHAPE] = 1.0 if p.cell_shape == "polygon" else 0.0
    M[K.VESSELS] = float(p.vessels)
    M[K.VPROB] = p.vessel_cluster_probability
    M[K.VPAIR] = p.vessel_pair_fraction
    M[K.VTRIPLE] = p.vessel_triple_fraction
    M[K.VWALL] = p.vessel_wall()
    M[K.RAYS] = float(p.ray_cells)
    M[K.RSPACE] = p.ray_spacing_nodes
    M[K.RJIT] = p.ray_jitter_nodes
    M[K.RSER] = p.ray_seriate
    M[K.RWIDTH] = p.ray_cell_width_um
    M[K.RHEIGHT] = p.ray_cell_height_um
    M[K.RLEN] = p.ray_cell_length_um
    M[K.RLEN_SD] = p.ray_cell_length_sd_um
    M[K.RGROUP] = p.ray_group_cells
    M[K.RGROUP_SD] = p.ray_group_cells_sd
    M[K.RSQUEEZE] = p.ray_squeeze_um
    M[K.RRAMP] = p.ray_ramp_um
    M[K.DIST] = p.distortion
    M[K.LARGE_P] = p.large_distortion_probability
    M[K.BEND_A] = p.global_bend_um
    M[K.BEND_WL] = p.global_bend_wavelength_um
    return M


def lumen_half_width_um(p: WoodParams) -> float:
    """A fibre lumen's half-width, averaged over directions in the R-T plane, for the nominal
    lattice (no jitter): the inset ellipse of semi-axes c − t₀ (R) and c + push − t₀ (T)."""
    c, t0 = p.node_pitch_um, p.wall_thickness_um / 2.0
    phi = np.linspace(0.0, 2.0 * np.pi, 721)
    return float(np.mean(np.hypot((c - t0) * np.cos(phi), (c + p.lumen_elongation_um * p.scale - t0) * np.sin(phi))))


def tip_wall_angle_deg(p: WoodParams) -> float:
    """Inclination to L of the oblique wall between overlapping fibre tips, atan(w/λ)
    (docs/methods.md, "Fibre tips"); 0 for flat fibre ends."""
    if not p.fibre_tip_um:
        return 0.0
    return math.degrees(math.atan(lumen_half_width_um(p) / p.fibre_tip_um))


TILE_BUDGET = 2048  # distortion tiles kept beside the wood in use (65² × 2 floats each: ~140 MB in all)
WOOD_TILE_CAP = 16384  # tiles the wood in use keeps at most (~1.1 GB), a ceiling for rays guided along R
TILE_BYTES = (K.TILE + 1) ** 2 * 2 * 8  # one tile's grid [bytes] (its counters beside it are negligible)


class _WoodTiles:
    """The distortion tiles a process has computed, kept by wood (a ply's seed and constants).

    Whole woods are let go, least recently used first, once more than ``budget`` tiles are held,
    but never the wood asked for last: while a worker traces one wood (its shards of every value
    and study run in a row, docs/performance.md), none of its tiles is computed twice while it
    holds at most ``wood_cap``; past that, its own least recently used tiles go.  A 150 µm beam
    through 2 mm of birch needs about 430 tiles; the few rays guided along R by total reflection
    at the walls up to the event cap need thousands, revisited as they bounce, which is what the
    cap bounds.  A tile is a pure function of its key, so what is kept changes no number.
    """

    def __init__(self, budget: int, wood_cap: int = WOOD_TILE_CAP):
        self.budget = budget
        self.wood_cap = max(wood_cap, 1)
        self.woods: collections.OrderedDict = collections.OrderedDict()
        self.held = 0
        self.lock = threading.Lock()

    def get(self, seed: int, M_bytes: bytes, a: int, b: int) -> tuple[tuple[np.ndarray, np.ndarray], bool]:
        """((tile, its counters), whether it was computed by this call)."""
        wood = (seed, M_bytes)
        with self.lock:
            tiles = self.woods.setdefault(wood, collections.OrderedDict())
            self.woods.move_to_end(wood)
            found = tiles.get((a, b))
            if found is not None:
                tiles.move_to_end((a, b))
                return found, False
        made = _compute_tile(seed, M_bytes, a, b)
        with self.lock:
            tiles = self.woods.setdefault(wood, collections.OrderedDict())
            if (a, b) not in tiles:
                tiles[(a, b)] = made
                self.held += 1
            while self.held > self.budget and len(self.woods) > 1 and next(iter(self.woods)) != wood:
                _, gone = self.woods.popitem(last=False)
                self.held -= len(gone)
            while len(tiles) > self.wood_cap:  # the wood in use over its ceiling: its least recently used
                tiles.popitem(last=False)
                self.held -= 1
            return tiles.get((a, b), made), True

    def cache_clear(self) -> None:
        with self.lock:
            self.woods.clear()
            self.held = 0


_TILES = _WoodTiles(TILE_BUDGET)


def _compute_tile(seed: int, M_bytes: bytes, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    # Writable, as every other caller's: a read-only M would compile the kernels it reaches again.
    M = np.frombuffer(M_bytes, dtype=np.float64).copy()
    out = np.empty((K.TILE + 1, K.TILE + 1, 2))
    stats = np.zeros(N_STATS, np.int64)
    box = np.array(large_range(M, a, b), np.int64)
    large = (_large_dipoles(seed, M_bytes, *box) if M[K.LARGE_P] > 0.0 and M[K.DIST] > 0.0
             else np.empty((0, 2), np.int64))
    distortion_tile(np.uint64(seed), M, a, b, out, stats, large, box)
    out.setflags(write=False)
    return out, stats


def _tile(seed: int, M_bytes: bytes, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Distortion tile (a, b) of the wood (seed, constants) and its counters, from the process's
    tiles (:class:`_WoodTiles`)."""
    return _TILES.get(seed, M_bytes, a, b)[0]


_tile.cache_clear = _TILES.cache_clear


def tiles_held() -> int:
    """How many distortion tiles this process holds, of every wood (benchmarks count them)."""
    return _TILES.held


def clear_tiles() -> None:
    """Let go every distortion tile this process holds (a tile is a pure function of its key, so
    no number changes; the next trace builds what it needs again)."""
    _TILES.cache_clear()


LARGE_BLOCK = 128  # nodes per side of a block whose large-scale dipoles are found once


@functools.lru_cache(maxsize=1024)
def _large_block(seed: int, M_bytes: bytes, i: int, j: int) -> np.ndarray:
    """The large-scale dipoles of node block (i, j) (LARGE_BLOCK² nodes), by m then nn."""
    M = np.frombuffer(M_bytes, dtype=np.float64).copy()
    out = np.empty((LARGE_BLOCK * LARGE_BLOCK, 2), np.int64)
    B = LARGE_BLOCK
    k = large_dipoles_in(np.uint64(seed), M, i * B, i * B + B - 1, j * B, j * B + B - 1, out)
    return out[:k].copy()


def _large_dipoles(seed: int, M_bytes: bytes, n_lo: int, n_hi: int, m_lo: int, m_hi: int) -> np.ndarray:
    """The large-scale dipoles of nodes [n_lo, n_hi] × [m_lo, m_hi], by m then nn: the order a
    scan of those nodes finds them in (a tile's sum adds them in it), from the cached blocks
    (a tile's range spans 180 nodes for birch; its neighbours' share most of it)."""
    B = LARGE_BLOCK
    parts = [_large_block(seed, M_bytes, i, j) for i in range(n_lo // B, n_hi // B + 1)
             for j in range(m_lo // B, m_hi // B + 1)]
    found = np.concatenate(parts) if parts else np.empty((0, 2), np.int64)
    keep = (found[:, 0] >= n_lo) & (found[:, 0] <= n_hi) & (found[:, 1] >= m_lo) & (found[:, 1] <= m_hi)
    found = found[keep]
    return np.ascontiguousarray(found[np.lexsort((found[:, 0], found[:, 1]))])


def tile_range(M, r_lo, r_hi, t_lo, t_hi) -> tuple[int, int, int, int]:
    """(a0, a1, b0, b1): the distortion tiles a0..a1 (along R) × b0..b1 (along T) covering
    [r_lo, r_hi] × [t_lo, t_hi] µm."""
    span = K.TILE * M[K.PITCH] / K.GRID_PER_PITCH
    return math.floor(r_lo / span), math.floor(r_hi / span), math.floor(t_lo / span), math.floor(t_hi / span)


def _patch(seed, M, r_lo, r_hi, t_lo, t_hi, stats):
    """Distortion grid covering [r_lo, r_hi] × [t_lo, t_hi] µm, assembled from cached tiles."""
    a0, a1, b0, b1 = tile_range(M, r_lo, r_hi, t_lo, t_hi)
    patch = np.empty(((a1 - a0 + 1) * K.TILE + 1, (b1 - b0 + 1) * K.TILE + 1, 2))
    key = M.tobytes()
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            (tile, tstats), made = _TILES.get(int(seed), key, a, b)
            if made:
                stats += tstats
            i, j = (a - a0) * K.TILE, (b - b0) * K.TILE
            patch[i:i + K.TILE + 1, j:j + K.TILE + 1] = tile
    return patch, a0 * K.TILE, b0 * K.TILE


def _plies(p: WoodParams, seed: int, t_lo_um: float, t_hi_um: float):
    """(index, cos, sin, ΔR, ΔT, ΔL, seed, T range [µm]) of the plies crossing [t_lo, t_hi]."""
    if p.laminate is None:
        yield 0, 1.0, 0.0, 0.0, 0.0, 0.0, seed, -math.inf, math.inf
        return
    th = p.ply_thickness_um
    for idx in range(math.floor(t_lo_um / th), math.floor(t_hi_um / th) + 1):
        angle = math.radians(p.laminate[idx % len(p.laminate)])
        ply_seed = int(np.uint64(_rng.hash5(np.uint64(seed), _rng.PLY, idx, 0, 0)))
        offsets = [1000.0 * _rng.uniform(np.uint64(seed), _rng.PLY, idx, 1, q) for q in range(3)]
        cs, sn = math.cos(angle), math.sin(angle)
        if abs(sn) < 1e-15:
            sn = 0.0
        yield idx, cs, sn, offsets[0], offsets[1], offsets[2], ply_seed, idx * th, (idx + 1) * th


def generate_block(
    params: WoodParams,
    grid: Grid,
    start: tuple[int, int, int],
    shape: tuple[int, int, int],
    *,
    seed: int,
    stats: np.ndarray | None = None,
    need: np.ndarray | None = None,
) -> np.ndarray:
    """Generate voxels ``[start, start + shape)`` of the volume on ``grid``.

    Parameters
    ----------
    params : WoodParams
        Validated microstructure parameters.
    grid : Grid
        Voxel size [µm] and origin [µm] of the volume; voxel (i, j, k) has its
        centre at ``origin + (index + 0.5) * voxel``.
    start, shape : tuple of 3 int
        Global voxel index of the block's first voxel, and the block shape.
    seed : int
        Non-negative seed; every random value is a hash of it.
    stats : ndarray of int64, optional
        Work counters (see ``STAT_NAMES``) incremented in place.
    need : ndarray of uint8, optional
        Only the voxels (i, j, k) of the block with ``need[i // s, j // s, k // s]`` nonzero are
        generated, ``s`` = ``shape[0] // need.shape[0]`` (the same along every axis); the others
        are 0.  Those generated are the same as without ``need``.

    Returns
    -------
    ndarray of shape (R, T, L), uint8
        1 = cell wall, 0 = polymer.
    """
    if stats is None:
        stats = np.zeros(N_STATS, np.int64)
    M = model_constants(params)
    v = grid.voxel_um
    org = np.asarray(grid.origin_um, dtype=np.float64)
    gstart = np.asarray(start, dtype=np.int64)
    nR, nT, nL = shape
    if need is None:
        buf = np.empty((nR, nT, nL), np.uint8)
        need, ns = np.zeros((1, 1, 1), np.uint8), 0
    else:
        buf = np.zeros((nR, nT, nL), np.uint8)
        need = np.ascontiguousarray(need, np.uint8)
        ns = nR // need.shape[0] if need.ndim == 3 and need.shape[0] > 0 else 0
        if ns < 1 or any(n != m * ns for n, m in zip(shape, need.shape)):
            raise ValueError(f"need of shape {need.shape} does not divide the block {tuple(shape)}")
    lo = org + gstart * v
    hi = org + (gstart + np.asarray(shape)) * v
    t_centres = org[1] + (gstart[1] + np.arange(nT) + 0.5) * v
    c = params.node_pitch_um
    for _, cs, sn, oR, oT, oL, ply_seed, t0, t1 in _plies(params, seed, lo[1], hi[1]):
        sel = np.nonzero((t_centres >= t0) & (t_centres < t1))[0]
        if sel.size == 0:
            continue
        j_lo, j_hi = int(sel[0]), int(sel[-1]) + 1
        corners_r = [cs * r + sn * l + oR for r in (lo[0], hi[0]) for l in (lo[2], hi[2])]
        r_lo, r_hi = min(corners_r), max(corners_r)
        tt_lo, tt_hi = t_centres[j_lo] + oT, t_centres[j_hi - 1] + oT
        pseed = np.uint64(ply_seed)
        patch, gi0, gj0 = _patch(pseed, M, r_lo - 1.0, r_hi + 1.0, tt_lo - 1.0, tt_hi + 1.0, stats)
        dmax = float(np.abs(patch).max())
        margin = dmax + max(c, 0.5 * params.ray_seriate * (params.ray_cell_width_um
                                                            + params.wall_thickness_um))
        vessels = np.empty((4096, 5), np.int64)
        nv = vessels_in_region(
            pseed, M,
            math.floor((r_lo - margin) / c) - 6, math.ceil((r_hi + margin) / c) + 6,
            math.floor((tt_lo - margin) / c) - 6, math.ceil((tt_hi + margin) / c) + 6,
            vessels,
        )
        fill_block(buf, pseed, M, gstart, org, v, j_lo, j_hi,
                     np.array([cs, sn, oR, oT, oL]), patch, gi0, gj0, dmax,
                     vessels[:max(nv, 1)], nv, stats, need, ns)
    return buf
