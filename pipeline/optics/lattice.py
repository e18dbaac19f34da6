"""Lattices of many thin walls, tubes and honeycombs extruded along L: exact reference media
(docs/methods.md#exact-references).

A :class:`Lattice` is defined everywhere in the R-T plane.  As a surface
medium (:meth:`Lattice.slab`) it is traced exactly, every crossing an exact
ray-circle or ray-line intersection; as a voxel medium (:meth:`Lattice.source`)
it is voxelised chunk by chunk at any voxel size, so that the voxel methods
can be judged on the very same walls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _exact
from ._lattice_rows import lattice_context
from ._surface_march import HIT, TOL, march, new_work
from .interface import REFLECTED, TRANSMITTED
from .rays import RayResult
from .settings import settings_for

PACKINGS = ("square", "hex")


@dataclass(frozen=True)
class Lattice:
    """A 2-D cross-section in the R-T plane, extruded along L, with an exact tracer.

    Build one with :func:`tube_lattice` or :func:`honeycomb`.  Lengths are
    physical [µm]; sites sit on a square or hexagonal lattice of ``pitch_um``,
    rotated by ``rotation_deg`` from R, each moved by up to ``jitter`` ×
    pitch in R and T (a hash of ``seed`` and its lattice index).  The
    geometry is defined everywhere, so :meth:`source` voxelises any region
    at any voxel size, chunk by chunk.
    """

    family: str  # "tubes" or "cells"
    packing: str
    pitch_um: float
    r_outer_um: float = 0.0  # tubes
    r_inner_um: float = 0.0  # tubes
    wall_um: float = 0.0  # cells: the wall between two lumens
    jitter: float = 0.0
    rotation_deg: float = 0.0
    seed: int = 0
    origin_um: tuple = (0.0, 0.0)  # the site of lattice index (0, 0), before jitter [µm]

    @property
    def kind(self) -> int:
        return _exact.TUBES if self.family == "tubes" else _exact.CELLS

    @property
    def geo(self) -> np.ndarray:
        p = self.pitch_um
        a = math.radians(self.rotation_deg)
        c, s = math.cos(a), math.sin(a)
        u = (p, 0.0)
        v = (0.0, p) if self.packing == "square" else (0.5 * p, 0.5 * math.sqrt(3.0) * p)
        a1 = (c * u[0] - s * u[1], s * u[0] + c * u[1])
        a2 = (c * v[0] - s * v[1], s * v[0] + c * v[1])
        inv = np.linalg.inv(np.array([[a1[0], a2[0]], [a1[1], a2[1]]]))
        second = ((self.r_outer_um, self.r_inner_um) if self.family == "tubes" else (0.5 * self.wall_um, 0.0))
        return np.array([*a1, *a2, *self.origin_um, self.jitter * p, inv[0, 0], inv[0, 1], inv[1, 0], inv[1, 1],
                         *second])

    def phase(self, r_um, t_um) -> np.ndarray:
        """Phase (1 = wall, 0 = polymer) on the grid r_um × t_um [µm]: shape (len(r_um), len(t_um)), uint8."""
        r_um = np.ascontiguousarray(r_um, np.float64)
        t_um = np.ascontiguousarray(t_um, np.float64)
        out = np.empty((r_um.size, t_um.size), np.uint8)
        _exact.phase_grid(self.geo, self.kind, np.uint64(self.seed), r_um, t_um, out)
        return out

    def voxelise(self, *, voxel_um: float, r0_um: float, n_r: int, n_t: int, length: int = 32) -> np.ndarray:
        """The lattice as a voxel volume, shape (n_r, n_t, length), axes [R, T, L], 1 = wall.

        Voxel (i, j) is wall when its centre (r0_um + (i + ½)·voxel_um, (j + ½)·voxel_um)
        is; the section repeats along L.
        """
        r = r0_um + (np.arange(n_r) + 0.5) * voxel_um
        t = (np.arange(n_t) + 0.5) * voxel_um
        return np.repeat(self.phase(r, t)[:, :, None], length, axis=2)

    def grey_section(self, *, voxel_um: float, r0_um: float, n_r: int, n_t: int, supersample: int = 4) -> np.ndarray:
        """The section as a scan records it: the wall fraction (float32, shape (n_r, n_t)) of each voxel
        from ``supersample``² points at the centres of its sub-squares (the lattice is constant along L).
        Voxel (i, j) spans R ∈ r0_um + [i, i + 1)·voxel_um, T ∈ [j, j + 1)·voxel_um."""
        s = int(supersample)
        r = r0_um + (np.arange(n_r * s) + 0.5) * (voxel_um / s)
        t = (np.arange(n_t * s) + 0.5) * (voxel_um / s)
        return self.phase(r, t).reshape(n_r, s, n_t, s).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)

    def source(self, *, thickness_um: float, voxel_um: float, chunks=(64, 64, 64)) -> "LatticeSource":
        """The lattice, ``thickness_um`` thick along T, as the tracer's voxel source (unbounded in R, L)."""
        return LatticeSource(self, thickness_um=thickness_um, voxel_um=voxel_um, chunks=chunks)

    def slab(self, thickness_um: float) -> "LatticeSlab":
        """The lattice, ``thickness_um`` thick along T, as a surface medium (method ``exact``,
        traced by the march that traces generated wood)."""
        return LatticeSlab(self, thickness_um)

    def trace_independently(self, origins_um, direction, *, n_wall: float, n_poly: float, thickness_um: float,
              max_events: int = 100_000, backwards: bool = False, normal_noise_deg: float = 0.0) -> RayResult:
        """Trace rays exactly through the lattice from T = 0 to T = ``thickness_um``.

        Parameters
        ----------
        origins_um : ndarray of shape (N, 3)
            Entry points [µm] (their T is taken as 0).
        direction : array-like of shape (3,) or (N, 3)
            Directions inside the sample, pointing into it (+T).
        n_wall, n_poly : float
            Refractive indices of the wall (phase 1) and the polymer (phase 0).
        backwards : bool
            Rays start on the far face (T = thickness_um) and point into the
            sample (−T); those leaving through T = 0 are then "transmitted".
        normal_noise_deg : float
            Turn every normal in the R-T plane by a normal deviate of this
            standard deviation [degree] (a hash of the lattice's seed, the ray and
            the interface): what a normal estimator's error does to the results.

        Returns the RayResult of method ``exact`` [µm], with extras ``medium``
        (the phase each ray ends in) and ``first_normal`` ((N, 2): R, T of the
        first interface's normal, facing the ray).  Every crossing is an exact
        ray-circle or ray-line intersection with the normal of that circle or
        line; Snell's law, or total internal reflection
        (:math:`\\sin^2\\theta_t \\ge 1`), in 3-D.  Forwards, the same as
        :func:`pipeline.optics.trace.trace` of :meth:`slab`, which the surface march traces:
        this is the independent reference it is tested against.
        """
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = thickness_um if backwards else 0.0
        n = len(pos)
        dirs = np.array(np.broadcast_to(np.asarray(direction, np.float64), (n, 3)))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        if np.any(dirs[:, 1] >= 0 if backwards else dirs[:, 1] <= 0):
            raise ValueError(f"`direction` must point into the sample ({'-' if backwards else '+'}T)")
        out = self._run(pos, dirs, n_wall, n_poly, thickness_um, max_events, normal_noise_deg)
        status = out.pop("status")
        if backwards:
            status = np.where(status == TRANSMITTED, REFLECTED, np.where(status == REFLECTED, TRANSMITTED, status))
        position, direction_, events, path = (out.pop(k) for k in ("position", "direction", "events", "path"))
        return RayResult(position, direction_, direction_, status, events, path,
                         settings_for("exact", max_events=max_events), extras=out)

    def _run(self, pos, dirs, n_wall, n_poly, thickness_um, max_events, normal_noise_deg=0.0) -> dict:
        n = len(pos)
        out_dir, out_pos = np.empty((n, 3)), np.empty((n, 3))
        status, events = np.empty(n, np.int64), np.empty(n, np.int64)
        path = np.empty(n)
        medium, normals = np.empty(n, np.uint8), np.empty((n, 2))
        _exact.trace_lattice(self.geo, self.kind, np.uint64(self.seed), pos, dirs, float(n_wall), float(n_poly),
                 float(thickness_um), int(max_events), float(self.pitch_um), math.radians(normal_noise_deg),
                 out_dir, out_pos, status, events, path, medium, normals)
        return {"position": out_pos, "direction": out_dir, "status": status, "events": events, "path": path,
                "medium": medium, "first_normal": normals}


