"""A scalar field propagated along T through a refractive-index map: multi-slice angular spectrum.

The medium between T and T + dz is a phase screen ``exp(i k0 Δn(x) dz)`` (the index's excess over
the background ``n0``, sampled at the slice's centre) followed by free propagation in ``n0`` with
the exact angular-spectrum propagator ``exp(i (kz - k0 n0) dz)``, kz = √((k0 n0)² - kx²):
waves at any angle travel exactly between the screens, evanescent ones decay.  The method's
errors (docs/methods.md#wave-optics) are the screen's: its phase is the one a wave along T
picks up, k0 Δn dz rather than k0 Δn dz / cos θ for a wave at θ, an error of 1 - cos θ in the
index contrast a wave at θ sees (2 % at 11.5°, the largest angle total reflection in a wall
parallel to T reaches at ΔRI 0.03), and it sends nothing backwards (reflections are measured
apart, :func:`normal_reflectance`).  Steps are Strang-split: half a propagation, then screen and
propagation slice by slice, the last propagation halved.

Fields are (B, nx) arrays, one row per wavelength and index contrast, complex64; the window is
periodic, so an absorbing margin at each side takes the light that would wrap around.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..params import ParameterError

ABSORBER_UM = 15.0  # width of the absorbing margin at each side of the window [µm]


@dataclass(frozen=True)
class Sampling:
    """How finely the medium is sampled: the phase on a grid of ``sub_um``, averaged over cells
    of ``per_dx`` × ``per_dz`` of it (dx along R, dz along T); a cell's wall fraction is one of
    ``per_dx · per_dz + 1`` levels."""

    sub_um: float = 0.04
    per_dx: int = 3
    per_dz: int = 1

    @property
    def dx_um(self) -> float:
        return self.sub_um * self.per_dx

    @property
    def dz_um(self) -> float:
        return self.sub_um * self.per_dz

    @property
    def levels(self) -> int:
        return self.per_dx * self.per_dz

    def validate(self, wavelength_um: float, n: float) -> "Sampling":
        """This sampling, if it resolves every propagating angle of ``wavelength_um`` in index ``n``
        (dx <= λ/(2n)) and steps at most λ/(4n) along T; a ParameterError naming the field if not."""
        if not (isinstance(self.sub_um, (int, float)) and math.isfinite(self.sub_um) and self.sub_um > 0):
            raise ParameterError(f"`sampling.sub_um` must be > 0 µm, got {self.sub_um!r}")
        for name in ("per_dx", "per_dz"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 16:
                raise ParameterError(f"`sampling.{name}` must be an integer in [1, 16], got {v!r}")
        lam_n = wavelength_um / n
        if self.dx_um > lam_n / 2:
            raise ParameterError(f"`sampling` gives dx = {self.dx_um:g} µm, more than λ/(2n) = {lam_n / 2:.4g} µm "
                                 f"at {wavelength_um * 1e3:.0f} nm: lower sub_um or per_dx")
        if self.dz_um > lam_n / 4:
            raise ParameterError(f"`sampling` gives dz = {self.dz_um:g} µm, more than λ/(4n) = {lam_n / 4:.4g} µm "
                                 f"at {wavelength_um * 1e3:.0f} nm: lower sub_um or per_dz")
        return self

    def to_dict(self) -> dict:
        return {"sub_um": self.sub_um, "per_dx": self.per_dx, "per_dz": self.per_dz}


def gaussian_beam(x_um: np.ndarray, centre_um: float, diameter_um: float) -> np.ndarray:
    """Amplitude of a collimated Gaussian beam of 1/e² intensity diameter ``diameter_um`` at its
    waist, of unit power (Σ|u|² dx = 1 on a fine grid)."""
    w0 = diameter_um / 2.0
    a = np.exp(-((x_um - centre_um) / w0) ** 2)
    return a / math.sqrt(w0 * math.sqrt(math.pi / 2.0))


def absorber(nx: int, dx_um: float, width_um: float = ABSORBER_UM) -> np.ndarray:
    """Per-step amplitude mask: 1 inside, falling as cos^(1/8) of a quarter period over ``width_um``
    at each side, so that the light reaching a side is absorbed over many steps, not reflected."""
    x = np.arange(nx) * dx_um
    d = np.minimum(x, (nx - 1) * dx_um - x) / width_um  # 0 at a side, 1 at the inner edge of the margin
    return np.where(d >= 1.0, 1.0, np.cos(0.5 * math.pi * (1.0 - np.clip(d, 0.0, 1.0))) ** 0.125).astype(np.float32)


def kx_of(nx: int, dx_um: float) -> np.ndarray:
    """Transverse wavenumbers [rad/µm] of the FFT of an ``nx`` field sampled every ``dx_um``."""
    return 2.0 * math.pi * np.fft.fftfreq(nx, dx_um)


def propagator(kx: np.ndarray, k: np.ndarray, dz_um: float, dtype=np.complex64) -> np.ndarray:
    """(B, nx) exp(i (kz − k) dz) for background wavenumbers ``k`` = k0·n0 (B,): exact for
    propagating waves, decaying for evanescent ones (the carrier e^{ikz} left out)."""
    kz = np.sqrt((k[:, None] ** 2 - kx[None, :] ** 2).astype(np.complex128))
    return np.exp(1j * (kz - k[:, None]) * dz_um).astype(dtype)


def propagate(field: np.ndarray, slices, *, k0: np.ndarray, delta_n: np.ndarray, n0: np.ndarray,
              sampling: Sampling, mean_fraction: float = 0.0, mask: np.ndarray | None = None,
              dtype=np.complex64):
    """Propagate ``field`` (B, nx) through the medium whose wall fraction, slice by slice, is
    ``slices`` (an iterable of (nz, nx) uint8 arrays of levels 0..sampling.levels, in T order).

    Row b has vacuum wavenumber ``k0[b]`` [rad/µm], background index ``n0[b]`` and wall excess
    ``delta_n[b]``: a cell of wall fraction f has index n0 + delta_n·(f − ``mean_fraction``) (the
    background is the mean index when ``mean_fraction`` is the map's mean fraction, which halves
    the screen's error at an angle).  ``mask`` (nx,) multiplies the field at every step (an
    absorber).  ``dtype`` complex64 rounds away about 3e-8 of the power a step (a 1 mm section:
    1e-3), counted as lost; complex128 is exact to 1e-15 and twice as slow.

    Returns (spectrum, lost): the exit field's FFT (B, nx), complex64, and the fraction of each
    row's power that did not reach the exit plane (absorbed at the sides or evanescent).
    """
    from scipy import fft as sfft

    u = np.array(field, dtype=dtype, copy=True)
    b, nx = u.shape
    dz = sampling.dz_um
    k = np.asarray(k0, np.float64) * np.asarray(n0, np.float64)
    kx = kx_of(nx, sampling.dx_um)
    full = propagator(kx, k, dz, dtype)
    half = propagator(kx, k, dz / 2.0, dtype)
    frac = np.arange(sampling.levels + 1) / sampling.levels - mean_fraction
    table = np.exp(1j * (np.asarray(k0)[:, None] * np.asarray(delta_n)[:, None]) * frac[None, :] * dz)
    table = table.astype(dtype)
    mask = np.ones(nx) if mask is None else np.asarray(mask, np.float64)
    mask = mask.astype(np.float32 if dtype == np.complex64 else np.float64)
    p0 = np.sum(np.abs(u) ** 2, axis=1)
    spec = sfft.fft(u, axis=1, overwrite_x=True, workers=1)
    spec *= half
    first = True
    for block in slices:
        for lev in block:
            if not first:
                spec *= full
            first = False
            u = sfft.ifft(spec, axis=1, overwrite_x=True, workers=1)
            screen(u, table, lev, mask)
            spec = sfft.fft(u, axis=1, overwrite_x=True, workers=1)
    spec *= half
    p1 = np.sum(np.abs(spec) ** 2, axis=1) / nx
    return spec, np.clip(1.0 - p1 / p0, 0.0, 1.0)


@njit(cache=True, nogil=True)
def screen(u, table, lev, mask):
    """u[b, x] *= table[b, lev[x]] · mask[x] in place: the phase screen of one slice."""
    for b in range(u.shape[0]):
        for x in range(u.shape[1]):
            u[b, x] *= table[b, lev[x]] * mask[x]


class StepReflectance:
    """What the forward solver leaves out, estimated as it streams the slices past: the Fresnel
    reflectance at normal incidence of every step of index along T, r = Δn·Δf / (2n), summed
    incoherently (single scattering, random phases) and averaged over the columns.  Per unit
    ΔRI: :meth:`reflectance` scales it by ΔRI²."""

    def __init__(self, slices, levels: int):
        self.slices, self.levels = slices, levels
        self.sum_sq = None
        self.last = None

    def __iter__(self):
        for block in self.slices:
            f = block.astype(np.float64) / self.levels
            steps = np.diff(f, axis=0) if self.last is None else np.diff(np.vstack([self.last[None], f]), axis=0)
            add = np.sum(steps ** 2, axis=0)
            self.sum_sq = add if self.sum_sq is None else self.sum_sq + add
            self.last = f[-1]
            yield block

    def reflectance(self, delta_n: float, n: float) -> float:
        """Mean reflected power fraction of a column at contrast ``delta_n`` in index ``n``."""
        return 0.0 if self.sum_sq is None else float(np.mean(self.sum_sq)) * (delta_n / (2.0 * n)) ** 2
