"""Exact references for the tracer (SPEC.md §8): voxelised rods, tubes and flat sheets and their
deflection laws."""

from __future__ import annotations

import math

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


def voxelised_tube(radius: float, wall: float, centre: tuple[float, float], size: int,
                   length: int = 32) -> np.ndarray:
    """A tube (axis along L) of outer ``radius`` and ``wall`` thickness [voxels]: 1 in its wall.

    Returns an array of shape (size, size, length), axes [R, T, L]; a voxel is
    wall when its centre lies between the circles of radii radius − wall and
    radius centred at ``centre`` (R, T).
    """
    i, j = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    r2 = (i - centre[0]) ** 2 + (j - centre[1]) ** 2
    ring = (r2 < radius * radius) & (r2 >= (radius - wall) ** 2)
    return np.repeat(ring.astype(np.uint8)[:, :, None], length, axis=2)


def tube_deflection_deg(b, radius: float, wall: float, m: float) -> np.ndarray:
    """Signed exit angle θ_R [degree] of a ray at impact parameter b crossing a tube.

    A ray that reaches the lumen (|b| < Ri = radius − wall) refracts at four
    concentric circles: D = 2(asin(b/R) − asin(b/(mR))) − 2(asin(b/Ri) − asin(b/(mRi))),
    the rod's deflection less that of a rod of the lumen's radius; one that
    passes by the lumen (|b| > m·Ri) is deflected like a rod.  Between the two,
    the ray is totally reflected at the lumen and the result is NaN.
    """
    b = np.asarray(b, dtype=np.float64)
    inner = radius - wall
    ab = np.abs(b)
    lumen = ab < inner
    d = rod_deflection_deg(b, radius, m)
    d = np.where(lumen, d - rod_deflection_deg(np.where(lumen, b, 0.0), inner, m), d)
    return np.where((ab >= inner) & (ab <= m * inner), np.nan, d)


def voxelised_sheet(tilt_deg: float, offset: float, thickness: float = 1.0, size: int = 128,
                    length: int = 32, phase: int = 1) -> np.ndarray:
    """A flat sheet of ``phase`` in the other, ``thickness`` voxels thick, tilted by
    ``tilt_deg`` from the R axis in the R-T plane (its normal is tilt_deg from +T).

    Returns an array of shape (size, size, length), axes [R, T, L]; a voxel is in
    the sheet when its centre lies between the planes at distances ``offset`` and
    offset + thickness from the centre of the R-T square.  A ray crossing a flat
    parallel sheet leaves it parallel to itself: no deflection.
    """
    a = math.radians(tilt_deg)
    i, j = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    s = (i - size / 2) * -math.sin(a) + (j - size / 2) * math.cos(a) - offset
    inside = (s >= 0) & (s < thickness)
    return np.repeat((inside if phase == 1 else ~inside).astype(np.uint8)[:, :, None], length, axis=2)
