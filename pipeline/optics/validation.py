"""Exact references for the tracer (docs/methods.md#exact-references): voxelised rods, tubes and
flat sheets and their deflection laws, and the comparison of a voxel method with the exact
optics of a lattice (:mod:`pipeline.optics.lattice`)."""

from __future__ import annotations

import math

import numpy as np

from .lattice import Lattice


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

    from ..analysis import LORENTZ_MLE as MLE, fwhm, haze
    from .rays import square_beam
    from .settings import Optics, traced_voxel_um
    from .trace import trace

    voxel_um = traced_voxel_um(voxel_um, settings)
    beam = square_beam(n_rays, beam_um, seed=seed)
    optics = Optics(n_wall, n_poly)
    # The independent exact tracer (ray-circle and ray-line roots), which ``exact`` matches ray by ray.
    ex = lattice.trace_independently(beam.origins, beam.unit_directions(), n_wall=n_wall, n_poly=n_poly, thickness_um=thickness_um)
    t0 = time.perf_counter()
    vx = trace(lattice.source(thickness_um=thickness_um, voxel_um=voxel_um, chunks=chunks), beam, optics, settings)
    elapsed = time.perf_counter() - t0
    te, tv = ex.transmitted, vx.transmitted
    fe, fv = fwhm(ex.theta_r[te], MLE), fwhm(vx.theta_r[tv], MLE)
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
            errs.append(fwhm(xv[k], MLE) / fwhm(xe[k], MLE) - 1.0)
        out["fwhm_r_error_ci"] = [float(np.quantile(errs, 0.025)), float(np.quantile(errs, 0.975))]
    return out


def partial_volume_wall(normal, offset_um: float, shape: tuple[int, int, int], voxel_um: float,
                        supersample: int = 4) -> np.ndarray:
    """The scan a µCT records of the half-space n·x > ``offset_um`` [µm] of wall: each voxel's wall
    fraction from ``supersample``³ points at the centres of its sub-voxels (as ``twray generate --grey``)."""
    n = np.asarray(normal, dtype=np.float64)
    axes = [(np.arange(k) + 0.5) * voxel_um for k in shape]
    base = n[0] * axes[0][:, None, None] + n[1] * axes[1][None, :, None] + n[2] * axes[2][None, None, :]
    sub = ((np.arange(supersample) + 0.5) / supersample - 0.5) * voxel_um
    out = np.zeros(shape)
    for i in sub:
        for j in sub:
            for k in sub:
                out += base + (n[0] * i + n[1] * j + n[2] * k) > offset_um
    return out / supersample ** 3


def iso_wall_normals(alpha_deg: float, beta_deg: float, *, voxel_um: float, smooth_um: float = 0.0, rays: int = 1000,
                     shape: tuple[int, int, int] = (64, 48, 64), n_wall: float = 1.6, n_poly: float = 1.5) -> dict:
    """The normals `iso` refracts by on :func:`partial_volume_wall` of a wall whose normal is turned by
    ``beta_deg`` in the R-T plane and tilted by ``alpha_deg`` towards L: rays along T cross it once
    mid-volume, and n_wall·d_out − n_poly·d_in is along the normal each was refracted by.  Returns the
    wall's normal and, per ray crossing once, that normal's angle from it and its parts along L and
    in R-T [degree]."""
    from .iso import IsoVolume
    from .rays import square_beam
    from .settings import Optics, settings_for
    from .trace import trace

    a, b = math.radians(alpha_deg), math.radians(beta_deg)
    n = np.array([math.sin(b) * math.cos(a), math.cos(b) * math.cos(a), math.sin(a)])
    centre = np.array(shape) * voxel_um / 2.0
    vol = IsoVolume(partial_volume_wall(n, float(n @ centre), shape, voxel_um), voxel_um=voxel_um, iso=0.5,
                    smooth_um=smooth_um)
    beam = square_beam(rays, 0.5 * min(shape[0], shape[2]) * voxel_um, (centre[0], centre[2]), seed=7)
    r = trace(vol, beam, Optics(n_wall, n_poly), settings_for("iso"))
    one = r.events == 1
    m = n_wall * r.direction[one] - n_poly * beam.unit_directions()[one]
    m /= np.linalg.norm(m, axis=1)[:, None]
    m *= np.sign(m @ n)[:, None]
    return {"normal": n, "angle_deg": np.degrees(np.arccos(np.clip(m @ n, -1.0, 1.0))),
            "along_l_deg": np.degrees(np.arcsin(np.clip(m[:, 2], -1.0, 1.0)) - a),
            "across_deg": np.degrees(np.arctan2(m[:, 0], m[:, 1]) - b)}
