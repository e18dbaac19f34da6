"""Grey-level scans of generated wood: what a µCT would record of a wood of known truth
(docs/methods.md#iso-surfaces).

Each voxel holds the fraction of its volume that is wall (the partial-volume effect), measured by
generating the wood on voxels ``supersample`` times smaller and averaging them; then, as a
scanner's, optionally a Gaussian point-spread function of ``blur_um`` (σ) and Gaussian noise of
``noise`` (standard deviation, in the fraction's units) drawn from the counter-based stream of
each voxel, so a scan is the same whatever its chunking.

:class:`LazyGreyScan` is the same scan as an array read in parts: each part is generated (with the
halo its blur needs) when it is first read, bit for bit the part of :func:`grey_volume`'s scan, so
that a scan millimetres wide costs only what a trace reads of it.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from ..params import Grid, ParameterError, WoodParams, check_voxel
from ..rng import SCAN_NOISE, normal
from ._grey_uniform import UniformVoxels, for_scan
from .model import generate_block
from ..lru import ByteLRU

SLAB_FINE_VOXELS = 32e6  # fine voxels generated at a time (memory: one byte each)
TILE = 16  # LazyGreyScan generates tiles of TILE³ voxels (16: a third less generated than 32 around rays)
TILE_CACHE_BYTES = 256 * 2 ** 20  # the tiles a LazyGreyScan keeps
TRUNCATE = 4.0  # the blur's kernel reaches TRUNCATE σ (scipy's default)


def grey_volume(params: WoodParams, grid: Grid, *, seed: int, supersample: int = 4, blur_um: float = 0.0,
                noise: float = 0.0, noise_seed: int = 0) -> np.ndarray:
    """The grey-level scan (float32, R × T × L, the wall fraction of each voxel of ``grid``) of the
    wood of ``params`` and ``seed``: ``supersample``³ fine voxels a voxel, then the blur and the
    noise."""
    fine = _checked(params, grid, supersample, blur_um, noise)  # before the generation, not after
    out = _clean(params, fine, supersample, seed, (0, 0, 0), grid.shape, for_scan(params, grid, seed, supersample))
    return degrade(out, grid.voxel_um, blur_um=blur_um, noise=noise, noise_seed=noise_seed)


def _checked(params, grid, supersample, blur_um, noise) -> Grid:
    """The fine grid of a scan of ``grid``, after checking the scan's options."""
    if isinstance(supersample, bool) or not isinstance(supersample, int) or not 1 <= supersample <= 16:
        raise ParameterError(f"`supersample` must be an integer in [1, 16], got {supersample!r}")
    _check_degradation(blur_um, noise)
    fine = Grid(tuple(n * supersample for n in grid.shape), grid.voxel_um / supersample, grid.origin_um)
    check_voxel(fine.voxel_um, params)
    return fine


