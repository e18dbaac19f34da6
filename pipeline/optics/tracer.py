"""Trace a beam through a two-phase voxel volume (SPEC.md §4-5).

:func:`trace_beam` is the one orchestrator: it pages chunks in as rays need
them, runs the Numba kernel, answers paper-mode SVM requests, and returns a
:class:`RayResult` with one entry per ray.  No ray is ever dropped: each ends
transmitted, reflected back out, out through a side, or trapped.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np

from ..microstructure import _rng
from ..params import ParameterError
from . import _kernels as K
from .sources import ChunkCache

STATUS_NAMES = {K.TRANSMITTED: "transmitted", K.REFLECTED: "reflected", K.SIDE: "side",
                K.TRAPPED: "trapped", 5: "tir_at_exit_face"}
TIR_EXIT = 5
BEAM_KIND = 41


@dataclass(frozen=True)
class TraceSettings:
    """How rays find interfaces and normals.

    method : "paper" (2-voxel steps, midpoint crossing, linear SVM on a
        6×6×6 box), "fast" or "accurate" (exact voxel traversal, crossing on
        the voxel face, gradient of a Gaussian-smoothed wall indicator).
    refine : generated wood (a function of position) is traced on voxels
        ``refine`` times smaller than the scene's (the same physical wood,
        refine³ as many voxels); a user volume is traced on its own voxels.
        Binary voxels alias walls nearly parallel to a grid axis into
        staircases whose smoothed normals err by degrees, the same at any
        voxel size in voxel units; against exact optics of many thin walls
        (benchmarks/bench_accuracy.py) the error falls about as the voxel.
    """

    method: str = "accurate"
    step_vox: float = 2.0  # paper marching step [voxels]
    svm_box: int = 6  # paper SVM sub-volume edge [voxels]
    sigma_vox: float = 2.0  # Gaussian σ of the gradient normal [voxels]
    radius_vox: float = 6.0  # truncation of the Gaussian sum, about 3σ [voxels]
    newton: int = 3  # Newton steps putting the crossing on the smoothed surface
    refit: int = 1  # of which evaluate the window again (the others step on its 2nd-order model)
    fresnel: bool = False
    max_events: int = 2000  # a ray meets ~170 interfaces in 1.5 mm of birch; guided rays bounce on
    exit: str = "internal"  # angles "internal" (in the sample) or after refraction into "air"
    refine: int = 1  # generated wood traced on voxels this many times smaller

    def validate(self) -> "TraceSettings":
        if self.method not in PRESETS:
            raise ParameterError(f"`method` must be one of {', '.join(PRESETS)}, got {self.method!r}")
        if self.exit not in ("internal", "air"):
            raise ParameterError(f"`exit` must be internal or air, got {self.exit!r}")
        if not self.step_vox > 0:
            raise ParameterError(f"`step_vox` must be > 0 voxels, got {self.step_vox!r}")
        if not self.sigma_vox > 0 or not 1 <= self.radius_vox <= 24:
            raise ParameterError(f"`sigma_vox` must be > 0 and `radius_vox` in [1, 24], got "
                                 f"{self.sigma_vox!r}, {self.radius_vox!r}")
        if not 0 <= self.refit <= self.newton:
            raise ParameterError(f"`refit` must be in [0, newton = {self.newton!r}], got {self.refit!r}")
        if isinstance(self.refine, bool) or not isinstance(self.refine, int) or not 1 <= self.refine <= 8:
            raise ParameterError(f"`refine` must be an integer in [1, 8], got {self.refine!r}")
        if self.max_events < 1:
            raise ParameterError(f"`max_events` must be >= 1, got {self.max_events!r}")
        return self


# Bump when the kernels' numbers change for the same inputs (part of the
# study and camera cache keys, so cached rays and images are traced again).
TRACER_VERSION = "7"

PRESETS = {
    "paper": TraceSettings(method="paper"),
    # One window evaluation; the Newton steps run on its second-order model.
    "fast": TraceSettings(method="fast", sigma_vox=1.75, radius_vox=5.25, newton=3, refit=0),
    # The window evaluated again after the first Newton step, on voxels half the scene's.
    "accurate": TraceSettings(method="accurate", sigma_vox=2.0, radius_vox=6.0, newton=3, refit=1, refine=2),
}


def traced_voxel_um(voxel_um: float, settings: TraceSettings) -> float:
    """The voxel [µm] generated wood is traced on: the scene's, divided by ``settings.refine``."""
    return voxel_um / settings.refine


def settings_for(method: str, **changes) -> TraceSettings:
    if method not in PRESETS:
        raise ParameterError(f"`method` must be one of {', '.join(PRESETS)}, got {method!r}")
    return replace(PRESETS[method], **changes).validate()


