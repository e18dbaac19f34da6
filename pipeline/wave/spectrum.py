"""From exit fields to what a hazemeter and a goniometer read: angular power, haze and widths.

White light: a hazemeter weights its source (CIE illuminant C, ASTM D1003) by the eye's luminous
efficiency ȳ(λ); :func:`white_light` samples that product at equal-weight quantiles.  Indices do
not depend on the wavelength here (no dispersion: ΔRI is the same at every λ).

Widths are the rays' estimators (:mod:`pipeline.analysis`) applied to power instead of ray counts:
``half-max`` smooths the angular power with the kernel the rays' estimate uses for the same
interquartile range and ray count, ``lorentz-hist`` fits the same histogram, so that a ray result
and a wave result of one case differ by their physics, not by their estimators.
"""

from __future__ import annotations

import math

import numpy as np

from ..analysis import HALF_MAX, HAZE_ANGLE_DEG, LORENTZ_HIST, FwhmSpec, half_max_of_counts, hist_grid, kde_grid, \
    lorentz_hist_of_counts

# CIE illuminant C (relative spectral power) and the CIE 1931 luminous efficiency ȳ, 400-700 nm every 20 nm.
TABLE_NM = np.arange(400.0, 701.0, 20.0)
ILLUMINANT_C = np.array([63.30, 98.10, 121.50, 123.10, 123.90, 112.10, 96.90, 102.10, 105.30, 97.80, 89.70, 88.10,
                         87.80, 87.90, 84.00, 76.30])
Y_BAR = np.array([0.000396, 0.004, 0.023, 0.060, 0.13902, 0.323, 0.710, 0.954, 0.995, 0.870, 0.631, 0.381, 0.175,
                  0.061, 0.017, 0.004102])
WAVE_ESTIMATORS = (HALF_MAX, LORENTZ_HIST)  # the widths a wave result carries
SPECTRUM_GRID_DEG = (-60.0, 0.1, 1201)  # first centre, step, bins of the stored angular distributions


def white_light(count: int) -> np.ndarray:
    """``count`` wavelengths [µm] of equal weight sampling illuminant C × ȳ over 400-700 nm: the
    midpoints of ``count`` equal parts of its cumulative distribution."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"`wavelengths` must be an integer >= 1, got {count!r}")
    nm = np.arange(400.0, 700.01, 0.5)
    w = np.interp(nm, TABLE_NM, ILLUMINANT_C * Y_BAR)
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    return np.interp((np.arange(count) + 0.5) / count, cdf, nm) / 1e3


def exit_angles(spectrum: np.ndarray, kx: np.ndarray, k0: np.ndarray, n_inside: np.ndarray, exit: str):
    """(θ [degree], power) of each plane wave of the exit fields ``spectrum`` (B, nx): inside the
    sample (index ``n_inside`` per row) or after refraction into air at the T face, where the
    angle comes from kx alone (kx = k0 sin θ_air).  θ is NaN where the wave does not propagate
    there (evanescent inside; totally reflected at the exit face)."""
    k = k0[:, None] * (1.0 if exit == "air" else n_inside[:, None])
    s = kx[None, :] / k
    with np.errstate(invalid="ignore"):
        theta = np.where(np.abs(s) < 1.0, np.degrees(np.arcsin(np.clip(s, -1.0, 1.0))), np.nan)
    return theta, (np.abs(spectrum) ** 2).astype(np.float64)


def _weighted_quartiles(theta: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    order = np.argsort(theta)
    t, c = theta[order], np.cumsum(w[order])
    q1, med, q3 = np.interp(np.array([0.25, 0.5, 0.75]) * c[-1], c, t)
    return float(med), float(q3 - q1)


def power_summary(theta: np.ndarray, power: np.ndarray, *, n_rays: int, lost: float = 0.0,
                  fwhm: FwhmSpec = FwhmSpec()) -> dict:
    """Haze and widths of angular power ``power`` at ``theta`` [degree] (NaN angles: not
    transmitted).  ``lost``: power that left the window sideways, as a fraction of the transmitted
    power (counted as deviated: it went beyond the window's angle).  Widths by the rays'
    estimators for a sample of ``n_rays`` angles with the power's quartiles."""
    ok = np.isfinite(theta) & (power > 0)
    t, w = theta[ok], power[ok]
    total = float(w.sum())
    out = {"haze": float((w[np.abs(t) > HAZE_ANGLE_DEG].sum() + lost * total) / (total * (1.0 + lost)))}
    med, iqr = _weighted_quartiles(t, w)
    plan = kde_grid(med, iqr, n_rays)
    out[HALF_MAX] = 0.0 if plan is None else float(half_max_of_counts(binned(t, w, plan[0]), *plan)[0])
    bins = hist_grid(med, iqr, n_rays, fwhm.of(LORENTZ_HIST), span=(float(t.min()), float(t.max())))
    out[LORENTZ_HIST] = 0.0 if bins is None else float(lorentz_hist_of_counts(binned(t, w, bins), bins)[0])
    return out


def binned(theta: np.ndarray, weights: np.ndarray, bins) -> np.ndarray:
    """The power of a sampled angular spectrum in each of ``bins``, read as a density: each sample's
    power is spread over the angles up to its neighbours (the cumulative power interpolated
    linearly between the samples), so bins finer than the samples' spacing are not spiky."""
    order = np.argsort(theta, kind="stable")
    t, c = theta[order], np.cumsum(weights[order])
    centres = 0.5 * (t[1:] + t[:-1])  # each sample's power lies between the midpoints to its neighbours
    edges = bins.lo - bins.step / 2.0 + bins.step * np.arange(bins.m + 1)
    cdf = np.interp(edges, centres, c[:-1], left=0.0, right=c[-1])
    return np.diff(cdf)


def stored_distribution(theta: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The distribution of angles ``theta`` [degree] (weighted by ``weights``) on the stored grid
    (:data:`SPECTRUM_GRID_DEG`), normalised to unit sum (beyond the grid's ends: left out)."""
    from ..analysis import Bins

    ok = np.isfinite(theta)
    grid = Bins(*SPECTRUM_GRID_DEG)
    counts = grid.counts(theta[ok]) if weights is None else binned(theta[ok], weights[ok], grid)
    s = counts.sum()
    return counts / s if s > 0 else counts


def diffraction_limit_deg(wavelength_um: float, n: float, beam_um: float) -> float:
    """Full width at half maximum [degree] of the angular power of an unscattered Gaussian beam
    of 1/e² diameter ``beam_um``: the finest width a wave result can show."""
    w0 = beam_um / 2.0
    sigma = wavelength_um / (2.0 * math.pi * n * w0)  # of the power's angular Gaussian, in radians (θ ≈ kx/k)
    return math.degrees(2.0 * math.sqrt(2.0 * math.log(2.0)) * sigma)
