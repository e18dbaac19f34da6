"""A regime file's cases as a cached Dask graph, and the map they make as an xarray Dataset.

Each case (geometry × realisation) is one task and one verified cache entry under
``<cache>/wave/``, keyed by everything its numbers depend on; a rerun computes only the missing
cases, on any number of workers, with the same numbers bit for bit (each case is computed alone,
its random streams keyed by seed, ray and beam position).  The Dataset ``<results>/<name>.zarr``
holds every case's numbers (dims geometry, exit, delta_ri, realisation) and the verdict per cell:
where the ray result lies within :data:`HAZE_TOL` haze and :data:`FWHM_TOL` of the wave result.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .. import __version__
from ..analysis import HALF_MAX, LORENTZ_HIST, SLUG
from ..cache import cache_key, read_npz, write_npz
from .regime import EXITS, RAY_METHOD, WAVE_VERSION, Regime, run_case
from .spectrum import SPECTRUM_GRID_DEG, diffraction_limit_deg, white_light

HAZE_TOL = 0.02  # rays hold where |haze_ray - haze_wave| <= 2 points ...
FWHM_TOL = 0.10  # ... and |FWHM_R ray / wave - 1| <= 10 % (half-max)
PER_EXIT = ("haze", HALF_MAX, LORENTZ_HIST)
WINDOW_LOST = 0.01  # waves losing more than this at the window's sides have a FWHM_R cut by the window


def case_record(regime: Regime, geometry, realisation: int) -> dict:
    return {"what": "wave-case", **regime.record(), "geometry": geometry.to_dict(), "seed": regime.seed,
            "realisation": realisation}


def case_path(cache: Path, record: dict) -> Path:
    return Path(cache) / "wave" / f"{cache_key(record)}.npz"


def cached_case(regime: Regime, geometry, realisation: int, cache) -> dict:
    """A case's arrays: read from its cache entry, or computed and stored."""
    record = case_record(regime, geometry, realisation)
    path, key = case_path(cache, record), cache_key(record)
    found = read_npz(path, key)
    if found is not None:
        return found
    out = run_case(regime, geometry, realisation)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_npz(path, record, out)
    return out


def missing(regime: Regime, cache) -> list[tuple]:
    """(geometry, realisation) of the cases with no sound cache entry."""
    from ..cache import check_npz

    out = []
    for g in regime.geometries:
        for r in range(regime.realisations):
            record = case_record(regime, g, r)
            if check_npz(case_path(cache, record), cache_key(record))[0] is None:
                out.append((g, r))
    return out


def compute(regime: Regime, cache, client, *, progress: str = "off") -> int:
    """Compute the missing cases on ``client``; returns how many ran."""
    import dask

    todo = missing(regime, cache)
    if not todo:
        return 0
    from ..progress import graph_keys
    from ..runlog import gather_graph

    arg = dask.delayed(regime, name=f"regime-{regime.name}", traverse=False)
    tasks, labels = [], {}
    # The thickest sections first: their cases take longest, and the workers then end together.
    for g, r in sorted(todo, key=lambda c: -c[0].thickness_um):
        key = f"wave-{g.name}-{r}"
        labels[key] = f"{regime.name} {g.name} realisation {r}"
        tasks.append(dask.delayed(cached_case, pure=False)(arg, g, r, str(cache), dask_key_name=key))
    futures = client.compute(tasks)
    gather_graph(client, futures, graph_keys(tasks), "twray wave", progress, labels)
    return len(todo)