@dataclass
class Beam:
    """Rays entering the T = 0 face.

    origins : (N, 3) entry points [voxels]; direction : (3,) one direction
    for every ray, or (N, 3) one per ray; inside the sample, or in the outside
    medium when :func:`trace_beam` is given ``n_outside``.
    """

    origins: np.ndarray
    direction: np.ndarray
    ray_ids: np.ndarray


def square_beam(n_rays: int, width_vox: float, centre_vox=(0.0, 0.0), *, seed: int,
                direction=(0.0, 1.0, 0.0)) -> Beam:
    """``n_rays`` at uniformly random points of a width × width square of the L-R face.

    Each ray's position is a hash of (seed, ray id): the beam is the same
    however the rays are later split into shards.
    """
    if n_rays < 1:
        raise ParameterError(f"`rays` must be >= 1, got {n_rays}")
    ids = np.arange(n_rays, dtype=np.int64)
    s = np.uint64(seed)
    u = _rng.uniform_table(s, BEAM_KIND, ids, 2, 0)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    if d[1] <= 0:
        raise ParameterError(f"`direction` must point into the sample (+T), got {tuple(direction)}")
    origins = np.zeros((n_rays, 3))
    origins[:, 0] = centre_vox[0] + (u[:, 0] - 0.5) * width_vox
    origins[:, 2] = centre_vox[1] + (u[:, 1] - 0.5) * width_vox
    return Beam(origins, d, ids)


@dataclass
class RayResult:
    """Per-ray outcome of a trace (angles in degrees, lengths in voxels)."""

    position: np.ndarray  # (N, 3) exit (or last) point
    direction: np.ndarray  # (N, 3) final direction inside the sample
    exit_direction: np.ndarray  # (N, 3) after the exit-medium setting
    status: np.ndarray  # (N,)
    events: np.ndarray
    path: np.ndarray
    fallbacks: np.ndarray  # (N, 3): degenerate normals, face/direction disagreements, thin-wall normals
    settings: TraceSettings
    chunks_loaded: int = 0
    # (N, 3) the direction each ray would leave in, in the convention of
    # exit_direction, had nothing deflected it (haze is measured from it);
    # None: every ray came in along +T.  NaN where that undeflected ray could
    # not leave into air (total reflection at the exit face).
    incident: np.ndarray | None = None

    @property
    def transmitted(self) -> np.ndarray:
        return self.status == K.TRANSMITTED

    @property
    def theta_r(self) -> np.ndarray:
        d = self.exit_direction
        return np.degrees(np.arctan2(d[:, 0], d[:, 1]))

    @property
    def theta_l(self) -> np.ndarray:
        d = self.exit_direction
        return np.degrees(np.arctan2(d[:, 2], d[:, 1]))

    def counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.status == code)) for code, name in STATUS_NAMES.items()}


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
    K.mark_boxes(lo - base, hi - base, grid)
    return np.argwhere(grid) + base


def _enter(dirs: np.ndarray, status: np.ndarray, n_in: np.ndarray, n_out: float) -> None:
    """Refract directions (in place) through the T = 0 face from index n_out into n_in."""
    tang = dirs[:, [0, 2]] * (n_out / n_in)[:, None]
    s2 = np.sum(tang**2, axis=1)
    tir = s2 >= 1.0
    status[tir & (status == K.NEEDS_CHUNK)] = K.REFLECTED
    ok = ~tir
    dirs[ok, 0] = tang[ok, 0]
    dirs[ok, 2] = tang[ok, 1]
    dirs[ok, 1] = np.sqrt(1.0 - s2[ok])


