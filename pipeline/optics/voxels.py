"""The voxel backend: a beam traced through a two-phase voxel volume (methods paper, fast and
accurate; docs/methods.md#voxel-methods).

:func:`trace_beam` pages chunks in as rays need them, runs the Numba kernel,
answers paper-mode SVM requests, and returns a :class:`RayResult` with one
entry per ray, positions and lengths in voxels.  No ray is ever dropped: each
ends transmitted, reflected back out, out through a side, or trapped.
:func:`trace_voxels` is the same in µm, the form the tracer interface
(:mod:`pipeline.optics.trace`) calls.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from ..params import ParameterError
from . import _march as K
from ._normals import NEWTON_REACH, window_scratch
from ._packing import OUTSIDE, mark_boxes, phases_at
from .interface import (NEEDS_CHUNK, NEEDS_NORMAL, REFLECTED, SIDE, TIR_EXIT, TRANSMITTED, enter_from,
                        leave_into_air)
from .rays import Beam, RayResult
from .settings import PRESETS, Optics, TraceSettings
from .sources import ChunkCache


def svm_normal(box: np.ndarray, centre: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, bool]:
    """The paper's interface normal: that of the plane a linear SVM fits between the
    wall and polymer voxels of a small box.

    Parameters
    ----------
    box : ndarray of shape (n, n, n), uint8
        The voxels around the crossing (1 = wall), the paper's 6 × 6 × 6.
    centre : ndarray of shape (3,)
        The crossing point [voxels].
    lo : ndarray of shape (3,), int
        The index of ``box[0, 0, 0]`` in the volume.

    Returns
    -------
    normal : ndarray of shape (3,)
        Unit normal pointing into the wall, or zeros for a one-phase box.
    ok : bool
        False for a one-phase box (no plane to fit).
    """
    from sklearn.svm import SVC

    labels = box.reshape(-1)
    if labels.min() == labels.max():
        return np.zeros(3), False
    g = np.stack(np.meshgrid(*[np.arange(n) for n in box.shape], indexing="ij"), axis=-1)
    pts = (g.reshape(-1, 3) + lo + 0.5) - centre
    clf = SVC(kernel="linear", C=1.0)
    clf.fit(pts, labels)
    w = clf.coef_[0]
    norm = np.linalg.norm(w)
    if not norm > 0:
        return np.zeros(3), False
    return w / norm, True


def _unique_rows(idx: np.ndarray) -> np.ndarray:
    """The distinct rows of an (N, 3) integer array, sorted (np.unique(axis=0), but fast)."""
    if len(idx) == 0:
        return idx.reshape(0, 3)
    lo = idx.min(axis=0)
    ext = idx.max(axis=0) - lo + 1
    rel = idx - lo
    key = np.unique((rel[:, 0] * ext[1] + rel[:, 1]) * ext[2] + rel[:, 2])
    out = np.empty((key.size, 3), np.int64)
    out[:, 2] = key % ext[2]
    key //= ext[2]
    out[:, 1] = key % ext[1]
    out[:, 0] = key // ext[1]
    return out + lo


def _chunks_of_boxes(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The distinct chunks (rows, sorted) of the boxes of chunks [lo, hi] (inclusive, (N, 3) each),
    leaving out those before the entrance face (T < 0)."""
    lo = np.ascontiguousarray(lo, np.int64).copy()
    hi = np.ascontiguousarray(hi, np.int64)
    lo[:, 1] = np.maximum(lo[:, 1], 0)
    if len(lo) == 0:
        return lo.reshape(0, 3)
    base = lo.min(axis=0)
    extent = np.maximum(hi.max(axis=0) - base + 1, 1)
    if np.prod(extent) > 1 << 24:
        # Boxes strewn far apart: list them one offset at a time.
        span = (hi - lo).max(axis=0, initial=0)
        parts = []
        for d in itertools.product(*(range(int(s) + 1) for s in span)):
            c = lo + np.asarray(d)
            parts.append(c[np.all(c <= hi, axis=1)])
        return _unique_rows(np.concatenate(parts))
    grid = np.zeros(tuple(extent), np.bool_)
    mark_boxes(lo - base, hi - base, grid)
    return np.argwhere(grid) + base