@dataclass(frozen=True)
class LatticeSlab:
    """A :class:`Lattice` between T = 0 and T = ``thickness_um`` as a surface medium (method
    ``exact``), traced by the march that traces generated wood
    (:mod:`pipeline.optics._surface_march`): each wall a circle or a line of the R-T section,
    extruded along L, listed as rows with their distances (:mod:`pipeline.optics._lattice_rows`).
    :meth:`Lattice.trace_independently` is the independent reference it is tested against."""

    lattice: Lattice
    thickness_um: float
    hit: float = HIT
    tol: float = TOL

    def entry_phase(self, origins_um) -> np.ndarray:
        pos = np.asarray(origins_um, np.float64).reshape(-1, 3)
        return np.array([self.lattice.phase([r], [0.0])[0, 0] for r in pos[:, 0]], np.uint8)

    def march_walls(self, origins_um, directions, *, n_wall: float, n_poly: float, max_events: int,
                       fresnel: bool = False, seed: int = 0, ray_ids=None, log_events: int = 0) -> dict:
        lat = self.lattice
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        n = len(pos)
        ids = np.arange(n, dtype=np.int64) if ray_ids is None else np.asarray(ray_ids, np.int64)
        out = {"position": np.empty((n, 3)), "direction": np.empty((n, 3)), "status": np.empty(n, np.int64),
               "events": np.empty(n, np.int64), "path": np.empty(n), "evaluations": np.empty(n, np.int64),
               "passes": np.empty(n, np.int64), "medium": np.empty(n, np.uint8)}
        log = np.zeros((n, log_events, 12) if log_events else (0, 0, 12))
        march(pos, np.ascontiguousarray(directions, np.float64), ids, float(self.thickness_um), float(n_wall),
              float(n_poly), int(max_events), bool(fresnel), np.uint64(seed),
              lattice_context(lat.geo, lat.kind, lat.seed), self.hit, self.tol, 1.0, False, *out.values(), log,
              np.zeros(1), np.zeros(n, np.uint8), np.zeros((n, 5)), np.empty((n, 3)), new_work())
        if log_events:
            out["log"] = log
        return out