def trace_beam(source, beam: Beam, *, n_wall: float, n_poly: float,
               settings: TraceSettings = PRESETS["accurate"], seed: int = 0,
               capacity: int = 512, n_outside: float | None = None) -> RayResult:
    """Trace ``beam`` through ``source`` (an ArraySource or WoodSource).

    Parameters
    ----------
    n_wall, n_poly : float
        Refractive indices of the cell wall (phase 1) and polymer (phase 0).
    settings : TraceSettings
        Method preset and options.
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
    if not (n_wall > 0 and n_poly > 0 and math.isfinite(n_wall) and math.isfinite(n_poly)):
        raise ParameterError(f"refractive indices must be finite and > 0, got {n_wall=}, {n_poly=}")
    cache = ChunkCache(source, capacity=capacity)
    n = len(beam.ray_ids)
    pos = beam.origins.astype(np.float64).copy()
    dirs = np.array(np.broadcast_to(np.asarray(beam.direction, np.float64), (n, 3)))
    norms = np.linalg.norm(dirs, axis=1)
    if np.any(~(norms > 0)) or np.any(dirs[:, 1] <= 0):
        raise ParameterError("beam directions must be non-zero and point into the sample (+T)")
    dirs /= norms[:, None]
    vox = np.floor(pos).astype(np.int64)
    vox[:, 1] = 0
    pos[:, 1] = 0.0
    status = np.full(n, K.NEEDS_CHUNK, np.int8)
    events = np.zeros(n, np.int64)
    path = np.zeros(n)
    fallbacks = np.zeros((n, 3), np.int64)
    request = vox // np.asarray(source.chunks)
    normals = np.zeros((n, 4))
    shape = np.asarray(source.shape, np.int64)
    cs = cache.chunk_shape
    method = K.PAPER if settings.method == "paper" else K.EXACT
    reach = (int(math.ceil(settings.radius_vox + K.NEWTON_REACH)) + 2 if method == K.EXACT
             else settings.svm_box)
    scratch = K.window_scratch(settings.radius_vox)
    # A ray starts in the phase of the voxel it enters; outside a finite volume it is "side".
    cache.require(_unique_rows(request).tolist())
    medium = np.zeros(n, np.uint8)
    K.phases_at(cache.bits, cache.table, cache.box, cs, shape, vox, medium)
    status[medium == K.OUTSIDE] = K.SIDE
    medium[medium == K.OUTSIDE] = 0
    n_entry = np.where(medium == 1, n_wall, n_poly)
    if n_outside is not None:
        _enter(dirs, status, n_entry, float(n_outside))
    entered = dirs.copy()
    while True:
        K.trace(pos, dirs, medium, vox, status, events, path, fallbacks, request, normals,
                beam.ray_ids, cache.bits, cache.masks, cache.table, cache.box, cs, shape, method,
                settings.step_vox, settings.sigma_vox, settings.radius_vox, settings.newton,
                settings.refit, n_wall, n_poly, settings.fresnel, np.uint64(seed), settings.max_events,
                *scratch)
        waiting = np.flatnonzero(status == K.NEEDS_CHUNK)
        asking = np.flatnonzero(status == K.NEEDS_NORMAL)
        if waiting.size == 0 and asking.size == 0:
            break
        if waiting.size:
            # Keep every chunk that a live ray's normal window may read, or rays
            # near chunk borders would evict each other's chunks forever.
            live = (vox if method == K.EXACT else np.floor(pos).astype(np.int64))[status >= K.NEEDS_CHUNK]
            # The chunks each live ray's window [x - reach, x + reach] spans.
            keep = map(tuple, _chunks_of_boxes((live - reach) // cs, (live + reach) // cs).tolist())
            cache.require(_unique_rows(request[waiting]).tolist(), keep=set(keep))
        half = settings.svm_box // 2
        for r in asking:
            centre = pos[r]
            lo = np.floor(centre).astype(np.int64) - (half - 1)
            box = cache.voxels(lo, (settings.svm_box,) * 3)
            w, ok = svm_normal(box, centre, lo)
            normals[r, :3] = w
            normals[r, 3] = 1.0 if ok else 0.0
    loads = cache.loads
    cache.release()  # its buffers serve the next trace of this process
    exit_dirs = dirs.copy()
    incident = entered
    if settings.exit == "air":
        done = status == K.TRANSMITTED
        exit_dirs, tir = _leave_into_air(dirs, np.where(medium == 1, n_wall, n_poly), done)
        status[done & tir] = TIR_EXIT
        # Undeflected, a ray keeps the phase and direction it entered with: it
        # leaves along the beam's own direction in air (Snell both ways).
        incident, blocked = _leave_into_air(entered, n_entry, np.ones(n, bool))
        incident[blocked] = np.nan
    return RayResult(pos, dirs, exit_dirs, status.astype(np.int64), events, path, fallbacks,
                     settings, loads, incident)


def _leave_into_air(dirs: np.ndarray, n_in: np.ndarray, which: np.ndarray):
    """Directions (a copy) refracted from indices ``n_in`` into air through a T face
    where ``which``; and where that is total reflection (those rows left as they were)."""
    out = dirs.copy()
    tang = dirs[:, [0, 2]] * n_in[:, None]
    s2 = np.sum(tang**2, axis=1)
    tir = s2 >= 1.0
    ok = which & ~tir
    out[ok, 0] = tang[ok, 0]
    out[ok, 2] = tang[ok, 1]
    out[ok, 1] = np.sqrt(1.0 - s2[ok])
    return out, tir
