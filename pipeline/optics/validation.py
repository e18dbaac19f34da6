"""Exact references for the tracer (SPEC.md §8): voxelised rods, tubes and flat sheets and their
deflection laws, and lattices of many thin walls (tubes, honeycombs) with an exact tracer."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _exact as _X


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


# --------------------------------------------------------------------------
# Many thin interfaces: lattices of tubes and honeycombs extruded along L
# --------------------------------------------------------------------------
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
        return _X.TUBES if self.family == "tubes" else _X.CELLS

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
        _X.phase_grid(self.geo, self.kind, np.uint64(self.seed), r_um, t_um, out)
        return out

    def voxelise(self, *, voxel_um: float, r0_um: float, n_r: int, n_t: int, length: int = 32) -> np.ndarray:
        """The lattice as a voxel volume, shape (n_r, n_t, length), axes [R, T, L], 1 = wall.

        Voxel (i, j) is wall when its centre (r0_um + (i + ½)·voxel_um, (j + ½)·voxel_um)
        is; the section repeats along L.
        """
        r = r0_um + (np.arange(n_r) + 0.5) * voxel_um
        t = (np.arange(n_t) + 0.5) * voxel_um
        return np.repeat(self.phase(r, t)[:, :, None], length, axis=2)

    def source(self, *, thickness_um: float, voxel_um: float, chunks=(64, 64, 64)) -> "LatticeSource":
        """The lattice, ``thickness_um`` thick along T, as the tracer's voxel source (unbounded in R, L)."""
        return LatticeSource(self, thickness_um=thickness_um, voxel_um=voxel_um, chunks=chunks)

    def trace(self, origins_um, direction, *, n_wall: float, n_poly: float, thickness_um: float,
              max_events: int = 100_000, backwards: bool = False, normal_noise_deg: float = 0.0) -> "ExactResult":
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

        Every crossing is an exact ray-circle or ray-line intersection with
        the normal of that circle or line; Snell's law, or total internal
        reflection (:math:`\\sin^2\\theta_t \\ge 1`), in 3-D.
        """
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = thickness_um if backwards else 0.0
        n = len(pos)
        dirs = np.array(np.broadcast_to(np.asarray(direction, np.float64), (n, 3)))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        if np.any(dirs[:, 1] >= 0 if backwards else dirs[:, 1] <= 0):
            raise ValueError(f"`direction` must point into the sample ({'-' if backwards else '+'}T)")
        out_dir, out_pos = np.empty((n, 3)), np.empty((n, 3))
        status, events = np.empty(n, np.int64), np.empty(n, np.int64)
        medium, normals = np.empty(n, np.uint8), np.empty((n, 2))
        _X.trace(self.geo, self.kind, np.uint64(self.seed), pos, dirs, float(n_wall), float(n_poly),
                 float(thickness_um), int(max_events), float(self.pitch_um), math.radians(normal_noise_deg),
                 out_dir, out_pos, status, events,
                 medium, normals)
        if backwards:
            status = np.where(status == _X.TRANSMITTED, _X.REFLECTED,
                              np.where(status == _X.REFLECTED, _X.TRANSMITTED, status))
        return ExactResult(out_pos, out_dir, status, events, medium, normals)


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


@dataclass
class ExactResult:
    """Per-ray outcome of :meth:`Lattice.trace` (positions [µm], angles [degree])."""

    position: np.ndarray
    direction: np.ndarray
    status: np.ndarray  # 1 transmitted, 2 reflected back out, 4 trapped
    events: np.ndarray
    medium: np.ndarray  # the phase each ray ends in
    first_normal: np.ndarray  # (N, 2): R, T of the first interface's normal, facing the ray

    @property
    def transmitted(self) -> np.ndarray:
        return self.status == _X.TRANSMITTED

    @property
    def theta_r(self) -> np.ndarray:
        return np.degrees(np.arctan2(self.direction[:, 0], self.direction[:, 1]))

    @property
    def theta_l(self) -> np.ndarray:
        return np.degrees(np.arctan2(self.direction[:, 2], self.direction[:, 1]))


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


def smoothed_ks(a, b, resolution_deg: float = 0.25) -> float:
    """Kolmogorov distance between two samples of angles [degree] seen at an angular
    resolution: the largest difference of their cumulative distributions, each
    convolved with a normal of standard deviation ``resolution_deg``.

    The plain KS statistic of θ_R is dominated by rays that cross only parallel
    faces: exactly undeflected in exact optics, a few hundredths of a degree off
    through voxels (no instrument resolves either).
    """
    from scipy.special import ndtr

    a = np.sort(np.asarray(a, np.float64))
    b = np.sort(np.asarray(b, np.float64))
    lo = min(a[0], b[0]) - 5 * resolution_deg
    hi = max(a[-1], b[-1]) + 5 * resolution_deg
    grid = np.linspace(lo, hi, 4001)
    fa = np.array([ndtr((g - a) / resolution_deg).mean() for g in grid])
    fb = np.array([ndtr((g - b) / resolution_deg).mean() for g in grid])
    return float(np.max(np.abs(fa - fb)))


def compare_with_exact(lattice: Lattice, settings, *, voxel_um: float, thickness_um: float, n_wall: float,
                       n_poly: float, n_rays: int = 4000, beam_um: float = 150.0, seed: int = 1,
                       chunks=(64, 64, 64), n_boot: int = 0) -> dict:
    """Trace the same beam through ``lattice`` exactly and through its voxelisation at
    ``voxel_um`` with ``settings`` (a TraceSettings), and compare what a study reports.

    The lattice is a function of position, so it is voxelised at
    ``voxel_um / settings.refine``, as generated wood is.

    Returns FWHM_R [degree] and haze of both, the FWHM_R error (relative, None where
    the exact FWHM_R is under 0.05°, and in degrees), the haze error [points], the KS statistic of θ_R (plain and at 0.25° resolution),
    interfaces per ray, and the voxel trace's wall time [s].  With ``n_boot`` > 0,
    a 95 % bootstrap interval of the FWHM_R error, resampling rays (paired).
    """
    import time

    from scipy import stats

    from ..analysis import fwhm, haze
    from .tracer import square_beam, trace_beam, traced_voxel_um

    voxel_um = traced_voxel_um(voxel_um, settings)
    beam = square_beam(n_rays, beam_um / voxel_um, seed=seed)
    ex = lattice.trace(beam.origins * voxel_um, beam.direction, n_wall=n_wall, n_poly=n_poly,
                       thickness_um=thickness_um)
    t0 = time.perf_counter()
    vx = trace_beam(lattice.source(thickness_um=thickness_um, voxel_um=voxel_um, chunks=chunks), beam,
                    n_wall=n_wall, n_poly=n_poly, settings=settings)
    elapsed = time.perf_counter() - t0
    te, tv = ex.transmitted, vx.transmitted
    fe, fv = fwhm(ex.theta_r[te]), fwhm(vx.theta_r[tv])
    he, hv = haze(ex.direction[te]), haze(vx.direction[tv])
    out = {
        # Relative to the exact width, unless that is too narrow (< 0.05°) for a ratio to mean anything.
        "fwhm_r_exact_deg": fe, "fwhm_r_deg": fv, "fwhm_r_error": fv / fe - 1.0 if fe >= 0.05 else None,
        "fwhm_r_error_deg": fv - fe,
        "haze_exact": he, "haze": hv, "haze_error_points": 100.0 * (hv - he),
        "ks": float(stats.ks_2samp(vx.theta_r[tv], ex.theta_r[te]).statistic),
        "ks_025deg": smoothed_ks(vx.theta_r[tv], ex.theta_r[te]),
        "interfaces_exact": float(ex.events.mean()), "interfaces": float(vx.events.mean()),
        "transmitted_exact": int(te.sum()), "transmitted": int(tv.sum()), "seconds": elapsed,
        "traced_voxel_um": voxel_um,
    }
    if n_boot:
        rng = np.random.default_rng(seed)
        both = te & tv
        xe, xv = ex.theta_r[both], vx.theta_r[both]
        errs = []
        for _ in range(n_boot):
            k = rng.integers(0, xe.size, xe.size)
            errs.append(fwhm(xv[k]) / fwhm(xe[k]) - 1.0)
        out["fwhm_r_error_ci"] = [float(np.quantile(errs, 0.025)), float(np.quantile(errs, 0.975))]
    return out
