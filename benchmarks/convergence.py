"""Is Table 1 converged?  How far each value moves with more rays and with a finer voxel.

For every Table 1 value, on wood realisation 0 (seed 1) at paper scale, against the
study traced with ``accurate`` (``results/paper/accurate/``: the 0.5 µm study voxel traced on
0.25 µm, 1000 rays; Table 1 itself is now ``exact``, which has neither voxel nor this question):

- ``rays_4x``: 4 times the rays, 4000 (the first 1000 are the committed ones, reused from the cache);
- ``voxel_0.5``: the wood traced on 0.5 µm voxels (``refine`` 1), 1000 rays, the same
  entry points.

Each change is a paired bootstrap over rays (200 draws; the same ray indices for both
settings).  The voxel change says how far the committed values are from a voxel twice
as coarse; with an error that falls about as the voxel (results/accuracy.md), the
committed 0.25 µm values are off from the limit by about the same amount again.

Writes ``results/convergence.zarr`` and ``results/CONVERGENCE.md`` (``make convergence``;
with a warm cache of ``make table1`` it traces 3000 more rays per value and every Table 1
wood once more at 0.5 µm).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.effects import reduce_rays  # noqa: E402
from pipeline.result_sets import TABLE1  # noqa: E402
from pipeline.study.graph import compute  # noqa: E402
from pipeline.study.plan import plan_study  # noqa: E402
from pipeline.study.tasks import load_rays  # noqa: E402
from pipeline.study.spec import load_study, with_rays  # noqa: E402

N_BOOT = 200
VARIANTS = ("baseline", "rays_4x", "voxel_0.5")


def studies_of(scale: str) -> dict:
    """Table 1's studies on wood realisation 0, traced with the voxel method Table 1 was traced with
    before `exact` (results/paper/accurate/): what its voxel and its rays leave unconverged."""
    return {name: load_study(ROOT / "studies" / "table1" / f"{name}.yaml", scale=scale, realisations=1,
                             method="accurate") for name in TABLE1}


def variant(study, name: str):
    if name == "rays_4x":
        return with_rays(study, 4 * study.scenes[0].rays)
    if name == "voxel_0.5":
        return dataclasses.replace(study, scenes=tuple(
            dataclasses.replace(s, settings=dataclasses.replace(s.settings, voxel=dataclasses.replace(
                s.settings.voxel, refine=1))) for s in study.scenes))
    return study


def angles(plan, i: int):
    """(θ_R, θ_L, transmitted) of value ``i`` of a one-realisation plan."""
    summ = next(s for s in plan.summaries if s.scene_index == i)
    r, _ = load_rays(plan.shards_of(summ), plan.study.realisation(i, summ.realisation))
    return r.theta_r, r.theta_l, r.transmitted


def paired_change(base, other, n_common: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Change of (FWHM_R, FWHM_L) in % and haze in points of ``other`` against ``base``, with
    95 % paired bootstrap intervals (rays ``[0, n_common)`` drawn alike for both, the rest
    of the larger beam drawn on its own)."""
    point = [reduce_rays(*b[:2], b[2], np.arange(b[2].size)) for b in (base, other)]

    def delta(a, b):
        return np.array([100 * (b[0] / a[0] - 1), 100 * (b[1] / a[1] - 1), 100 * (b[2] - a[2])])

    boots = []
    for _ in range(N_BOOT):
        common = rng.integers(0, n_common, n_common)
        extra = other[2].size - n_common
        idx_o = np.concatenate([common, n_common + rng.integers(0, extra, extra)]) if extra else common
        a = reduce_rays(*base[:2], base[2], common if base[2].size == n_common else idx_o)
        b = reduce_rays(*other[:2], other[2], idx_o)
        boots.append(delta(a, b))
    boots = np.array(boots)
    return delta(*point), np.quantile(boots, [0.025, 0.975], axis=0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(ROOT / "results" / "cache"))
    ap.add_argument("--results", default=str(ROOT / "results"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scale", default="paper", help="paper (the committed Table 1) or small (a quick check)")
    args = ap.parse_args(argv)
    import xarray as xr
    from distributed import Client, LocalCluster

    studies = studies_of(args.scale)
    plans = {(name, v): plan_study(variant(st, v), args.cache) for name, st in studies.items() for v in VARIANTS}
    t0 = time.perf_counter()
    todo = [p for p in plans.values() if not p.up_to_date]
    if todo:
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            compute(todo, client, progress="lines")
        plans = {k: plan_study(p.study, args.cache) for k, p in plans.items()}
    seconds = time.perf_counter() - t0
    rows, values = [], {v: [] for v in VARIANTS}
    change = {v: [] for v in VARIANTS[1:]}
    lo_hi = {v: [] for v in VARIANTS[1:]}
    rng = np.random.default_rng(0)
    for name, st in studies.items():
        for i in range(len(st.scenes)):
            rows.append(f"{name} {st.dimension}={st.coordinate()[i]}")
            got = {v: angles(plans[name, v], i) for v in VARIANTS}
            for v in VARIANTS:
                values[v].append(reduce_rays(*got[v][:2], got[v][2], np.arange(got[v][2].size)))
            for v in VARIANTS[1:]:
                d, ci = paired_change(got["baseline"], got[v], got["baseline"][2].size, rng)
                change[v].append(d)
                lo_hi[v].append(ci)
    quantities = ["FWHM_R", "FWHM_L", "haze"]
    data = {}
    for v in VARIANTS:
        arr = np.array(values[v])
        for q, name in enumerate(quantities):
            data[f"{name}_{v}"] = ("value", arr[:, q] * (100 if name == "haze" else 1),
                                   {"units": "percent" if name == "haze" else "degree"})
    for v in VARIANTS[1:]:
        d, ci = np.array(change[v]), np.array(lo_hi[v])
        for q, name in enumerate(quantities):
            unit = "percentage points" if name == "haze" else "percent of the committed value"
            data[f"{name}_change_{v}"] = ("value", d[:, q], {"units": unit})
            data[f"{name}_change_{v}_ci_lower"] = ("value", ci[:, 0, q], {"units": unit})
            data[f"{name}_change_{v}_ci_upper"] = ("value", ci[:, 1, q], {"units": unit})
    ds = xr.Dataset(data, coords={"value": ("value", np.array(rows, dtype=object))},
                    attrs={"title": "convergence of Table 1 (realisation 0, paper scale)",
                           "seconds": seconds, "bootstrap_resamples": N_BOOT,
                           "variants": "baseline: accurate, 0.25 µm traced voxel, the study's rays; rays_4x: 4x the rays; "
                                       "voxel_0.5: 0.5 µm traced voxel (refine 1)"})
    out = Path(args.results)
    from pipeline.publish import write_zarr

    import shutil

    stem = "convergence" if args.scale == "paper" else f"convergence-{args.scale}"
    shutil.rmtree(out / f"{stem}.zarr", ignore_errors=True)
    ds.attrs["scale"] = args.scale
    write_zarr(ds, out / f"{stem}.zarr")
    (out / f"{stem.upper()}.md").write_text(markdown(ds))
    print(f"wrote {out / (stem + '.zarr')} and {out / (stem.upper() + '.md')} ({seconds:.0f} s)")
    return 0


def _cell(ds, name, v, k, unit):
    d = float(ds[f"{name}_change_{v}"][k])
    lo, hi = float(ds[f"{name}_change_{v}_ci_lower"][k]), float(ds[f"{name}_change_{v}_ci_upper"][k])
    mark = "" if lo > 0 or hi < 0 else " ·"
    return f"{d:+.1f}{unit} [{lo:+.1f}, {hi:+.1f}]{mark}"


def markdown(ds) -> str:
    lines = ["# Is Table 1 converged?", "",
             "Generated by `make convergence` (`benchmarks/convergence.py`). "
             f"Every Table 1 value on wood realisation 0 (seed 1) at scale {ds.attrs.get('scale', 'paper')}, "
             "against the committed setting "
             "(`accurate`, wood traced on 0.25 µm voxels, the study's rays): the change with 4× the rays, and "
             "with the wood traced on 0.5 µm voxels. Paired bootstrap 95 % intervals over rays; · marks a change whose "
             "interval contains 0.", "",
             "| value | FWHM_R (°) | 4× rays: FWHM_R | 0.5 µm: FWHM_R | 4× rays: FWHM_L | 0.5 µm: FWHM_L "
             "| 4× rays: haze | 0.5 µm: haze |", "|---|---|---|---|---|---|---|---|"]
    for k, row in enumerate(ds["value"].values):
        lines.append(f"| {row} | {float(ds['FWHM_R_baseline'][k]):.2f} | "
                     f"{_cell(ds, 'FWHM_R', 'rays_4x', k, ' %')} | {_cell(ds, 'FWHM_R', 'voxel_0.5', k, ' %')} | "
                     f"{_cell(ds, 'FWHM_L', 'rays_4x', k, ' %')} | {_cell(ds, 'FWHM_L', 'voxel_0.5', k, ' %')} | "
                     f"{_cell(ds, 'haze', 'rays_4x', k, ' pts')} | {_cell(ds, 'haze', 'voxel_0.5', k, ' pts')} |")
    r = np.abs(ds["FWHM_R_change_rays_4x"].values)
    v = np.abs(ds["FWHM_R_change_voxel_0.5"].values)
    hv = np.abs(ds["haze_change_voxel_0.5"].values)
    lines += ["", f"Median |change| of FWHM_R: {np.median(r):.1f} % with 4× the rays, {np.median(v):.1f} % at 0.5 µm; "
              f"of haze at 0.5 µm: {np.median(hv):.1f} points. "
              f"Traced in {float(ds.attrs['seconds']) / 60:.1f} min on this host.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
