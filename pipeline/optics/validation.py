"""Exact references for the tracer (SPEC.md §8): a voxelised rod and its deflection law."""

from __future__ import annotations

import numpy as np


def voxelised_rod(radius: float, centre: tuple[float, float], size: int, length: int = 32) -> np.ndarray:
    """A rod (axis along L) of ``radius`` voxels: 1 inside, 0 outside.

    Returns an array of shape (size, size, length), axes [R, T, L]; a voxel is
    wall when its centre lies inside the circle centred at ``centre`` (R, T).
    """
    i, j = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    disk = ((i - centre[0]) ** 2 + (j - centre[1]) ** 2) < radius * radius
    return np.repeat(disk.astype(np.uint8)[:, :, None], length, axis=2)


def rod_deflection_deg(b, radius: float, m: float) -> np.ndarray:
    """Signed exit angle θ_R [degree] of a ray at impact parameter b crossing a rod.

    D = 2(asin(b/R) − asin(b/(mR))) for relative index m; a denser rod (m > 1)
    is a converging lens, so rays above the axis (b > 0) turn toward −R.
    """
    b = np.asarray(b, dtype=np.float64)
    return -np.degrees(2.0 * (np.arcsin(b / radius) - np.arcsin(b / (m * radius))))
