"""A grey-level scan traced on its iso-surface (method ``iso``, docs/methods.md#iso-surfaces).

A µCT or FIB-SEM volume records, in each voxel, how much wall it holds; binarising it throws away
where between two voxel centres the wall really is.  :class:`IsoVolume` keeps it: the field is the
trilinear interpolation of the grey levels between voxel centres, the wall is where it exceeds a
threshold (given, or Otsu's from the data), crossings are roots of the interpolant along each ray
(:mod:`pipeline.optics._iso_march`) and normals its gradient.  It is a surface medium: the faces
are handled by :func:`pipeline.optics.faces.through_faces` as for every medium.
"""

from __future__ import annotations

import math

import numpy as np

from ..params import ParameterError
from ._iso_march import march

OTSU_BINS = 256


def otsu_threshold(values: np.ndarray, bins: int = OTSU_BINS) -> float:
    """Otsu's threshold of ``values``: the grey level between the two classes of largest
    between-class variance, at the edge of the bin it ends (one of ``bins`` over the data's range)."""
    v = np.asarray(values, np.float64).ravel()
    lo, hi = float(v.min()), float(v.max())
    if not lo < hi:
        raise ParameterError(f"`volume` holds one grey level ({lo:g}): no threshold separates wall from polymer")
    counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
    p = counts / counts.sum()
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(p)
    m = np.cumsum(p * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (m[-1] * w0 - m) ** 2 / (w0 * (1.0 - w0))
    between[~np.isfinite(between)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


class IsoVolume:
    """A grey-level volume (R, T, L) of ``voxel_um`` voxels, its corner at the origin, as the
    surface of level ``iso`` (None: Otsu's threshold of the data); wall above it."""

    medium_kind = "fields"

    def __init__(self, array, *, voxel_um: float, iso: float | None = None):
        if not (isinstance(voxel_um, (int, float)) and math.isfinite(voxel_um) and voxel_um > 0):
            raise ParameterError(f"`voxel_um` must be > 0 µm, got voxel_um={voxel_um!r}")
        if np.ndim(array) != 3 or min(np.shape(array)) < 1:
            raise ParameterError(f"`volume` must be a 3-D array (R, T, L) of grey levels, got shape {np.shape(array)}")
        data = np.ascontiguousarray(np.asarray(array), dtype=np.float64)
        bad = ~np.isfinite(data)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ParameterError(f"`volume` must hold finite grey levels, got {int(bad.sum())} that are not "
                                 f"(the first at voxel {first})")
        lo, hi = float(data.min()), float(data.max())
        self.iso_from = "given"
        if iso is None:
            iso, self.iso_from = otsu_threshold(data), "otsu"
        if not (isinstance(iso, (int, float)) and math.isfinite(iso) and lo <= iso < hi):
            raise ParameterError(f"`iso` must lie in the volume's grey levels [{lo:g}, {hi:g}), got iso={iso!r}")
        self.data = data
        self.voxel_um = float(voxel_um)
        self.iso = float(iso)
        self.shape = data.shape
        self.thickness_um = data.shape[1] * self.voxel_um

    def field(self, points_um) -> np.ndarray:
        """The interpolated grey level at ``points_um`` (N, 3) [µm] (constant beyond the outermost
        voxel centres)."""
        p = np.asarray(points_um, np.float64).reshape(-1, 3) / self.voxel_um - 0.5
        i0 = np.floor(p).astype(np.int64)
        f = p - i0
        out = np.zeros(len(p))
        for a in (0, 1):
            for b in (0, 1):
                for e in (0, 1):
                    idx = [np.clip(i0[:, q] + o, 0, self.shape[q] - 1) for q, o in enumerate((a, b, e))]
                    w = ((f[:, 0] if a else 1 - f[:, 0]) * (f[:, 1] if b else 1 - f[:, 1])
                         * (f[:, 2] if e else 1 - f[:, 2]))
                    out += w * self.data[idx[0], idx[1], idx[2]]
        return out

    def entry_phase(self, origins_um) -> np.ndarray:
        """1 (wall) where the field at the entry point exceeds ``iso``, 0 elsewhere; 255 outside
        the volume's R-L face."""
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        inside = ((pos[:, 0] >= 0) & (pos[:, 0] <= self.shape[0] * self.voxel_um)
                  & (pos[:, 2] >= 0) & (pos[:, 2] <= self.shape[2] * self.voxel_um))
        return np.where(inside, (self.field(pos) > self.iso).astype(np.uint8), 255).astype(np.uint8)

    def march_walls(self, origins_um, directions, *, n_wall: float, n_poly: float, max_events: int,
                    fresnel: bool = False, seed: int = 0, ray_ids=None) -> dict:
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        n = len(pos)
        ids = np.arange(n, dtype=np.int64) if ray_ids is None else np.asarray(ray_ids, np.int64)
        phase = self.entry_phase(pos)
        out = {"position": np.empty((n, 3)), "direction": np.empty((n, 3)), "status": np.empty(n, np.int64),
               "events": np.empty(n, np.int64), "path": np.empty(n), "medium": np.empty(n, np.uint8),
               "cells": np.empty(n, np.int64), "flat_normals": np.empty(n, np.int64)}
        march(self.data, self.voxel_um, self.iso, pos, np.ascontiguousarray(directions, np.float64), ids,
              phase, float(n_wall), float(n_poly), int(max_events), bool(fresnel), np.uint64(seed), *out.values())
        return out
