"""The voxel backend: a beam traced through a two-phase voxel volume (methods paper, fast and
accurate; docs/methods.md#voxel-methods).

:func:`trace_in_voxels` pages chunks in as rays need them, runs the Numba kernel,
answers paper-mode SVM requests, and returns a :class:`RayResult` with one
entry per ray, positions and lengths in voxels.  No ray is ever dropped: each
ends transmitted, reflected back out, out through a side, or trapped.
:func:`trace_voxels` is the same in µm, the form the tracer interface
(:mod:`pipeline.optics.trace`) calls.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..params import ParameterError
from . import _voxel_march as voxel_march
from ._normals import NEWTON_REACH, window_scratch
from ._packing import OUTSIDE, mark_boxes, phases_at
from .faces import NO_PHASE, through_faces
from .interface import NEEDS_CHUNK, NEEDS_NORMAL
from .rays import VOXEL_COUNTS, Beam, RayResult
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


class VoxelInterior:
    """The voxel backend between the faces (:func:`~pipeline.optics.faces.through_faces`):
    the phase at the entry points and the interior march through the volume ``source``, its
    chunks paged in as rays need them; positions and lengths in units of ``unit_um`` µm (the
    voxels' side: in voxels)."""

    def __init__(self, source, settings: TraceSettings, *, unit_um: float = 1.0, capacity: int = 512):
        self.source, self.settings = source, settings
        self.scale = float(source.voxel_um) / float(unit_um)  # the voxels' side in the caller's unit
        self.cache = ChunkCache(source, capacity=capacity)

    def _voxels(self, origins):
        pos = origins / self.scale if self.scale != 1.0 else origins.astype(np.float64).copy()
        pos[:, 1] = 0.0
        vox = np.floor(pos).astype(np.int64)
        vox[:, 1] = 0
        return pos, vox

    def entry_phase(self, origins: np.ndarray) -> np.ndarray:
        """The phase of the voxel each ray enters (NO_PHASE outside a finite volume)."""
        _, vox = self._voxels(origins)
        cache = self.cache
        cache.require(_unique_rows(vox // np.asarray(self.source.chunks)).tolist())
        phase = np.zeros(len(vox), np.uint8)
        phases_at(cache.bits, cache.table, cache.box, cache.chunk_shape, np.asarray(self.source.shape, np.int64),
                  vox, phase)
        phase[phase == OUTSIDE] = NO_PHASE
        return phase

    def march(self, origins, dirs, phase, ray_ids, *, optics: Optics, settings: TraceSettings) -> tuple[dict, dict]:
        vs = settings.voxel
        cache, source = self.cache, self.source
        pos, vox = self._voxels(origins)
        dirs = np.array(dirs, np.float64, copy=True)
        medium = np.array(phase, np.uint8, copy=True)
        n = len(ray_ids)
        status = np.full(n, NEEDS_CHUNK, np.int8)
        events = np.zeros(n, np.int64)
        path = np.zeros(n)
        fallbacks = np.zeros((n, 3), np.int64)
        request = vox // np.asarray(source.chunks)
        normals = np.zeros((n, 4))
        shape = np.asarray(source.shape, np.int64)
        cs = cache.chunk_shape
        method = voxel_march.FIXED_STEPS if settings.method == "paper" else voxel_march.TRAVERSAL
        reach = (int(math.ceil(vs.radius_vox + NEWTON_REACH)) + 2 if method == voxel_march.TRAVERSAL
                 else vs.svm_box)
        scratch = window_scratch(vs.radius_vox)
        while n:
            voxel_march.march_voxels(pos, dirs, medium, vox, status, events, path, fallbacks, request, normals,
                    ray_ids, cache.bits, cache.masks, cache.table, cache.box, cs, shape, method,
                    vs.step_vox, vs.sigma_vox, vs.radius_vox, vs.newton,
                    vs.refit, optics.n_wall, optics.n_poly, settings.fresnel, np.uint64(optics.seed),
                    settings.max_events, *scratch)
            waiting = np.flatnonzero(status == NEEDS_CHUNK)
            asking = np.flatnonzero(status == NEEDS_NORMAL)
            if waiting.size == 0 and asking.size == 0:
                break
            if waiting.size:
                # Keep every chunk that a live ray's normal window may read, or rays
                # near chunk borders would evict each other's chunks forever.
                live = (vox if method == voxel_march.TRAVERSAL else np.floor(pos).astype(np.int64))[status >= NEEDS_CHUNK]
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
        # Voxels read: those along each path, and at each interface the normal's neighbourhood
        # (a Gaussian window of radius ``radius_vox``, evaluated 1 + ``refit`` times, or the
        # paper's SVM box).
        if settings.method == "paper":
            per_interface = vs.svm_box ** 3
        else:
            per_interface = (2 * math.ceil(vs.radius_vox) + 1) ** 3 * (1 + vs.refit)
        out = {"position": pos * self.scale if self.scale != 1.0 else pos, "direction": dirs,
               "status": status.astype(np.int64), "events": events,
               "path": path * self.scale if self.scale != 1.0 else path, "medium": medium,
               "voxels_read": path + events * float(per_interface)}
        out.update({name: fallbacks[:, q] for q, name in enumerate(VOXEL_COUNTS[:3])})
        return out, {"chunks_loaded": int(loads), "traced_voxel_um": float(source.voxel_um)}


def trace_in_voxels(source, beam: Beam, *, n_wall: float, n_poly: float,
               settings: TraceSettings = PRESETS["accurate"], seed: int = 0,
               capacity: int = 512, n_outside: float | None = None) -> RayResult:
    """Trace ``beam`` (positions in voxels) through the voxel ``source`` (an ArraySource,
    WoodSource or LatticeSource), faces handled as for every medium: the voxel backend in its
    own unit, for tests and benchmarks that think in voxels (the tracer interface,
    :func:`pipeline.optics.trace.trace`, is the same in µm).

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
    optics = Optics(n_wall, n_poly, n_outside, seed).validate()
    return through_faces(VoxelInterior(source, settings, unit_um=source.voxel_um, capacity=capacity), beam.origins, beam.unit_directions(),
                         beam.ray_ids, optics, settings)


def voxel_interior(medium, settings: TraceSettings) -> VoxelInterior:
    """The voxel backend of ``medium`` for :func:`~pipeline.optics.trace.trace`, in µm."""
    return VoxelInterior(medium, settings)
