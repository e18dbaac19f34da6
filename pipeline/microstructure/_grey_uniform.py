"""Voxels of a grey-level scan that lie wholly in one phase, proven without supersampling them
(docs/methods.md#iso-surfaces).

A voxel's wall fraction is the mean of its ``s``³ fine voxels.  Where the model's clearance at a
point (:func:`~pipeline.microstructure.surface.evaluate`: the least distance any of its primitives
can be from it, a proven bound) exceeds the distance to the farthest fine voxel centre of a box
of voxels around it, no fine voxel of the box can be in the other phase: each of them is the
point's phase, and their mean is that phase exactly (0.0 or 1.0), the same number supersampling
gives.  Boxes of 4³, then 2³ voxels, then single voxels are tried; only the voxels left
undecided are supersampled.  It pays where a point of the generator costs more than an
evaluation shared by many voxels: balsa's polygon cells (docs/performance.md, "Grey scans").
"""

from __future__ import annotations

import collections
import math
import threading

import numpy as np

from . import _constants as K
from ._surface_cells import new_cache
from .model import model_constants
from .region import context_tuple, phases, region_context

SUPER_UM = 64.0  # a context covers whole squares of this side in R and L (and the grid's T)
CONTEXTS = 8  # contexts kept
SLACK = 1e-9  # [µm] added to every radius, with a relative 1e-9: the rounding of the centres
_OFFSETS = {side: np.array(list(np.ndindex(side, side, side)), np.int64) for side in (1, 2, 4)}


def applies(params, grid) -> bool:
    """Whether scans of this wood on ``grid`` are made with proven voxels: polygonal cells (where
    a point of the generator is dear) and a grid inside T >= 0 (the plies the model lists)."""
    return model_constants(params)[K.SHAPE] == 1.0 and grid.origin_um[1] >= 0.0


def for_scan(params, grid, seed: int, supersample: int) -> UniformVoxels | None:
    """The proof for the scan of ``grid`` where it applies (:func:`applies`), else None."""
    return UniformVoxels(params, grid, seed, supersample) if applies(params, grid) else None


class UniformVoxels:
    """For parts of the scan of ``grid`` (voxels ``supersample`` times the fine grid's), the wall
    fraction of every voxel proven to lie in one phase, NaN elsewhere."""

    def __init__(self, params, grid, seed: int, supersample: int):
        self.params, self.grid, self.seed, self.s = params, grid, int(seed), int(supersample)
        self.t_max = grid.origin_um[1] + grid.shape[1] * grid.voxel_um
        rotated = params.laminate is not None and any(math.sin(math.radians(a)) != 0.0 for a in params.laminate)
        # A rotated ply's fine voxels are classified at L' rounded to half a fine voxel: moved by a quarter.
        self.margin = SLACK + (grid.voxel_um / self.s / 4.0 if rotated else 0.0)
        self.contexts: collections.OrderedDict = collections.OrderedDict()
        self._local = threading.local()
        self._lock = threading.Lock()
        self.evaluations = 0  # points evaluated so far

    def _context(self, r_lo, r_hi, l_lo, l_hi) -> tuple:
        key = tuple(math.floor(x / SUPER_UM) for x in (r_lo, r_hi, l_lo, l_hi))
        with self._lock:
            ctx = self.contexts.get(key)
            if ctx is not None:
                self.contexts.move_to_end(key)
                return ctx
        r = (key[0] * SUPER_UM - 2.0, (key[1] + 1) * SUPER_UM + 2.0)
        l_ = (key[2] * SUPER_UM - 2.0, (key[3] + 1) * SUPER_UM + 2.0)
        ctx = context_tuple(region_context(self.params, self.seed, self.t_max, r, l_, (0.0, self.t_max)))
        with self._lock:
            self.contexts[key] = ctx
            while len(self.contexts) > CONTEXTS:
                self.contexts.popitem(last=False)
        return ctx

    def decide(self, first, shape) -> np.ndarray:
        """float32 ``shape``: voxels ``first`` + [0, ``shape``) of the scan, their wall fraction
        where proven (0.0 or 1.0), NaN where they must be supersampled.  Boxes of 4³ voxels are
        tried at their centres, then the octants of those not proven, then their voxels."""
        h = self.grid.voxel_um
        o = self.grid.origin_um
        lo = np.array([o[q] + first[q] * h for q in range(3)])
        hi = lo + np.asarray(shape) * h
        ctx = self._context(lo[0], hi[0], lo[2], hi[2])
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = new_cache()
        out = np.full(tuple(shape), np.nan, np.float32)
        size = np.asarray(shape, np.int64)
        starts = np.stack(np.meshgrid(*[np.arange(0, n, 4) for n in shape], indexing="ij"), -1).reshape(-1, 3)
        ext = np.minimum(4, size - starts)
        for side in (4, 2, 1):
            if side < 4:  # the parts of the boxes left, of this side
                d = _OFFSETS[2] * side
                starts = (starts[:, None, :] + d[None, :, :]).reshape(-1, 3)
                ext = np.minimum(side, (ends[:, None, :] - starts.reshape(len(ends), 8, 3))).reshape(-1, 3)
                keep = (ext > 0).all(axis=1)
                starts, ext = starts[keep], ext[keep]
            clr = np.empty(len(starts))
            ph = phases(lo + (starts + 0.5 * ext) * h, 0.0, ctx, clearances=clr, cache=cache)
            self.evaluations += len(starts)
            radius = 0.5 * h * np.sqrt((ext.astype(np.float64) ** 2).sum(axis=1))
            ok = (ph != 255) & (clr > radius * (1.0 + SLACK) + self.margin)
            offsets = _OFFSETS[side]  # every voxel of a box of this side, those past its extent masked
            inside = (offsets[None, :, :] < ext[ok][:, None, :]).all(axis=2)
            idx = (starts[ok][:, None, :] + offsets[None, :, :])[inside]
            out[idx[:, 0], idx[:, 1], idx[:, 2]] = np.repeat(ph[ok], inside.sum(axis=1))
            starts, ext = starts[~ok], ext[~ok]
            ends = starts + ext
        return out