def regime_dataset(regime: Regime, cache):
    """The map of ``regime`` from its cached cases (one missing is computed here)."""
    import xarray as xr

    geos, nr = regime.geometries, regime.realisations
    cases = [[cached_case(regime, g, r, cache) for r in range(nr)] for g in geos]
    dims = ("geometry", "exit", "delta_ri", "realisation")
    data = {}
    for side in ("ray", "wave"):
        for name in PER_EXIT:
            slug = "haze" if name == "haze" else f"FWHM_R_{SLUG[name]}"
            arr = np.array([[[c[f"{name}_{side}_{e}"] for c in row] for e in EXITS] for row in cases])  # g, e, r, d
            data[f"{slug}_{side}"] = (dims, arr.transpose(0, 1, 3, 2))
    for name in ("wave_coherent", "wave_lost", "wave_reflected", "ray_not_transmitted"):
        arr = np.array([[c[name] for c in row] for row in cases])  # g, r, d
        data[name] = (("geometry", "delta_ri", "realisation"), arr.transpose(0, 2, 1))
    for name in ("distribution_wave", "distribution_ray"):
        arr = np.array([[c[name] for c in row] for row in cases])  # g, r, d, angle
        data[name] = (("geometry", "delta_ri", "realisation", "angle"), arr.transpose(0, 2, 1, 3))
    lo, step, m = SPECTRUM_GRID_DEG
    lam = white_light(regime.wavelengths)
    text = lambda values: np.array(values, dtype=object)  # noqa: E731 - variable-length strings in Zarr v3
    coords = {"geometry": text([g.name for g in geos]), "exit": text(EXITS), "delta_ri": list(regime.delta_ri),
              "realisation": np.arange(nr), "angle": lo + step * np.arange(m),
              "thickness_mm": ("geometry", [g.thickness_um / 1e3 for g in geos]),
              "kind": ("geometry", text([("lattice " + g.reference["name"]) if g.reference else g.preset for g in geos]))}
    ds = xr.Dataset(data, coords=coords)
    ds["diffraction_limit_deg"] = ((), diffraction_limit_deg(float(np.min(lam)), regime.ri_polymer, regime.beam_um))
    ds = with_verdict(ds)
    _describe(ds, regime, lam)
    return ds


def with_verdict(ds):
    """Per geometry, exit and ΔRI: the ray − wave differences over realisations (mean and a t
    interval on R − 1 degrees of freedom when R >= 2) and ``rays_hold`` (1 where both lie within
    tolerance, 0 where one does not, judged on the means)."""
    from scipy.stats import t as student_t

    r = ds.sizes["realisation"]
    haze_d = ds["haze_ray"] - ds["haze_wave"]
    ratio = ds[f"FWHM_R_{SLUG[HALF_MAX]}_ray"] / ds[f"FWHM_R_{SLUG[HALF_MAX]}_wave"]
    for name, v in (("haze_difference", haze_d), ("fwhm_r_ratio", ratio)):
        mean = v.mean("realisation")
        ds[name] = mean
        if r >= 2:
            half = float(student_t.ppf(0.975, r - 1)) * v.std("realisation", ddof=1) / math.sqrt(r)
            ds[f"{name}_ci_lower"], ds[f"{name}_ci_upper"] = mean - half, mean + half
    ds["rays_hold"] = ((abs(ds["haze_difference"]) <= HAZE_TOL) & (abs(ds["fwhm_r_ratio"] - 1.0) <= FWHM_TOL)).astype(
        np.int8)
    ds["haze_holds"] = (abs(ds["haze_difference"]) <= HAZE_TOL).astype(np.int8)
    # Light spread beyond the window's angle is absorbed at its sides (counted in haze): past WINDOW_LOST
    # of the power, the waves' FWHM_R is cut by the window, a lower bound, and the width's verdict is open.
    ds["window_limited"] = (ds["wave_lost"].mean("realisation") > WINDOW_LOST).astype(np.int8)
    return ds


