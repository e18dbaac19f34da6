"""Rays against waves on the same sections: the regime file, its cases, and one case computed.

A regime file (``studies/wave/regime.yaml``, docs/guide.md#where-rays-hold) names geometries
(reference lattices, or a wood preset made a section), the ΔRI values, realisations, beam
positions, the beam, the rays and the white light.  A case is one geometry and one realisation:
its section's index map is sampled once and every ΔRI, wavelength and beam position propagates
through it, and ``exact`` traces the same rays' worth of beam (Gaussian positions, the same
centres) through the same section at every ΔRI.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import rng, versions
from ..analysis import HALF_MAX, LORENTZ_HIST, deviated_from_angles, half_max_fwhm, lorentz_hist_fwhm
from ..optics.settings import INDEX_RANGE
from ..params import ParameterError, build_params, read_yaml_file
from .sections import LatticeSection, WoodSection, extruded, slices
from .solver import ABSORBER_UM, Sampling, StepReflectance, absorber, gaussian_beam, kx_of, propagate, propagator
from .spectrum import exit_angles, power_summary, stored_distribution, white_light

WAVE_VERSION = "3"  # bump when a case's numbers change for the same inputs
RAY_METHOD = "exact"  # the rays beside the waves; its version is part of every case's key
EXITS = ("internal", "air")
PAD = 4  # the exit field is zero-padded this many times before its spectrum: angles sampled 4x finer
POSITION_SPACING_UM = 5000.0  # beam positions of a realisation lie this far apart along R
SCALES = {"paper": 1.0, "quick": 0.25, "small": 0.1}  # thickness factor; quick and small also trace fewer rays
KEYS = {"title", "seed", "realisations", "positions", "beam_um", "rays", "ri_polymer", "delta_ri", "wavelengths",
        "sampling", "keep_deg", "geometries"}
GEOMETRY_KEYS = {"name", "thickness_mm", "reference", "pitch_um", "wall_um", "r_outer_um", "jitter", "preset", "set"}


@dataclass(frozen=True)
class Geometry:
    """One section: a reference lattice (``reference`` and its fields) or a wood ``preset`` with
    ``overrides``, ``thickness_um`` thick."""

    name: str
    thickness_um: float
    reference: dict | None = None
    preset: str | None = None
    overrides: dict = field(default_factory=dict)

    def section(self, seed: int):
        """The section of realisation ``seed``, and ``medium(r_lo, r_hi)``: the surfaces ``exact``
        traces for it, for a wood bounded to the window [r_lo, r_hi] along R (a ray leaving it
        has status SIDE; a ray guided along the walls of a section, which nothing along L lets
        out, could otherwise wander for centimetres)."""
        if self.reference is not None:
            from ..optics.references import reference

            lat = reference(**self.reference).lattice(seed)
            return LatticeSection(lat), lambda r_lo, r_hi: lat.slab(self.thickness_um)
        from ..optics.wood_surface import WoodSurface

        sec = WoodSection(build_params(self.preset, overrides=self.overrides), seed)
        return sec, lambda r_lo, r_hi: WoodSurface(sec.params, thickness_um=self.thickness_um, seed=seed,
                                                   r_bounds_um=(r_lo, r_hi))

    def to_dict(self) -> dict:
        return {"name": self.name, "thickness_um": self.thickness_um, "reference": self.reference,
                "preset": self.preset, "overrides": self.overrides}


@dataclass(frozen=True)
class Regime:
    """A regime file, read and checked."""

    name: str
    title: str
    geometries: tuple
    delta_ri: tuple
    ri_polymer: float = 1.49
    seed: int = 1
    realisations: int = 3
    positions: int = 2
    beam_um: float = 100.0
    rays: int = 2000  # per beam position
    wavelengths: int = 6
    sampling: Sampling = Sampling()
    keep_deg: float = 30.0
    scale: str = "paper"
    text: str = ""

    def record(self) -> dict:
        """What a case's numbers depend on, besides its geometry and realisation."""
        return {"delta_ri": list(self.delta_ri), "ri_polymer": self.ri_polymer, "positions": self.positions,
                "beam_um": self.beam_um, "rays": self.rays, "wavelengths": self.wavelengths,
                "sampling": self.sampling.to_dict(), "keep_deg": self.keep_deg, "wave": WAVE_VERSION,
                "tracer": versions.tracer(RAY_METHOD)}

    def window_um(self, geometry: Geometry) -> float:
        """Width of the simulated window: twice the beam, the spread to ``keep_deg`` over the
        thickness on each side, and the absorbing margins."""
        return (2.0 * self.beam_um + 2.0 * geometry.thickness_um * math.tan(math.radians(self.keep_deg))
                + 2.0 * ABSORBER_UM)