def trace_beam(source, beam: Beam, *, n_wall: float, n_poly: float,
               settings: TraceSettings = PRESETS["accurate"], seed: int = 0,
               capacity: int = 512, n_outside: float | None = None) -> RayResult:
    """Trace ``beam`` (positions in voxels) through the voxel ``source`` (an ArraySource,
    WoodSource or LatticeSource).

    Parameters
    ----------
    n_wall, n_poly : float
        Refractive indices of the cell wall (phase 1) and polymer (phase 0).
    settings : TraceSettings
        A voxel method's preset and options.
    seed : int
        Seed of the per-ray Fresnel streams.
    capacity : int
        Most chunks held in memory at once.
    n_outside : float, optional
        Refractive index of the medium the beam comes from (1.0: air).  Each
        ray is then refracted at the T = 0 face into the phase of the voxel it
        enters (or reflected, status "reflected", where that is total);
        without it the beam's directions are already inside the sample.
    """
    settings = settings.validate()
    if settings.voxel is None:
        raise ParameterError(f"`method` must be a voxel method to trace voxels, got {settings.method!r}")
    Optics(n_wall, n_poly, n_outside, seed).validate()
    vs = settings.voxel
    cache = ChunkCache(source, capacity=capacity)
    n = len(beam.ray_ids)
    pos = beam.origins.astype(np.float64).copy()
    dirs = beam.unit_directions()
    vox = np.floor(pos).astype(np.int64)
    vox[:, 1] = 0
    pos[:, 1] = 0.0
    status = np.full(n, NEEDS_CHUNK, np.int8)
    events = np.zeros(n, np.int64)
    path = np.zeros(n)
    fallbacks = np.zeros((n, 3), np.int64)
    request = vox // np.asarray(source.chunks)
    normals = np.zeros((n, 4))
    shape = np.asarray(source.shape, np.int64)
    cs = cache.chunk_shape
    method = K.PAPER if settings.method == "paper" else K.EXACT
    reach = (int(math.ceil(vs.radius_vox + NEWTON_REACH)) + 2 if method == K.EXACT
             else vs.svm_box)
    scratch = window_scratch(vs.radius_vox)
    # A ray starts in the phase of the voxel it enters; outside a finite volume it is "side".
    cache.require(_unique_rows(request).tolist())
    medium = np.zeros(n, np.uint8)
    phases_at(cache.bits, cache.table, cache.box, cs, shape, vox, medium)
    status[medium == OUTSIDE] = SIDE
    medium[medium == OUTSIDE] = 0
    n_entry = np.where(medium == 1, n_wall, n_poly)
    if n_outside is not None:
        tir = enter_from(dirs, n_entry, float(n_outside)) == REFLECTED
        status[tir & (status == NEEDS_CHUNK)] = REFLECTED
    entered = dirs.copy()
    while True:
        K.trace(pos, dirs, medium, vox, status, events, path, fallbacks, request, normals,
                beam.ray_ids, cache.bits, cache.masks, cache.table, cache.box, cs, shape, method,
                vs.step_vox, vs.sigma_vox, vs.radius_vox, vs.newton,
                vs.refit, n_wall, n_poly, settings.fresnel, np.uint64(seed), settings.max_events,
                *scratch)
        waiting = np.flatnonzero(status == NEEDS_CHUNK)
        asking = np.flatnonzero(status == NEEDS_NORMAL)
        if waiting.size == 0 and asking.size == 0:
            break
        if waiting.size:
            # Keep every chunk that a live ray's normal window may read, or rays
            # near chunk borders would evict each other's chunks forever.
            live = (vox if method == K.EXACT else np.floor(pos).astype(np.int64))[status >= NEEDS_CHUNK]
            # The chunks each live ray's window [x - reach, x + reach] spans.
            keep = map(tuple, _chunks_of_boxes((live - reach) // cs, (live + reach) // cs).tolist())
            cache.require(_unique_rows(request[waiting]).tolist(), keep=set(keep))
        half = vs.svm_box // 2
        for r in asking:
            centre = pos[r]
            lo = np.floor(centre).astype(np.int64) - (half - 1)
            box = cache.voxels(lo, (vs.svm_box,) * 3)
            w, ok = svm_normal(box, centre, lo)
            normals[r, :3] = w
            normals[r, 3] = 1.0 if ok else 0.0
    loads = cache.loads
    cache.release()  # its buffers serve the next trace of this process
    exit_dirs = dirs.copy()
    incident = entered
    if settings.exit == "air":
        done = status == TRANSMITTED
        exit_dirs, tir = leave_into_air(dirs, np.where(medium == 1, n_wall, n_poly), done)
        status[done & tir] = TIR_EXIT
        # Undeflected, a ray keeps the phase and direction it entered with: it
        # leaves along the beam's own direction in air (Snell both ways).
        incident, blocked = leave_into_air(entered, n_entry, np.ones(n, bool))
        incident[blocked] = np.nan
    return RayResult(pos, dirs, exit_dirs, status.astype(np.int64), events, path, fallbacks,
                     settings, loads, incident)


def trace_voxels(medium, beam: Beam, optics: Optics, settings: TraceSettings) -> RayResult:
    """:func:`trace_beam` in µm: ``beam`` and the result's positions and path lengths in µm,
    the volume ``medium`` of voxels ``medium.voxel_um`` on a side."""
    v = medium.voxel_um
    res = trace_beam(medium, Beam(beam.origins / v, beam.direction, beam.ray_ids), n_wall=optics.n_wall, n_poly=optics.n_poly,
                     settings=settings, seed=optics.seed, n_outside=optics.n_outside)
    return dataclasses.replace(res.scaled(v), voxel_um=v)
