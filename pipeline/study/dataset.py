"""A study's xarray Dataset, built from its cache entries and published atomically."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import __version__
from ..publish import publish_dataset
from .plan import Plan, read_entry, target_met
from .summaries import describe_intervals, summary_variables
from .spec import scene_record
from .tasks import load_rays


def study_dataset(plan: Plan):
    """The study's xarray Dataset from its cached entries.

    Dimensions: the varied parameter (one per parameter of a grid), ``realisation`` (the wood drawn with seed
    ``seed + realisation``) and ``ray``.  FWHM_R, FWHM_L and haze are the
    realisations pooled, with intervals that include the wood-to-wood variation
    (``*_ci_lower``/``*_ci_upper``) and of the ray sampling alone
    (``*_ray_ci_*``); ``*_per_realisation`` are each realisation's own.
    """
    import xarray as xr

    from ..optics.interface import STATUS_NAMES

    st = plan.study
    dim = st.dimension
    R = st.realisations
    pooled, each, rays = [], [], []
    for pool in plan.pools:
        pooled.append(read_entry(pool))
        mine = plan.summaries_of(pool)
        each.append([read_entry(s) for s in mine])
        rays.append([load_rays(plan.shards_of(s), st.realisation(pool.scene_index, s.realisation))[0]
                     for s in mine])
    codes = sorted(STATUS_NAMES)
    data = {name: ((dim,) + rest, values, attrs) for name, (rest, values, attrs) in summary_variables(pooled).items()}
    per_realisation = {  # name: (value of a realisation's summary, long_name, units)
        "interfaces_per_ray_per_realisation": (lambda s: s["interfaces_per_ray"],
                                               "mean interfaces met per ray in each realisation", "1"),
        "n_transmitted_per_realisation": (lambda s: s["n_transmitted"],
                                          "rays transmitted in each realisation", "1"),
    }
    per_ray = {  # name: (values of a RayResult, attributes)
        "theta_r": (lambda r: r.theta_r, {"long_name": "exit angle in the R-T plane from +T", "units": "degree"}),
        "theta_l": (lambda r: r.theta_l, {"long_name": "exit angle in the L-T plane from +T", "units": "degree"}),
        "n_interfaces": (lambda r: r.events.astype("int32"), {"long_name": "interfaces met by the ray", "units": "1"}),
        "status": (lambda r: r.status.astype("int32"), {
            "long_name": "ray status", "flag_values": codes,
            "flag_meanings": " ".join(STATUS_NAMES[c] for c in codes)}),
    }
    data.update({name: ((dim, "realisation"), np.array([[get(s) for s in row] for row in each]),
                        {"long_name": ln, "units": u})
                 for name, (get, ln, u) in per_realisation.items()})
    data.update({name: ((dim, "realisation", "ray"), np.array([[get(r) for r in row] for row in rays]), attrs)
                 for name, (get, attrs) in per_ray.items()})
    data["thickness_traced"] = (dim, np.array([s.thickness_um / 1000.0 for s in st.scenes]), {
        "long_name": "TW sample thickness traced along T", "units": "mm"})
    # A grid: the values' dimension becomes one per varied parameter (the scenes are in C order).
    dims = tuple(a.dimension for a in st.axes)
    data = {name: (dims + ((d,) if isinstance(d, str) else d)[1:], v.reshape(st.shape + v.shape[1:]), attrs)
            for name, (d, v, attrs) in data.items()}
    coords = {}
    for a in st.axes:
        coord = a.coordinate()
        if any(isinstance(c, str) for c in coord):
            coord = np.array(coord, dtype=object)  # variable-length strings (laminate notation)
        coords[a.dimension] = (a.dimension, coord, {"long_name": a.long_name, **({"units": a.units} if a.units else {})})
    n_rays = len(rays[0][0].status)
    seed = st.scenes[0].seed
    ds = xr.Dataset(
        data,
        coords={
            **coords,
            "realisation": ("realisation", np.arange(R), {
                "long_name": "wood realisation: the wood and beam of seed `seed` + realisation"}),
            "seed_of_realisation": ("realisation", seed + np.arange(R), {"long_name": "seed of the realisation"}),
            "ray": ("ray", np.arange(n_rays), {"long_name": "ray index in the beam"}),
        },
        attrs={
            "Conventions": "CF-1.10",
            "title": st.title,
            "source": f"twray {__version__}",
            "study": st.name,
            "study_yaml": st.text,
            "scale": st.scale,
            "seed": seed,
            "realisations": R,
            "trace_settings": json.dumps(st.scenes[0].settings.to_dict()),
            "exit_angles": st.scenes[0].settings.exit,
            "cache_keys": json.dumps(plan.keys()),
            "scenes": json.dumps([scene_record(s) for s in st.scenes]),
        },
    )
    from ..provenance import provenance_attrs

    ds.attrs.update(provenance_attrs({"study": st.name, "scale": st.scale, "realisations": R,
                                      "scenes": [scene_record(s) for s in st.scenes]},
                                     st.scenes[0].settings.method))
    describe_intervals(ds, pooled[0])
    target = st.scenes[0].target
    ds.attrs["rays"] = n_rays
    # What was traced (``thickness_traced`` above), which a reduced scale makes differ from the study's numbers.
    ds.attrs["beam_traced_um"] = st.scenes[0].beam_um
    if target is not None:
        ds.attrs["target_ci"] = json.dumps(target.to_dict())
        ds.attrs["target_ci_met"] = int(target_met(target, pooled))
    return ds


def _provenance(plan: Plan) -> dict:
    return {"study_yaml": plan.study.text, "scale": plan.study.scale,
            "cache_keys": json.dumps(plan.keys()), "source": f"twray {__version__}"}


def write_dataset(plan: Plan, results_dir) -> Path:
    """Publish ``results/<study>.zarr``; one built from the same study and cache entries is kept."""
    return publish_dataset(lambda: study_dataset(plan), Path(results_dir) / f"{plan.study.name}.zarr",
                           _provenance(plan))