def _number(d: dict, key: str, where: str, default, *, lo=None, integer=False):
    v = d.get(key, default)
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(v) or (lo is not None and v < lo):
        kind = "an integer" if integer else "a number"
        raise ParameterError(f"{where}: `{key}` must be {kind}{'' if lo is None else f' >= {lo:g}'}, got {v!r}")
    return v


def load_regime(path, *, scale: str = "paper") -> Regime:
    """Read and check a regime file; ``scale`` "quick" or "small" makes every section thinner
    (a quarter, a tenth) and traces fewer rays, for a quick look and for tests."""
    path = Path(path)
    if scale not in SCALES:
        raise ParameterError(f"`scale` must be one of {', '.join(SCALES)}, got {scale!r}")
    text, d = read_yaml_file(path, "regime file")
    unknown = sorted(set(d) - KEYS)
    if unknown:
        raise ParameterError(f"{path}: unknown key `{unknown[0]}` (known: {', '.join(sorted(KEYS))})")
    where = str(path)
    dris = d.get("delta_ri")
    if not isinstance(dris, list) or not dris or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v != 0 for v in dris):
        raise ParameterError(f"{where}: `delta_ri` must be a list of non-zero numbers, got {dris!r}")
    n_poly = _number(d, "ri_polymer", where, 1.49)
    lo, hi = INDEX_RANGE
    if not all(lo <= n_poly + v <= hi for v in dris) or not lo <= n_poly <= hi:
        raise ParameterError(f"{where}: `ri_polymer` and `delta_ri` must give indices in [{lo:g}, {hi:g}]")
    samp = d.get("sampling") or {}
    if not isinstance(samp, dict) or set(samp) - {"sub_um", "per_dx", "per_dz"}:
        raise ParameterError(f"{where}: `sampling` must be a mapping of sub_um, per_dx, per_dz, got {samp!r}")
    sampling = Sampling(**samp)
    n_wl = _number(d, "wavelengths", where, 6, lo=1, integer=True)
    try:
        sampling.validate(float(white_light(n_wl)[0]), n_poly + max(0.0, max(dris)))  # the shortest λ, densest phase
    except ParameterError as exc:
        raise ParameterError(f"{where}: {exc}") from None
    factor = SCALES[scale]
    geos = []
    for i, g in enumerate(d.get("geometries") or []):
        gw = f"{where}: geometries[{i}]"
        if not isinstance(g, dict) or set(g) - GEOMETRY_KEYS:
            raise ParameterError(f"{gw} must be a mapping of {', '.join(sorted(GEOMETRY_KEYS))}, got {g!r}")
        t_mm = _number(g, "thickness_mm", gw, None, lo=1e-3)
        name = g.get("name")
        if not isinstance(name, str) or not name:
            raise ParameterError(f"{gw}: `name` must be a non-empty string, got {name!r}")
        if ("reference" in g) == ("preset" in g):
            raise ParameterError(f"{gw}: give either `reference` (a lattice) or `preset` (a wood), not "
                                 f"{'both' if 'reference' in g else 'neither'}")
        if "reference" in g:
            from ..optics.references import reference

            ref = {k: g[k] for k in ("pitch_um", "wall_um", "r_outer_um", "jitter") if k in g}
            try:
                reference(g["reference"], **{"pitch_um": None, "wall_um": None, **ref})
            except ParameterError as exc:
                raise ParameterError(f"{gw}: {exc}") from None
            geos.append(Geometry(name, 1e3 * t_mm * factor, reference={"name": g["reference"], **ref}))
        else:
            over = g.get("set") or {}
            try:
                extruded(build_params(g["preset"], overrides=over))
            except ParameterError as exc:
                raise ParameterError(f"{gw}: {exc}") from None
            geos.append(Geometry(name, 1e3 * t_mm * factor, preset=g["preset"], overrides=dict(over)))
    if not geos:
        raise ParameterError(f"{where}: `geometries` must list at least one section")
    if len({g.name for g in geos}) != len(geos):
        raise ParameterError(f"{where}: geometry names must differ")
    rays = _number(d, "rays", where, 2000, lo=10, integer=True)
    return Regime(
        name=path.stem, title=str(d.get("title", path.stem)), geometries=tuple(geos), delta_ri=tuple(float(v) for v in dris),
        ri_polymer=float(n_poly), seed=_number(d, "seed", where, 1, lo=0, integer=True),
        realisations=_number(d, "realisations", where, 3, lo=1, integer=True),
        positions=_number(d, "positions", where, 2, lo=1, integer=True),
        beam_um=float(_number(d, "beam_um", where, 100.0, lo=1.0)),
        rays=rays if scale == "paper" else max(100, int(rays * factor)), wavelengths=n_wl, sampling=sampling,
        keep_deg=float(_number(d, "keep_deg", where, 30.0, lo=5.0)), scale=scale, text=text)