def _describe(ds, regime: Regime, lam) -> None:
    from ..provenance import provenance_attrs

    ds.attrs.update(provenance_attrs({"regime": regime.name, "scale": regime.scale,
                                      "cases": [g.to_dict() for g in regime.geometries]}, RAY_METHOD))
    ds.attrs.update({
        "title": regime.title, "wave_version": WAVE_VERSION, "scale": regime.scale,
        "ri_polymer": regime.ri_polymer, "beam_um": regime.beam_um, "rays_per_realisation": regime.rays * regime.positions,
        "beam_positions": regime.positions, "wavelengths_nm": json.dumps([round(float(v) * 1e3, 2) for v in lam]),
        "light": "CIE illuminant C × ȳ at the equal-weight quantiles of 400–700 nm",
        "sampling": json.dumps(regime.sampling.to_dict()), "dx_um": regime.sampling.dx_um,
        "dz_um": regime.sampling.dz_um, "keep_deg": regime.keep_deg, "haze_tolerance": HAZE_TOL,
        "fwhm_tolerance": FWHM_TOL,
        "verdict": "rays_hold = 1 where |haze_ray - haze_wave| <= haze_tolerance and |FWHM_R half-max ray / wave - 1| "
                   "<= fwhm_tolerance (means over realisations); window_limited = 1 where the waves lost more than "
                   f"{WINDOW_LOST:g} of their power at the window's sides (their FWHM_R a lower bound)",
    })
    units = {"haze": "1", "FWHM": "degree", "wave_": "1", "ray_": "1", "distribution": "1", "haze_difference": "1",
             "fwhm_r_ratio": "1"}
    for name in ds.data_vars:
        for prefix, unit in units.items():
            if name.startswith(prefix):
                ds[name].attrs["units"] = unit


def write_regime(regime: Regime, cache, results) -> Path:
    """Publish ``<results>/<regime.name>.zarr`` from the cached cases (kept if already current)."""
    from ..cache import cache_key as key_of
    from ..publish import publish_dataset

    keys = [key_of(case_record(regime, g, r)) for g in regime.geometries for r in range(regime.realisations)]
    provenance = {"regime_yaml": regime.text, "scale": regime.scale, "cache_keys": json.dumps(keys),
                  "source": f"twray {__version__}"}
    return publish_dataset(lambda: regime_dataset(regime, cache), Path(results) / f"{regime.name}.zarr", provenance)


def verdict_at(ds, preset: str, thickness_mm: float, delta_ri: float, exit: str = "internal") -> dict | None:
    """What the regime map ``ds`` says of rays for a wood of ``preset`` at ``thickness_mm``: the
    measured cell of that thickness (within 1 %) whose ΔRI has the same sign and is nearest on a
    log scale, within a factor of 2; None where no such cell was measured.  Keys: ``holds``
    (haze and FWHM_R within tolerance), ``haze_holds``, ``delta_ri`` (the cell's), ``haze_difference``."""
    kinds = [str(k) for k in ds["kind"].values]
    thick = [float(t) for t in ds["thickness_mm"].values]
    geos = [g for g, k, t in zip(ds["geometry"].values, kinds, thick)
            if k == preset and abs(t - thickness_mm) <= 0.01 * thickness_mm]
    same = [float(v) for v in ds["delta_ri"].values if np.sign(v) == np.sign(delta_ri)]
    if not geos or not same or delta_ri == 0:
        return None
    v = min(same, key=lambda d: abs(math.log(abs(d) / abs(delta_ri))))
    if abs(math.log(abs(v) / abs(delta_ri))) > math.log(2.0):  # no measured ΔRI within a factor of 2
        return None
    cell = ds.sel(geometry=geos[0], exit=exit, delta_ri=v)
    return {"holds": bool(int(cell["rays_hold"])), "haze_holds": bool(int(cell["haze_holds"])), "delta_ri": v,
            "geometry": str(geos[0]), "haze_difference": float(cell["haze_difference"]),
            "fwhm_r_ratio": float(cell["fwhm_r_ratio"])}


def verdict_text(v: dict | None) -> str:
    """One verdict as words, for `twray design` and the design maps' captions."""
    if v is None:
        return "not measured against waves at this thickness and ΔRI (`make wave`; add it to the regime file)"
    what = "rays hold" if v["holds"] else ("haze only holds" if v["haze_holds"] else "rays do not hold")
    return (f"{what} (waves, {v['geometry']} at ΔRI {v['delta_ri']:+g}: haze rays − waves "
            f"{100 * v['haze_difference']:+.1f} points, FWHM_R rays / waves {v['fwhm_r_ratio']:.2f})")