def tube_lattice(pitch_um: float, r_outer_um: float, wall_um: float, *, packing: str = "square",
                 jitter: float = 0.0, rotation_deg: float = 0.0, seed: int = 0,
                 origin_um=(0.0, 0.0)) -> Lattice:
    """Circular tubes (outer radius ``r_outer_um``, wall ``wall_um`` [µm]) on a lattice of ``pitch_um``.

    Tubes touch where 2·r_outer = pitch and merge their walls where it is
    larger (wall where a point is in some tube's outer disc and in no
    tube's lumen); the space between tubes is polymer.
    """
    _check_lattice(pitch_um, packing, jitter)
    if not 0 < wall_um <= r_outer_um:
        raise ValueError(f"`wall_um` must be in (0, r_outer_um = {r_outer_um}], got {wall_um=}")
    if not r_outer_um < pitch_um:
        raise ValueError(f"`r_outer_um` must be < pitch_um = {pitch_um}, got {r_outer_um=}")
    return Lattice("tubes", packing, float(pitch_um), r_outer_um=float(r_outer_um),
                   r_inner_um=float(r_outer_um - wall_um), jitter=float(jitter), rotation_deg=float(rotation_deg),
                   seed=int(seed), origin_um=_pair(origin_um))


def honeycomb(pitch_um: float, wall_um: float, *, packing: str = "hex", jitter: float = 0.0,
              rotation_deg: float = 0.0, seed: int = 0, origin_um=(0.0, 0.0)) -> Lattice:
    """Polygonal cells: straight walls of ``wall_um`` [µm] between the Voronoi cells of a
    lattice of sites ``pitch_um`` apart (hexagons for "hex", squares for "square";
    ``jitter`` > 0 moves the sites, giving irregular polygons as in wood
    cross-sections)."""
    _check_lattice(pitch_um, packing, jitter)
    if not 0 < wall_um < 0.5 * pitch_um:
        raise ValueError(f"`wall_um` must be in (0, pitch_um / 2 = {pitch_um / 2}), got {wall_um=}")
    return Lattice("cells", packing, float(pitch_um), wall_um=float(wall_um), jitter=float(jitter),
                   rotation_deg=float(rotation_deg), seed=int(seed), origin_um=_pair(origin_um))


def _pair(v) -> tuple:
    return (float(v[0]), float(v[1]))


def _check_lattice(pitch_um, packing, jitter):
    if packing not in PACKINGS:
        raise ValueError(f"`packing` must be one of {', '.join(PACKINGS)}, got {packing!r}")
    if not pitch_um > 0:
        raise ValueError(f"`pitch_um` must be > 0 µm, got {pitch_um=}")
    if not 0 <= jitter <= 0.25:
        raise ValueError(f"`jitter` must be in [0, 0.25] (fraction of the pitch), got {jitter=}")


class LatticeSource:
    """A :class:`Lattice` as the tracer's voxel source: ``thickness_um`` thick along T,
    unbounded along R and L (like generated wood), voxelised chunk by chunk at
    ``voxel_um``; voxel (i, j, k) is the phase at the centre of (i, j)."""

    unbounded = (True, True)

    def __init__(self, lattice: Lattice, *, thickness_um: float, voxel_um: float, chunks=(64, 64, 64)):
        n_t = int(round(thickness_um / voxel_um))
        if n_t < 1:
            raise ValueError(f"`thickness_um` must be at least one voxel, got {thickness_um:g} µm")
        self.lattice = lattice
        self.voxel_um = float(voxel_um)
        self.shape = (0, n_t, 0)
        self.chunks = tuple(int(c) for c in chunks)
        self.generated = 0
        self.token = ("lattice", repr(lattice), self.voxel_um, n_t, self.chunks)

    def inside(self, idx) -> bool:
        return 0 <= idx[1] < math.ceil(self.shape[1] / self.chunks[1])

    def get_many(self, indices) -> dict:
        cR, cT, cL = self.chunks
        out = {}
        for idx in indices:
            i, j, _ = (int(v) for v in idx)
            n_t = min(cT, self.shape[1] - j * cT)
            r = (i * cR + np.arange(cR) + 0.5) * self.voxel_um
            t = (j * cT + np.arange(n_t) + 0.5) * self.voxel_um
            section = self.lattice.phase(r, t)
            out[(i, j, int(idx[2]))] = np.ascontiguousarray(np.broadcast_to(section[:, :, None], (cR, n_t, cL)))
        self.generated += len(out)
        return out

    def get(self, idx) -> np.ndarray:
        return self.get_many([idx])[tuple(int(v) for v in idx)]