def ray_origins(regime: Regime, seed: int, position: int, centre_um: float) -> np.ndarray:
    """(rays, 3) entry points of a beam position: R drawn from the Gaussian beam's intensity
    (σ = beam/4) around ``centre_um`` by Box–Muller on the BEAM streams of (seed, ray, position)."""
    ids = np.arange(regime.rays, dtype=np.int64)
    u = rng.uniform_table(np.uint64(seed), rng.BEAM, ids, 2, position)
    r = np.sqrt(-2.0 * np.log1p(-u[:, 0])) * np.cos(2.0 * math.pi * u[:, 1])
    out = np.zeros((regime.rays, 3))
    out[:, 0] = centre_um + r * regime.beam_um / 4.0
    return out


def run_case(regime: Regime, geometry: Geometry, realisation: int) -> dict:
    """Waves and rays of one geometry and realisation at every ΔRI: arrays (exit, ΔRI) of haze and
    widths for each, the waves' coherent and lost power, and the internal angular distributions."""
    seed = regime.seed + realisation
    section, section_medium = geometry.section(seed)
    samp = regime.sampling
    nd = len(regime.delta_ri)
    from scipy import fft as sfft

    nx = sfft.next_fast_len(int(math.ceil(regime.window_um(geometry) / samp.dx_um)))
    nz = max(1, int(round(geometry.thickness_um / samp.dz_um)))
    x = (np.arange(nx) + 0.5) * samp.dx_um
    lam = white_light(regime.wavelengths)
    dri = np.array(regime.delta_ri)
    k0 = np.repeat(2.0 * math.pi / lam, nd)
    dn = np.tile(dri, lam.size)
    mask = absorber(nx, samp.dx_um)
    wave_theta = {e: [[] for _ in range(nd)] for e in EXITS}
    wave_power = {e: [[] for _ in range(nd)] for e in EXITS}
    lost, coherent = np.zeros((regime.positions, lam.size, nd)), np.zeros((regime.positions, lam.size, nd))
    ray_theta = {e: [[] for _ in range(nd)] for e in EXITS}
    ray_out = np.zeros(nd)
    reflected = np.zeros((regime.positions, nd))
    kxp = kx_of(nx * PAD, samp.dx_um)
    for p in range(regime.positions):
        r0 = p * POSITION_SPACING_UM
        it = slices(section, r0_um=r0, nx=nx, nz=nz, sampling=samp)
        first = next(it)
        fbar = float(first.mean()) / samp.levels
        steps = StepReflectance(itertools.chain([first], it), samp.levels)
        n0 = np.full(k0.size, regime.ri_polymer) + dn * fbar
        u0 = np.tile(gaussian_beam(x, x[nx // 2], regime.beam_um), (k0.size, 1))
        spec, lost_p = propagate(u0, steps, k0=k0, delta_n=dn, n0=n0, sampling=samp,
                                 mean_fraction=fbar, mask=mask)
        u = sfft.ifft(spec, axis=1)
        big = sfft.fft(u, n=nx * PAD, axis=1)
        free = sfft.fft(u0, n=nx * PAD, axis=1) * propagator(kxp, k0 * n0, nz * samp.dz_um, np.complex128)
        overlap = np.abs(np.sum(big * np.conj(free), axis=1)) ** 2 / (
            np.sum(np.abs(big) ** 2, axis=1) * np.sum(np.abs(free) ** 2, axis=1))
        lost[p] = lost_p.reshape(lam.size, nd)
        reflected[p] = [steps.reflectance(float(d), regime.ri_polymer) for d in dri]
        coherent[p] = overlap.reshape(lam.size, nd)
        for e in EXITS:
            theta, power = exit_angles(big, kxp, k0, np.full(k0.size, regime.ri_polymer), e)
            power /= np.nansum(np.where(np.isfinite(theta), power, 0.0), axis=1, keepdims=True)  # each row: unit power
            for row in range(k0.size):
                wave_theta[e][row % nd].append(theta[row])
                wave_power[e][row % nd].append(power[row])
        origins = ray_origins(regime, seed, p, r0 + x[nx // 2])
        medium = section_medium(r0, r0 + nx * samp.dx_um)
        for i, d in enumerate(dri):
            for e, th in ray_angles(medium, origins, regime.ri_polymer, float(d)).items():
                ray_theta[e][i].append(th)
                if e == "internal":
                    ray_out[i] += (regime.rays - th.size) / (regime.rays * regime.positions)
    out = {"ray_not_transmitted": ray_out, "wave_lost": lost.mean(axis=(0, 1)), "wave_reflected": reflected.mean(axis=0),
           "wave_coherent": coherent.mean(axis=(0, 1)), "distribution_wave": np.zeros((nd, 1201)),
           "distribution_ray": np.zeros((nd, 1201))}
    n_rays = regime.rays * regime.positions
    for e in EXITS:
        for name in ("haze", HALF_MAX, LORENTZ_HIST):
            out[f"{name}_ray_{e}"], out[f"{name}_wave_{e}"] = np.zeros(nd), np.zeros(nd)
        for i in range(nd):
            th = np.concatenate(ray_theta[e][i])
            out[f"haze_ray_{e}"][i] = float(np.mean(deviated_from_angles(th, np.zeros_like(th)))) if th.size else np.nan
            out[f"{HALF_MAX}_ray_{e}"][i] = half_max_fwhm(th)
            out[f"{LORENTZ_HIST}_ray_{e}"][i] = lorentz_hist_fwhm(th)
            t, w = np.concatenate(wave_theta[e][i]), np.concatenate(wave_power[e][i])
            s = power_summary(t, w, n_rays=n_rays, lost=float(lost.mean(axis=(0, 1))[i]))
            for name in ("haze", HALF_MAX, LORENTZ_HIST):
                out[f"{name}_wave_{e}"][i] = s[name]
            if e == "internal":
                out["distribution_wave"][i] = stored_distribution(t, w)
                out["distribution_ray"][i] = stored_distribution(th)
    return out


def ray_angles(medium, origins: np.ndarray, n_poly: float, delta_ri: float) -> dict:
    """θ_R [degree] of RAY_METHOD's rays through ``medium`` (inside, and into air), which left through
    the exit face, and which left the window through a side (counted as deviated, as the waves'
    light absorbed at the window's sides is)."""
    from ..optics.interface import SIDE, TRANSMITTED, leave_into_air
    from ..optics.rays import Beam
    from ..optics.settings import Optics, TraceSettings
    from ..optics.trace import trace

    optics = Optics.of_delta(n_poly, delta_ri)
    res = trace(medium, Beam(origins, np.array([0.0, 1.0, 0.0]), np.arange(len(origins))), optics,
                TraceSettings(method=RAY_METHOD))
    done = res.status == TRANSMITTED
    n_end = np.where(res.extras["medium"] == 1, optics.n_wall, optics.n_poly)
    air, tir = leave_into_air(res.direction, n_end, done)
    side = np.full(np.count_nonzero(res.status == SIDE), 90.0)  # beyond the window: deviated
    return {"internal": (np.concatenate([res.theta_r[done], side])),
            "air": (np.concatenate([np.degrees(np.arctan2(air[done & ~tir, 0], air[done & ~tir, 1])), side]))}
