"""A study Dataset's summary variables (every width estimator, haze, intervals, variance
components), built from pooled summaries; and the same variables recomputed from a Dataset's own
rays (``twray resummarize``), so that a change of estimator or interval needs no retrace."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..analysis import ESTIMATORS, HAZE_ANGLE_DEG, SLUG, FwhmSpec, deviated_from_angles
from ..summary import N_BOOT, reduce_angles

_NAMES = {"half-max": "width at half the maximum of a kernel density estimate",
          "lorentz-hist": "2 gamma of a Lorentzian least-squares fitted to the histogram",
          "lorentz-mle": "2 gamma of a Cauchy maximum-likelihood fit"}


def summary_variables(pooled: list[dict]) -> dict:
    """{name: (dimensions after the values', array, attributes)} for values ``pooled`` (one
    :func:`pipeline.summary.pool` dict each, in the study's order)."""
    first = pooled[0]
    spec = FwhmSpec.from_dict(first["fwhm"])
    n_real = first["realisations"]
    how = first["interval"]
    out = {}

    def put(name, get, long_name, units, rest=()):
        out[name] = (rest, np.array([get(p) for p in pooled], dtype=np.float64), {"long_name": long_name, "units": units})

    for q in ("r", "l"):
        Q = q.upper()
        put(f"FWHM_{Q}", lambda p: p[f"fwhm_{q}_deg"], f"FWHM of theta_{Q} ({spec.estimator}: {_NAMES[spec.estimator]}), "
                                                      "realisations pooled", "degree")
        for b, i in (("lower", 0), ("upper", 1)):
            put(f"FWHM_{Q}_ci_{b}", lambda p: p[f"fwhm_{q}_ci_deg"][i], f"95 % interval of FWHM_{Q}, {b}: {how}", "degree")
            put(f"FWHM_{Q}_ray_ci_{b}", lambda p: p[f"fwhm_{q}_ray_ci_deg"][i],
                f"bootstrap 95 % interval of FWHM_{Q} over rays alone, {b}", "degree")
        put(f"FWHM_{Q}_per_realisation", lambda p: p["estimators"][spec.estimator][f"fwhm_{q}_each"],
            f"FWHM_{Q} of each realisation", "degree", ("realisation",))
        for e in ESTIMATORS:
            s = f"FWHM_{Q}_{SLUG[e]}"
            put(s, lambda p: p["estimators"][e][f"fwhm_{q}_deg"], f"FWHM of theta_{Q} by {e}: {_NAMES[e]}", "degree")
            for b, i in (("lower", 0), ("upper", 1)):
                put(f"{s}_ci_{b}", lambda p: p["estimators"][e][f"fwhm_{q}_ci_deg"][i],
                    f"95 % interval of {s}, {b}: {how}", "degree")
            put(f"{s}_per_realisation", lambda p: p["estimators"][e][f"fwhm_{q}_each"], f"{s} of each realisation",
                "degree", ("realisation",))
        put(f"lorentz_ks_{Q}", lambda p: p[f"lorentz_ks_{q}"],
            f"Kolmogorov-Smirnov distance between theta_{Q} and its Lorentz maximum-likelihood fit", "1")
        for c, text in (("between_woods", "between woods"), ("rays_per_wood", "of one wood's value from its rays")):
            put(f"FWHM_{Q}_sd_{c}", lambda p: p["components"].get(f"fwhm_{q}", {}).get(c, np.nan),
                f"standard deviation of one wood's FWHM_{Q} {text}", "degree")
    put("haze", lambda p: p["haze"], f"fraction of transmitted rays deviating more than {HAZE_ANGLE_DEG} degree, "
                                     "realisations pooled", "1")
    for b, i in (("lower", 0), ("upper", 1)):
        put(f"haze_ci_{b}", lambda p: p["haze_ci"][i], f"95 % interval of haze, {b}: {how}", "1")
        put(f"haze_ray_ci_{b}", lambda p: p["haze_ray_ci"][i], f"Wilson 95 % interval of haze over rays alone, {b}", "1")
    put("haze_per_realisation", lambda p: p["haze_each"], "haze of each realisation", "1", ("realisation",))
    for c, text in (("between_woods", "between woods"), ("rays_per_wood", "of one wood's value from its rays")):
        put(f"haze_sd_{c}", lambda p: p["components"].get("haze", {}).get(c, np.nan),
            f"standard deviation of one wood's haze {text}", "1")
    put("n_transmitted", lambda p: p["n_transmitted"], "rays leaving through the far L-R face, all realisations", "1")
    put("n_lost", lambda p: p["n_lost"], "rays not transmitted (reflected, side, trapped), all realisations", "1")
    put("interfaces_per_ray", lambda p: p["interfaces_per_ray"], "mean interfaces met per ray, all realisations", "1")
    if n_real == 1:
        for name in list(out):
            if name.endswith("_per_realisation") or "_sd_" in name:
                out.pop(name)
    return out


def describe_intervals(ds, pooled: dict) -> None:
    """Attributes of a study Dataset's intervals: each variable's bounds linked to it (CF
    ``ancillary_variables``), their level, resamples and procedure; the estimator chosen."""
    how = pooled["interval"]
    for name in list(ds.data_vars):
        linked = [f"{name}_{k}_{b}" for k in ("ci", "ray_ci") for b in ("lower", "upper") if f"{name}_{k}_{b}" in ds]
        if linked:
            ds[name].attrs["ancillary_variables"] = " ".join(linked)
        for bound in linked:
            wilson = bound.startswith("haze_ray_ci") or (bound.startswith("haze_ci") and pooled["realisations"] == 1)
            ds[bound].attrs.update({"confidence_level": 0.95, **({} if wilson else {"bootstrap_resamples": pooled["n_boot"]}),
                                    "interval": "Wilson score (binomial)" if wilson else
                                    (how if "_ray_ci_" not in bound else "bootstrap percentile over rays")})
    ds["haze"].attrs["threshold_deg"] = HAZE_ANGLE_DEG
    ds.attrs["fwhm"] = json.dumps(pooled["fwhm"])
    ds.attrs["fwhm_estimator"] = pooled["fwhm"]["estimator"]
    ds.attrs["intervals"] = how


def pooled_from_dataset(ds, *, spec: FwhmSpec, seed: int, n_boot: int = N_BOOT) -> list[dict]:
    """The pooled summary of every value of a study Dataset, from its own rays (C order over a
    grid's dimensions), with its stored counts.  Each wood's haze from the angles must equal the
    stored one (checked: a beam at an angle needs the exit directions, which a Dataset does not keep)."""
    from ..optics.interface import TRANSMITTED

    value_dims = [d for d in ds["theta_r"].dims if d not in ("realisation", "ray")]
    tr = ds["theta_r"].transpose(*value_dims, "realisation", "ray").values
    tl = ds["theta_l"].transpose(*value_dims, "realisation", "ray").values
    st = ds["status"].transpose(*value_dims, "realisation", "ray").values
    shape = tr.shape[:-2]
    tr, tl, st = (a.reshape((-1,) + a.shape[-2:]) for a in (tr, tl, st))
    stored = ds["haze_per_realisation"].transpose(*value_dims, "realisation").values.reshape(tr.shape[:2]) \
        if "haze_per_realisation" in ds else ds["haze"].values.reshape(-1, 1)
    out = []
    for k in range(tr.shape[0]):
        parts = []
        for r in range(tr.shape[1]):
            ok = st[k, r] == TRANSMITTED
            parts.append((tr[k, r][ok], tl[k, r][ok], deviated_from_angles(tr[k, r][ok], tl[k, r][ok])))
        pooled = reduce_angles(parts, spec=spec, n_boot=n_boot, seed=seed)
        if not np.array_equal(np.array(pooled["haze_each"]), stored[k]):
            raise ValueError(f"value {k}: the haze of the stored angles ({pooled['haze_each']}) is not the stored "
                             f"haze ({list(stored[k])}): the beam was not along +T; rerun the study")
        index = np.unravel_index(k, shape)
        one = ds.isel(dict(zip(value_dims, index)))
        pooled.update({"n_rays": int(st[k].size), "n_transmitted": int(one["n_transmitted"]),
                       "n_lost": int(one["n_lost"]), "interfaces_per_ray": float(one["interfaces_per_ray"])})
        out.append(pooled)
    return out


def resummarized(ds, *, spec: FwhmSpec | None = None, n_boot: int = N_BOOT):
    """``ds`` (a study Dataset, loaded) with its summary variables recomputed from its rays by
    today's estimators and intervals (``spec``: the Dataset's own, or the default), its rays
    untouched; and the pooled summaries."""
    from .. import versions
    from ..analysis import Target
    from .plan import target_met

    if spec is None:
        spec = FwhmSpec.from_dict(json.loads(ds.attrs["fwhm"])) if "fwhm" in ds.attrs else FwhmSpec()
    pooled = pooled_from_dataset(ds, spec=spec, seed=int(ds.attrs["seed"]), n_boot=n_boot)
    value_dims = [d for d in ds["theta_r"].dims if d not in ("realisation", "ray")]
    shape = tuple(ds.sizes[d] for d in value_dims)
    keep = {"theta_r", "theta_l", "status", "n_interfaces", "thickness_traced",
            "interfaces_per_ray_per_realisation", "n_transmitted_per_realisation"}
    new = ds.drop_vars([v for v in ds.data_vars if v not in keep])
    for name, (rest, values, attrs) in summary_variables(pooled).items():
        if "realisation" in rest and "realisation" not in ds.dims:
            continue
        new[name] = (tuple(value_dims) + rest, values.reshape(shape + values.shape[1:]), attrs)
    describe_intervals(new, pooled[0])
    if "target_ci" in ds.attrs:
        new.attrs["target_ci_met"] = int(target_met(Target(**json.loads(ds.attrs["target_ci"])), pooled))
    new.attrs["summary_version"] = versions.STAGES["pool"]
    return new, pooled


def resummarize_file(path: Path, *, spec: FwhmSpec | None = None, n_boot: int = N_BOOT) -> list[dict]:
    """Recompute the summary variables of the study Dataset at ``path`` from its rays (built
    aside and renamed into place, see :mod:`pipeline.publish`); returns the pooled summaries."""
    import xarray as xr

    from ..publish import DIGEST_ATTR, publish_dataset

    path = Path(path)
    with xr.open_zarr(path) as ds:
        ds = ds.load()
    if "theta_r" not in ds:
        raise ValueError(f"`{path}` holds no rays (theta_r): only study Datasets can be re-summarised")
    new, pooled = resummarized(ds, spec=spec, n_boot=n_boot)
    new.attrs.pop(DIGEST_ATTR, None)
    publish_dataset(lambda: new, path, {"resummarised_from": str(ds.attrs.get(DIGEST_ATTR, ""))})
    return pooled
