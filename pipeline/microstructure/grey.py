"""Grey-level scans of generated wood: what a µCT would record of a wood of known truth
(docs/methods.md#iso-surfaces).

Each voxel holds the fraction of its volume that is wall (the partial-volume effect), measured by
generating the wood on voxels ``supersample`` times smaller and averaging them; then, as a
scanner's, optionally a Gaussian point-spread function of ``blur_um`` (σ) and Gaussian noise of
``noise`` (standard deviation, in the fraction's units) drawn from the counter-based stream of
each voxel, so a scan is the same whatever its chunking.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..params import Grid, ParameterError, WoodParams, check_voxel
from ..rng import SCAN_NOISE, normal
from .model import generate_block

SLAB_FINE_VOXELS = 32e6  # fine voxels generated at a time (memory: one byte each)


def grey_volume(params: WoodParams, grid: Grid, *, seed: int, supersample: int = 4, blur_um: float = 0.0,
                noise: float = 0.0, noise_seed: int = 0) -> np.ndarray:
    """The grey-level scan (float32, R × T × L, the wall fraction of each voxel of ``grid``) of the
    wood of ``params`` and ``seed``: ``supersample``³ fine voxels a voxel, then the blur and the
    noise."""
    if isinstance(supersample, bool) or not isinstance(supersample, int) or not 1 <= supersample <= 16:
        raise ParameterError(f"`supersample` must be an integer in [1, 16], got {supersample!r}")
    _check_degradation(blur_um, noise)  # before the generation, not after
    s = supersample
    fine = Grid(tuple(n * s for n in grid.shape), grid.voxel_um / s, grid.origin_um)
    check_voxel(fine.voxel_um, params)
    nr, nt, nl = grid.shape
    out = np.empty(grid.shape, np.float32)
    per_l = max(1, int(SLAB_FINE_VOXELS // (nr * nt * s ** 3)))  # coarse L layers a slab
    for k0 in range(0, nl, per_l):
        k1 = min(nl, k0 + per_l)
        block = generate_block(params, fine, (0, 0, k0 * s), (nr * s, nt * s, (k1 - k0) * s), seed=seed)
        out[:, :, k0:k1] = block.reshape(nr, s, nt, s, k1 - k0, s).mean(axis=(1, 3, 5), dtype=np.float64)
    return degrade(out, grid.voxel_um, blur_um=blur_um, noise=noise, noise_seed=noise_seed)


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
        _add_noise(out, float(noise), np.uint64(noise_seed))
    return out


def _check_degradation(blur_um, noise) -> None:
    for name, v in (("blur_um", blur_um), ("noise", noise)):
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ParameterError(f"`{name}` must be a number >= 0, got {name}={v!r}")


@njit(cache=True, nogil=True)
def _add_noise(vol, sigma, seed):
    for i in range(vol.shape[0]):
        for j in range(vol.shape[1]):
            for k in range(vol.shape[2]):
                vol[i, j, k] += sigma * normal(seed, SCAN_NOISE, i, j, k)
