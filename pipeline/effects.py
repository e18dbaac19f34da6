"""The numbers behind the reproduction report, read from the committed datasets: Table 1 rows,
paired effect sizes with hierarchical bootstrap intervals, the paper's method beside the
default, the measured samples, fibre tips, the camera and the cheapest setting meeting a
precision.  :mod:`pipeline.report` writes them as Markdown.

Effect sizes are paired differences between a study's values with a bootstrap
over rays: every value of a study is traced with the same beam (ray i enters
at the same point), so resampling ray indices once and reducing every value on
that resample pairs them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .analysis import HALF_MAX, deviated_from_angles, fwhm, image_quality
from .summary import N_BOOT, percentile_interval, t_interval
from .publish import open_dataset
from .result_sets import study_dimension, value_label
from .microstructure.model import tip_wall_angle_deg
from .optics.interface import TRANSMITTED
from .params import WoodParams

# The value of each study that the others are compared with: the Table 1 default scene
# (docs/methods.md#table-1) where the study contains it, else its first value.
REFERENCE = {"thickness": 1.0, "delta_ri": 0.01}

LEVEL = 0.95

# ------------------------------------------------------------------ effects
def reference_index(ds) -> int:
    dim = study_dimension(ds)
    if dim in REFERENCE:
        hits = np.flatnonzero(np.isclose(ds[dim].values.astype(float), REFERENCE[dim]))
        if hits.size:
            return int(hits[0])
    return 0

def reduce_rays(theta_r, theta_l, ok, idx, estimator: str = HALF_MAX) -> np.ndarray:
    """FWHM_R, FWHM_L (by ``estimator``) and haze of rays ``idx`` (those of them transmitted,
    ``ok``) of one value.

    The arrays are (realisation, ray) and ``idx`` a list of (realisation, ray indices) pairs,
    or 1-D arrays and an array of ray indices."""
    if np.ndim(theta_r) == 1:
        theta_r, theta_l, ok, idx = theta_r[None], theta_l[None], ok[None], [(0, idx)]
    sel_r = np.concatenate([theta_r[r][i[ok[r][i]]] for r, i in idx])
    sel_l = np.concatenate([theta_l[r][i[ok[r][i]]] for r, i in idx])
    return np.array([fwhm(sel_r, estimator), fwhm(sel_l, estimator), float(np.mean(deviated_from_angles(sel_r, sel_l)))])

def resample(rng: np.random.Generator, n_real: int, n_rays: int) -> list:
    """One bootstrap draw of (realisation, ray indices) pairs: with several woods, woods drawn
    with replacement, each with all its rays (docs/methods.md#realisations-and-intervals); with one,
    its rays drawn with replacement."""
    if n_real > 1:
        every = np.arange(n_rays)
        return [(int(r), every) for r in rng.integers(0, n_real, n_real)]
    return [(0, rng.integers(0, n_rays, n_rays))]


def resample_key(idx: list, n_real: int, estimator: str = HALF_MAX):
    """What :func:`reduce_rays` of a :func:`resample` depends on, so that each distinct resample is
    reduced once: with several woods and the half-max width, the woods drawn as a multiset (sorted),
    since the pooled rays' quartiles, binned counts and mean of 0/1 deviations are exact whatever
    order the woods come in (5 woods give at most 126 distinct resamples of 2000); None (reduce
    it) where rays are redrawn or another estimator may depend on the order."""
    if n_real > 1 and estimator == HALF_MAX:
        return tuple(sorted(r for r, _ in idx))
    return None


def resampled(rng: np.random.Generator, n_real: int, n_rays: int, n_boot: int, reduce,
              estimator: str = HALF_MAX) -> list:
    """``reduce(idx)`` of ``n_boot`` draws of :func:`resample`, in order; a resample drawn again
    (the same :func:`resample_key` for the ``estimator`` ``reduce`` uses) is reduced once."""
    seen, out = {}, []
    for _ in range(n_boot):
        idx = resample(rng, n_real, n_rays)
        key = resample_key(idx, n_real, estimator)
        if key is None or key not in seen:
            seen[key] = reduce(idx)
        out.append(seen[key])
    return out


def interval(point: float, draws: np.ndarray, n_real: int) -> tuple[float, float]:
    """The 95 % interval of a change from its bootstrap ``draws``: Student t on the woods'
    standard error with several woods, the percentile interval over rays with one."""
    lo, hi = t_interval(float(point), np.asarray(draws, dtype=float), n_real, LEVEL) if n_real > 1 else \
        percentile_interval(np.asarray(draws, dtype=float), LEVEL)
    return float(lo), float(hi)


def holm_resolved(p_values, alpha: float = 1.0 - LEVEL) -> int:
    """How many of ``p_values`` (NaNs left out) Holm's step-down procedure resolves at a
    family-wise error ``alpha``."""
    ps = np.sort(np.asarray([p for p in p_values if p == p], float))
    n = 0
    for i, p in enumerate(ps):
        if p > alpha / (ps.size - i):
            break
        n += 1
    return n


def p_value(effect: "Effect") -> float:
    """Two-sided p-value of an effect against no change, from its interval (t on woods − 1 d.o.f.,
    the interval's half-width being t · SE); NaN for an interval over rays alone."""
    from scipy.stats import t as student_t

    lo, hi = effect.ci
    if effect.woods < 2 or not hi > lo:
        return float("nan")
    q = float(student_t.ppf(0.5 + LEVEL / 2, effect.woods - 1))
    se = (hi - lo) / (2 * q)
    return float(2 * student_t.sf(abs(effect.change) / se, effect.woods - 1))


def paired_change(ref, other, *, n_boot: int = N_BOOT, seed: int = 0,
                  estimator: str = HALF_MAX) -> tuple[np.ndarray, np.ndarray]:
    """``other`` against ``ref``, two traces of the same rays (each (theta_r, theta_l, transmitted),
    1-D over the rays, ray i the same entry point in both): the change of FWHM_R and FWHM_L (% of
    ``ref``'s, by ``estimator``) and of haze (points), and its 95 % interval from a bootstrap
    drawing the same rays for both.  Returns (change (3,), interval (3, 2))."""
    rng = np.random.default_rng(seed)
    n = len(ref[0])

    def change(idx):
        a = reduce_rays(ref[0], ref[1], ref[2], idx, estimator)
        b = reduce_rays(other[0], other[1], other[2], idx, estimator)
        return np.array([100 * (b[0] / a[0] - 1), 100 * (b[1] / a[1] - 1), 100 * (b[2] - a[2])])

    point = change(np.arange(n))
    boots = np.array([change(rng.integers(0, n, n)) for _ in range(n_boot)])
    return point, np.array([percentile_interval(boots[:, j], LEVEL) for j in range(3)])


def per_ray(ds, name: str) -> np.ndarray:
    """A per-ray variable as (value, realisation, ray), a study of one realisation included."""
    da = ds[name]
    if "realisation" not in da.dims:
        da = da.expand_dims(realisation=1, axis=1)
    return da.transpose(study_dimension(ds), "realisation", "ray").values

@dataclass
class Effect:
    study: str
    parameter: str
    value: str
    reference: str
    quantity: str  # FWHM_R, FWHM_L or haze
    change: float  # % of the reference for FWHM, points for haze
    ci: tuple[float, float]
    woods: int = 1  # the woods the interval resampled (Student t on woods - 1 d.o.f.)

    @property
    def resolved(self) -> bool:
        return self.ci[0] > 0 or self.ci[1] < 0

def effects(name: str, ds, *, n_boot: int = N_BOOT, seed: int = 0) -> list[Effect]:
    """Each value of a study against its reference value: the change of FWHM_R and FWHM_L
    (% of the reference) and of haze (points), with paired 95 % intervals from a bootstrap
    that draws wood realisations with replacement, each with all its rays (one wood: its rays
    with replacement), and reduces every value on that draw.  Every value is traced on the same
    realisations (seeds) with the same beam (ray i enters at the same point), so the draw pairs
    them, and the interval holds the wood-to-wood variation of the difference as well as the
    ray sampling."""
    codes = dict(zip(ds["status"].attrs.get("flag_values", []), ds["status"].attrs.get("flag_meanings", "").split()))
    if codes.get(TRANSMITTED) != "transmitted":
        raise ValueError(f"{name}: status code {TRANSMITTED} is not 'transmitted' in this Dataset ({codes})")
    dim = study_dimension(ds)
    tr, tl, st = per_ray(ds, "theta_r"), per_ray(ds, "theta_l"), per_ray(ds, "status")
    n_values, n_real, n_rays = tr.shape
    ok = st == TRANSMITTED
    everything = [(r, np.arange(n_rays)) for r in range(n_real)]
    point = np.array([reduce_rays(tr[k], tl[k], ok[k], everything) for k in range(n_values)])
    # The stored numbers are this reduction of these rays.
    stored = np.stack([ds["FWHM_R"].values, ds["FWHM_L"].values, ds["haze"].values], axis=1)
    if not np.allclose(point, stored, rtol=1e-6, atol=1e-9):
        raise ValueError(f"{name}: the rays do not reduce to the stored FWHM and haze")
    rng = np.random.default_rng(seed)
    boots = np.array(resampled(rng, n_real, n_rays, n_boot,
                               lambda idx: [reduce_rays(tr[k], tl[k], ok[k], idx) for k in range(n_values)]),
                     dtype=np.float64).reshape(n_boot, n_values, 3)
    ref = reference_index(ds)
    out = []
    for k in range(n_values):
        if k == ref:
            continue
        for q, quantity in enumerate(("FWHM_R", "FWHM_L", "haze")):
            if quantity == "haze":
                diff, dist = 100 * (point[k, q] - point[ref, q]), 100 * (boots[:, k, q] - boots[:, ref, q])
            else:
                diff = 100 * (point[k, q] / point[ref, q] - 1)
                dist = 100 * (boots[:, k, q] / boots[:, ref, q] - 1)
            out.append(Effect(name, dim, value_label(ds[dim].values[k]), value_label(ds[dim].values[ref]),
                              quantity, float(diff), interval(diff, dist, n_real), n_real))
    return out

def all_effects_of(tables: dict, *, n_boot: int = N_BOOT) -> dict:
    """{study: effects} of every study, one process per core (each study's bootstrap has its own
    seeded stream, so the numbers do not depend on how many processes run them)."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    names = list(tables)
    workers = min(len(names), os.cpu_count() or 1)
    if workers == 1:
        return {name: effects(name, tables[name], n_boot=n_boot) for name in names}
    # Spawned, not forked: the caller may hold threads (a Dask client, Numba's pool).
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        done = pool.map(_effects_job, [(name, tables[name], n_boot) for name in names])
        return dict(zip(names, done))

def _effects_job(job) -> list:
    name, ds, n_boot = job
    return effects(name, ds, n_boot=n_boot)

def table1_rows(tables: dict) -> list[dict]:
    """One row per value of every study: the numbers the report prints, unrounded."""
    rows = []
    for name, ds in tables.items():
        dim = study_dimension(ds)
        for k in range(ds.sizes[dim]):
            one = ds.isel({dim: k})
            rows.append({
                "study": name, "parameter": dim, "value": value_label(ds[dim].values[k]),
                "FWHM_R": float(one["FWHM_R"]), "FWHM_R_ci": (float(one["FWHM_R_ci_lower"]),
                                                             float(one["FWHM_R_ci_upper"])),
                "FWHM_L": float(one["FWHM_L"]), "FWHM_L_ci": (float(one["FWHM_L_ci_lower"]),
                                                             float(one["FWHM_L_ci_upper"])),
                "haze": 100 * float(one["haze"]), "haze_ci": (100 * float(one["haze_ci_lower"]),
                                                              100 * float(one["haze_ci_upper"])),
                "transmitted": int(one["n_transmitted"]), "rays": ds.sizes["ray"] * ds.sizes.get("realisation", 1),
                "interfaces_per_ray": float(one["interfaces_per_ray"]),
                "FWHM_R_each": _each(one, "FWHM_R"), "FWHM_L_each": _each(one, "FWHM_L"),
                "haze_each": 100 * _each(one, "haze"),
                "FWHM_R_ray_ci": (float(one["FWHM_R_ray_ci_lower"]), float(one["FWHM_R_ray_ci_upper"]))
                if "FWHM_R_ray_ci_lower" in one else (float(one["FWHM_R_ci_lower"]), float(one["FWHM_R_ci_upper"])),
                # Variance components: (SD between woods, SD of one wood's value from its rays).
                "components": {q: (float(one[f"{q}_sd_between_woods"]), float(one[f"{q}_sd_rays_per_wood"]))
                               for q in ("FWHM_R", "haze") if f"{q}_sd_between_woods" in one},
            })
    return rows

def _each(one, name: str) -> np.ndarray:
    """Each realisation's value of ``name`` (one value of a study)."""
    each = f"{name}_per_realisation"
    return np.atleast_1d(one[each].values if each in one else one[name].values).astype(float)

def method_rows(tables: dict, other: dict, *, n_boot: int = N_BOOT, seed: int = 0) -> list[dict]:
    """Every Table 1 value traced with two methods (``tables``: the reference, ``other``: the
    compared one, each dataset's ``trace_settings`` naming its method): both pooled, and their
    paired difference (% of the reference; haze in points) on the rays both traced (the same woods,
    the same entry points: ray i of a beam enters at the same point whatever the total), from a
    hierarchical bootstrap drawing the same woods and rays for both methods.  Keys ``<q>_ref``,
    ``<q>_other`` (each method pooled over those common rays), ``<q>_change``; ``ref`` and ``other``
    are the methods' names."""
    rng = np.random.default_rng(seed)
    rows = []
    for name, acc in tables.items():
        pap = other[name]
        dim = study_dimension(acc)
        arrays = [[per_ray(d, v) for v in ("theta_r", "theta_l", "status")] for d in (acc, pap)]
        n_real = min(arrays[0][0].shape[1], arrays[1][0].shape[1])
        n = min(arrays[0][0].shape[2], arrays[1][0].shape[2])
        for k in range(acc.sizes[dim]):
            cut = [[x[k, :n_real, :n] for x in arr] for arr in arrays]
            every = [(r, np.arange(n)) for r in range(n_real)]
            point = [reduce_rays(c[0], c[1], c[2] == TRANSMITTED, every) for c in cut]

            def change(idx, cut=cut):
                pa, pp = (reduce_rays(c[0], c[1], c[2] == TRANSMITTED, idx) for c in cut)
                return [100 * (pp[0] / pa[0] - 1), 100 * (pp[1] / pa[1] - 1), 100 * (pp[2] - pa[2])]
            boots = np.array(resampled(rng, n_real, n, n_boot, change))
            diff = [100 * (point[1][0] / point[0][0] - 1), 100 * (point[1][1] / point[0][1] - 1),
                    100 * (point[1][2] - point[0][2])]
            rows.append({
                "study": name, "parameter": dim, "value": value_label(acc[dim].values[k]),
                "ref": method_of(acc), "other": method_of(pap),
                # Both methods on the rays both traced (a study may have more woods or rays than the other).
                **{f"{q}_{m}": float(point[i][j]) * (100 if q == "haze" else 1)
                   for j, q in enumerate(("FWHM_R", "FWHM_L", "haze")) for i, m in enumerate(("ref", "other"))},
                **{f"{q}_change": (diff[j], interval(diff[j], boots[:, j], n_real))
                   for j, q in enumerate(("FWHM_R", "FWHM_L", "haze"))},
                "rays_other": pap.sizes["ray"], "rays_common": n, "realisations_common": n_real,
            })
    return rows

def method_of(ds) -> str:
    """The trace method a study dataset was traced with."""
    return json.loads(ds.attrs["trace_settings"])["method"]

EXPERIMENT = ("birch-0.7mm", "balsa-1mm")

def experiment_rows(base: Path) -> list[dict]:
    """The two measured samples: haze and widths inside the sample and in air, per wall value."""
    rows = []
    for name in EXPERIMENT:
        inside = open_dataset(base / "experiment" / f"{name}.zarr")
        air = open_dataset(base / "experiment" / f"{name}-air.zarr")
        dim = study_dimension(inside)
        for k in range(inside.sizes[dim]):
            one, out = inside.isel({dim: k}), air.isel({dim: k})
            scene = json.loads(inside.attrs["scenes"])[k]
            rows.append({
                "sample": name, "wood": scene["wood"]["species"], "thickness_mm": scene["thickness_um"] / 1000,
                "wall_um": scene["wood"]["wall_thickness_um"], "fibre_um": scene["wood"]["fibre_diameter_um"],
                "realisations": inside.sizes.get("realisation", 1), "rays": inside.sizes["ray"],
                **{f"{q}_{where}": (100 if q == "haze" else 1) * float(d[q]) for q in ("haze", "FWHM_R", "FWHM_L")
                   for where, d in (("inside", one), ("air", out))},
                **{f"{q}_{where}_ci": tuple((100 if q == "haze" else 1) * float(d[f"{q}_ci_{b}"])
                                            for b in ("lower", "upper"))
                   for q in ("haze", "FWHM_R") for where, d in (("inside", one), ("air", out))},
                "haze_air_each": 100 * _each(out, "haze"),
            })
    return rows

FIBRE_TIPS = ("with-ray-cells", "without-ray-cells")

def fibre_tip_rows(base: Path, *, n_boot: int = N_BOOT) -> list[dict]:
    """The fibre-tip studies (with and without ray cells): each tip length pooled, and its change
    against flat fibre ends (the study's first value) as a paired hierarchical bootstrap."""
    rows = []
    for name in FIBRE_TIPS:
        ds = open_dataset(base / "fibre-tips" / f"{name}.zarr")
        dim = study_dimension(ds)
        changes = {(e.value, e.quantity): e for e in effects(name, ds, n_boot=n_boot)}
        scenes = json.loads(ds.attrs["scenes"])
        for k in range(ds.sizes[dim]):
            one, value = ds.isel({dim: k}), value_label(ds[dim].values[k])
            rows.append({
                "study": name, "ray_cells": bool(scenes[k]["wood"]["ray_cells"]),
                "tip_um": float(ds[dim].values[k]), "angle_deg": tip_wall_angle_deg(WoodParams.from_dict(scenes[k]["wood"])),
                "realisations": ds.sizes.get("realisation", 1), "rays": ds.sizes["ray"],
                "interfaces_per_ray": float(one["interfaces_per_ray"]),
                **{q: (100 if q == "haze" else 1) * float(one[q]) for q in ("FWHM_R", "FWHM_L", "haze")},
                **{f"{q}_ci": tuple((100 if q == "haze" else 1) * float(one[f"{q}_ci_{b}"])
                                    for b in ("lower", "upper")) for q in ("FWHM_R", "FWHM_L", "haze")},
                "change": {q: changes.get((value, q)) for q in ("FWHM_R", "FWHM_L", "haze")},
            })
    return rows

# ------------------------------------------------------------------ camera, trade-off, costs
def camera_rows(ds) -> list[dict]:
    rows = []
    for name in [str(c) for c in ds["config"].values]:
        one = ds.sel(config=name)
        q = image_quality(one["image"].values, one["ideal"].values)
        rows.append({"config": name, "focal_mm": float(one["focal_mm"]), "gap_um": float(one["gap_um"]),
                     "delta_ri": float(one["delta_ri"]), "object": str(one["object"].values),
                     "object_size_mm": float(one["object_size_mm"]),
                     "interfaces_per_ray": float(one["interfaces_per_ray"]), **q})
    return rows

# Precision targets of the speed/accuracy trade: (name, haze error [points], FWHM_R relative error).
TRADEOFF_TARGETS = [
    ("haze ±1 point, FWHM_R ±5 %", 1.0, 0.05),
    ("haze ±3 points, FWHM_R ±10 %", 3.0, 0.10),
    ("haze ±5 points, FWHM_R ±25 %", 5.0, 0.25),
]

def setting_label(method: str, voxel_um: float, rays: int, step_vox: float = float("nan")) -> str:
    """How a swept trace setting is named in tables: method, voxel (none for `exact`), rays, step."""
    where = "" if method == "exact" else f" at {voxel_um:g} µm"
    step = f", step {step_vox:g}" if method == "paper" else ""
    return f"`{method}`{where}, {rays} rays{step}"


def cheapest_meeting(rows: list[dict], haze_points: float, fwhm_rel: float) -> dict | None:
    """The row of least cold wall time (``wall_s``) whose total errors meet the target, or None.

    Rows carry ``haze_error`` (fraction) and ``fwhm_r_rel_error`` (FWHM_R error / reference).
    """
    ok = [r for r in rows if 100 * r["haze_error"] <= haze_points and abs(r["fwhm_r_rel_error"]) <= fwhm_rel]
    return min(ok, key=lambda r: r["wall_s"]) if ok else None

FINE = ("study-5-1", "convergence/study-5-1-0.125um")  # the study, and it traced on 0.125 µm voxels

def fine_voxel_rows(results: Path, *, n_boot: int = N_BOOT, seed: int = 0) -> list[dict]:
    """Study 5-1, wood realisation 0, traced on 0.5 (results/convergence.zarr), 0.25 (the
    study) and 0.125 µm voxels: FWHM_L at each, and the change from 0.25 to 0.125 µm with a
    paired bootstrap over rays (the same entry points).  Empty when the 0.125 µm run is missing."""
    results = Path(results)
    fine_path = results / "paper" / f"{FINE[1]}.zarr"
    conv_path = results / "convergence.zarr"
    if not (fine_path.exists() and conv_path.exists()):
        return []
    table1 = open_dataset(results / "paper" / f"{FINE[0]}.zarr")
    voxels = results / "paper" / "accurate" / f"{FINE[0]}.zarr"  # where Table 1 itself is exact
    study = open_dataset(voxels) if method_of(table1) == "exact" and voxels.exists() else table1
    exact = table1 if method_of(table1) == "exact" else None
    fine, conv = open_dataset(fine_path), open_dataset(conv_path)
    labels = list(conv["value"].values)
    mine = [i for i, label in enumerate(labels) if label.startswith(FINE[0] + " ")]  # the study's values, in order
    rng = np.random.default_rng(seed)
    rows = []
    dim = study_dimension(study)
    for k in range(study.sizes[dim]):
        a, b = ([per_ray(d, v)[k, 0] for v in ("theta_r", "theta_l")] + [per_ray(d, "status")[k, 0] == TRANSMITTED]
                for d in (study, fine))
        every = np.arange(a[0].size)
        pa = reduce_rays(*a, every)
        pb = reduce_rays(*b, every)
        change, ci = paired_change(a, b, n_boot=n_boot, seed=int(rng.integers(2**31)))
        coarse = float(conv["FWHM_L_voxel_0.5"].values[mine[k]])
        if exact is not None:  # the same wood and rays, traced exactly
            e = [per_ray(exact, v)[k, 0] for v in ("theta_r", "theta_l", "status")]
            exact_l = float(reduce_rays(e[0], e[1], e[2] == TRANSMITTED, every)[1])
        rows.append({"value": value_label(study[dim].values[k]), "FWHM_L_0.5": coarse, "FWHM_L_0.25": float(pa[1]),
                     "FWHM_L_exact": exact_l if exact is not None else None,
                     "FWHM_L_0.125": float(pb[1]), "change": float(change[1]), "ci": (float(ci[1, 0]), float(ci[1, 1])),
                     "FWHM_R_change": float(100 * (pb[0] / pa[0] - 1)), "haze_change": float(100 * (pb[2] - pa[2]))})
    return rows