def _clean(params, fine: Grid, s: int, seed: int, first, shape, uniform: UniformVoxels | None = None) -> np.ndarray:
    """The wall fractions of the voxels ``first`` + [0, ``shape``) of the scan whose fine grid is
    ``fine`` (``s``³ fine voxels a voxel), generated in slabs along L; with ``uniform``, only the
    voxels it does not prove to lie in one phase are supersampled (the same numbers)."""
    nr, nt, nl = shape
    i0, j0, k0 = first
    out = np.empty(shape, np.float32)
    per_l = max(1, int(SLAB_FINE_VOXELS // (nr * nt * s ** 3)))  # voxel layers along L a slab
    for a in range(0, nl, per_l):
        b = min(nl, a + per_l)
        start, size = (i0 * s, j0 * s, (k0 + a) * s), (nr * s, nt * s, (b - a) * s)
        if uniform is None:
            block = generate_block(params, fine, start, size, seed=seed)
            out[:, :, a:b] = block.reshape(nr, s, nt, s, b - a, s).mean(axis=(1, 3, 5), dtype=np.float64)
            continue
        known = uniform.decide((i0, j0, k0 + a), (nr, nt, b - a))
        need = np.isnan(known)
        if need.any():
            block = generate_block(params, fine, start, size, seed=seed, need=need.view(np.uint8))
            part = block.reshape(nr, s, nt, s, b - a, s).mean(axis=(1, 3, 5), dtype=np.float64)
            known[need] = part[need]
        out[:, :, a:b] = known
    return out


def degrade(scan: np.ndarray, voxel_um: float, *, blur_um: float = 0.0, noise: float = 0.0,
            noise_seed: int = 0) -> np.ndarray:
    """``scan`` as a scanner records it: blurred by a Gaussian of σ ``blur_um``, then with Gaussian noise
    of standard deviation ``noise`` from each voxel's own stream (a new array; ``scan`` is kept)."""
    _check_degradation(blur_um, noise)
    out = np.array(scan, np.float32, copy=True)
    if blur_um > 0:
        from scipy.ndimage import gaussian_filter

        out = gaussian_filter(out, sigma=blur_um / voxel_um, mode="nearest").astype(np.float32)
    if noise > 0:
        _add_noise(out, float(noise), np.uint64(noise_seed), 0, 0, 0)
    return out


def gaussian_part(read, lo, hi, shape, sigma: float, dtype) -> np.ndarray:
    """Voxels [lo, hi) of a volume of ``shape`` filtered by a Gaussian of ``sigma`` voxels, as the
    same part of the whole volume filtered (scipy's ``gaussian_filter``, mode "nearest"): read with
    the halo the kernel reaches (scipy's radius, ``int(TRUNCATE·σ + 0.5)``, clipped to the volume)
    by ``read(wide_lo, wide_hi)`` -> array in any data type, filtered in ``dtype``, cut to [lo, hi)."""
    from scipy.ndimage import gaussian_filter

    halo = int(TRUNCATE * sigma + 0.5)
    wlo = [max(a - halo, 0) for a in lo]
    whi = [min(b + halo, n) for b, n in zip(hi, shape)]
    part = gaussian_filter(np.asarray(read(wlo, whi)).astype(dtype), sigma=sigma, mode="nearest",
                           truncate=TRUNCATE)
    return np.ascontiguousarray(part[tuple(slice(a - w, b - w) for a, b, w in zip(lo, hi, wlo))])


def full_region(region) -> tuple:
    """An index of a 3-D array as a tuple of three entries (missing trailing axes: whole)."""
    region = region if isinstance(region, tuple) else (region,)
    return region + (slice(None),) * (3 - len(region))


def _check_degradation(blur_um, noise) -> None:
    for name, v in (("blur_um", blur_um), ("noise", noise)):
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ParameterError(f"`{name}` must be a number >= 0, got {name}={v!r}")


@njit(cache=True, nogil=True)
def _add_noise(vol, sigma, seed, i0, j0, k0):
    """Each voxel's noise from its own stream, keyed by its index in the whole scan (``vol`` starts
    at voxel (i0, j0, k0))."""
    for i in range(vol.shape[0]):
        for j in range(vol.shape[1]):
            for k in range(vol.shape[2]):
                vol[i, j, k] += sigma * normal(seed, SCAN_NOISE, i0 + i, j0 + j, k0 + k)


class LazyGreyScan:
    """:func:`grey_volume`'s scan of ``grid`` as an array whose parts are generated when read
    (``scan[i0:i1, j0:j1, k0:k1]``, float32), in tiles of :data:`TILE`³ voxels kept up to
    :data:`TILE_CACHE_BYTES`; each part is bit for bit the same part of the whole scan (a blurred
    tile is generated with the halo its kernel reaches).  ``tiles_generated`` counts the tiles made,
    ``generate_s`` the CPU seconds they took; ``cache_bytes`` bounds the tiles kept."""

    dtype = np.dtype(np.float32)

    def __init__(self, params: WoodParams, grid: Grid, *, seed: int, supersample: int = 4, blur_um: float = 0.0,
                 noise: float = 0.0, noise_seed: int = 0, cache_bytes: int = TILE_CACHE_BYTES):
        self.cache_bytes = int(cache_bytes)
        self.fine = _checked(params, grid, supersample, blur_um, noise)
        self.params, self.grid, self.seed, self.s = params, grid, seed, supersample
        self.blur_um, self.noise, self.noise_seed = float(blur_um), float(noise), noise_seed
        self.shape = tuple(int(n) for n in grid.shape)
        self.ndim = 3
        self.tiles = ByteLRU(self.cache_bytes)
        self.tiles_generated = 0
        self.generate_s = 0.0  # CPU seconds spent generating tiles
        self.uniform = for_scan(params, grid, seed, supersample)

    def _tile(self, key) -> np.ndarray:
        kept = self.tiles.get(key)
        if kept is not None:
            return kept
        t0 = time.process_time()
        lo = [k * TILE for k in key]
        hi = [min(a + TILE, n) for a, n in zip(lo, self.shape)]

        def clean(a, b):
            return _clean(self.params, self.fine, self.s, self.seed, a, tuple(y - x for x, y in zip(a, b)), self.uniform)
        if self.blur_um > 0:
            part = gaussian_part(clean, lo, hi, self.shape, self.blur_um / self.grid.voxel_um, np.float32)
        else:
            part = clean(lo, hi)
        if self.noise > 0:
            _add_noise(part, self.noise, np.uint64(self.noise_seed), *lo)
        self.tiles.put(key, part, part.nbytes)
        self.tiles_generated += 1
        self.generate_s += time.process_time() - t0
        return part

    def __getitem__(self, region) -> np.ndarray:
        region = full_region(region)
        spans = [sl.indices(n) for sl, n in zip(region, self.shape)]
        lo = [a for a, _, _ in spans]
        hi = [max(a, b) for a, b, _ in spans]
        out = np.empty([b - a for a, b in zip(lo, hi)], np.float32)
        for ti in range(lo[0] // TILE, -(-hi[0] // TILE)):
            for tj in range(lo[1] // TILE, -(-hi[1] // TILE)):
                for tk in range(lo[2] // TILE, -(-hi[2] // TILE)):
                    t = self._tile((ti, tj, tk))
                    a = [max(l, q * TILE) for l, q in zip(lo, (ti, tj, tk))]
                    b = [min(h, q * TILE + TILE) for h, q in zip(hi, (ti, tj, tk))]
                    out[tuple(slice(x - l, y - l) for x, y, l in zip(a, b, lo))] = \
                        t[tuple(slice(x - q * TILE, y - q * TILE) for x, y, q in zip(a, b, (ti, tj, tk)))]
        return out[tuple(slice(None, None, st) for _, _, st in spans)]

    def sample(self) -> np.ndarray:
        """Grey levels to choose and check a threshold from: a box of at most 64 × 128 × 64 voxels at
        the middle of the R-L face (reading the whole scan would generate all of it)."""
        box = [min(n, m) for n, m in zip(self.shape, (64, 128, 64))]
        lo = [(n - b) // 2 if q != 1 else 0 for q, (n, b) in enumerate(zip(self.shape, box))]
        return self[tuple(slice(a, a + b) for a, b in zip(lo, box))]
