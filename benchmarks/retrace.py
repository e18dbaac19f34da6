"""Old -> new for study datasets retraced with a new tracer version (docs/performance.md#retracing).

For each dataset present in both folders (matched by relative path), on the woods both traced:

* per ray: how many exit directions moved by more than 1e-9 rad, 1e-6 rad and 1e-3 rad (the exit
  angles theta_r and theta_l, in degrees in the dataset), how many changed status or interface count;
* per camera image: the RMS of the pixel differences against the most two independent renders
  would differ by;
* per published number (FWHM_R, FWHM_L and haze at each parameter value): the old and new values and
  the paired difference new - old over the woods both traced, with its 95 % interval (Student t on
  R - 1 degrees of freedom of the per-wood differences) and whether it is resolved (excludes zero);
  how many are resolved, against the 5 % expected by chance, and at a family-wise 95 % (Holm).

    python benchmarks/retrace.py --old OLD_RESULTS --new results/paper --out results/RETRACE.md

OLD_RESULTS is typically a worktree of the commit before the version change
(``git worktree add /tmp/old <rev>``, then ``/tmp/old/results/paper``).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import xarray as xr
from scipy import stats

from pipeline.effects import LEVEL, holm_resolved

NUMBERS = (("FWHM_R", "°"), ("FWHM_L", "°"), ("haze", "%"))
MOVED = (1e-9, 1e-6, 1e-3)  # [rad]


def _open(path: Path) -> xr.Dataset:
    return xr.open_zarr(path, decode_timedelta=False).load()


def _common(old: xr.Dataset, new: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Indices into old's and new's realisations of the woods (seeds) both traced."""
    key = "seed_of_realisation" if "seed_of_realisation" in old.coords else "realisation"
    so = old[key].values
    sn = new[key].values
    both = np.intersect1d(so, sn)
    return (np.array([int(np.flatnonzero(so == s)[0]) for s in both], int),
            np.array([int(np.flatnonzero(sn == s)[0]) for s in both], int))


def per_ray(old: xr.Dataset, new: xr.Dataset) -> dict:
    """Counts of rays whose exit moved, over the woods both traced, at every parameter value."""
    io, jn = _common(old, new)
    oa = old.isel(realisation=io)
    na = new.isel(realisation=jn)
    dr = np.radians(np.abs(na["theta_r"].values - oa["theta_r"].values))
    dl = np.radians(np.abs(na["theta_l"].values - oa["theta_l"].values))
    both_t = (oa["status"].values == 1) & (na["status"].values == 1)
    moved = np.where(both_t, np.fmax(dr, dl), 0.0)
    status = oa["status"].values != na["status"].values
    out = {"rays": int(moved.size), "status_changed": int(status.sum())}
    for t in MOVED:
        out[f"moved_over_{t:g}_rad"] = int(((moved > t) | status).sum())
    if "n_interfaces" in old and "n_interfaces" in new:
        out["interfaces_changed"] = int((oa["n_interfaces"].values != na["n_interfaces"].values).sum())
    return out


def paired(old: xr.Dataset, new: xr.Dataset, name: str) -> list[dict]:
    """Per parameter value (every cell of ``name``'s dimensions): old, new and the paired difference
    of ``name`` with its 95 % interval and p-value."""
    io, jn = _common(old, new)
    var = f"{name}_per_realisation"
    dims = old[name].dims
    scale = 100.0 if name == "haze" else 1.0
    rows = []
    for idx in np.ndindex(*old[name].shape):
        at = dict(zip(dims, idx))
        a = old[var].isel(at).values[io].astype(float)
        b = new[var].isel(at).values[jn].astype(float)
        ok = np.isfinite(a) & np.isfinite(b)
        d = (b - a)[ok]
        r = len(d)
        mean = float(d.mean()) * scale if r else math.nan
        se = float(d.std(ddof=1) / math.sqrt(r)) * scale if r > 1 else math.nan
        half = float(stats.t.ppf(0.5 + LEVEL / 2, r - 1)) * se if r > 1 else math.nan
        pval = (float(2.0 * stats.t.sf(abs(mean) / se, r - 1)) if se > 0 else (1.0 if mean == 0 else 0.0)) \
            if r > 1 else math.nan
        label = ", ".join(f"{dim} {float(old[dim].values[i]):g}"
                          if old[dim].dtype.kind in "fiu" else f"{dim} {old[dim].values[i]}" for dim, i in at.items())
        rows.append({"value": label, "old": float(old[name].values[idx]) * scale,
                     "new": float(new[name].values[idx]) * scale, "woods": r, "diff": mean, "half": half, "p": pval,
                     "resolved": bool(r > 1 and half == half and abs(mean) > half)})
    return rows


def images(old: xr.Dataset, new: xr.Dataset) -> list[dict]:
    """Per camera configuration: the RMS of the pixel differences new - old against what two
    independent renders would give at most (each pixel a mean of ``samples_per_pixel`` samples of
    an object read in [0, 1]: a variance of at most p(1 - p)/N each), and the mean difference."""
    n = int(new.attrs["samples_per_pixel"])
    rows = []
    for c in new["config"].values:
        a = old["image"].sel(config=c).values.astype(float)
        b = new["image"].sel(config=c).values.astype(float)
        p = 0.5 * (a + b)
        noise = math.sqrt(float(np.mean(2.0 * p * (1.0 - p) / n)))
        rms = math.sqrt(float(np.mean((b - a) ** 2)))
        rows.append({"config": str(c), "rms": rms, "independent_rms": noise,
                     "ratio": rms / noise if noise > 0 else math.nan, "mean_diff": float(np.mean(b - a)),
                     "equal_pixels": int((a == b).sum()), "pixels": int(a.size)})
    return rows


def compare(old_dir: Path, new_dir: Path) -> dict:
    result = {}
    for new_path in sorted(new_dir.rglob("*.zarr")):
        rel = new_path.relative_to(new_dir)
        old_path = old_dir / rel
        if not old_path.exists():
            continue
        new = _open(new_path)
        if (new.attrs.get("tracing_method") != "exact" or not ({"realisation", "config"} & set(new.dims))
                or not ({"theta_r", "image"} & set(new.data_vars))):
            continue
        old = _open(old_path)
        if old.attrs.get("tracer_version") == new.attrs.get("tracer_version"):
            continue  # not retraced
        if "image" in new and "config" in new.dims:
            result[str(rel)] = {"tracer": f"{old.attrs.get('tracer_version')} -> {new.attrs.get('tracer_version')}",
                                "images": images(old, new)}
            continue
        entry = {"tracer": f"{old.attrs.get('tracer_version')} -> {new.attrs.get('tracer_version')}",
                 "per_ray": per_ray(old, new)}
        for name, _ in NUMBERS:
            if f"{name}_per_realisation" in old and f"{name}_per_realisation" in new:
                entry[name] = paired(old, new, name)
        result[str(rel)] = entry
    return result


def markdown(result: dict) -> str:
    lines = ["# Old -> new after a tracer version change", "",
             "Generated by `benchmarks/retrace.py` (docs/performance.md#retracing). Rays: exit directions of "
             "rays transmitted in both traces that moved by more than the given angle, a changed status counting "
             "as moved. Numbers: the published value before and after, and the paired difference new − old over "
             "the woods both traced with its 95 % interval (t on R − 1 d.o.f. of the per-wood differences); "
             "**resolved** where the interval excludes zero.", "",
             "## Rays", "",
             "| dataset | tracer | rays | moved > 1e-9 rad | > 1e-6 rad | > 1e-3 rad | status changed | interface count changed |",
             "|---|---|---|---|---|---|---|---|"]
    for name, e in result.items():
        if "per_ray" not in e:
            continue
        p = e["per_ray"]
        lines.append(f"| {name} | {e['tracer']} | {p['rays']} | {p['moved_over_1e-09_rad']} | "
                     f"{p['moved_over_1e-06_rad']} | {p['moved_over_0.001_rad']} | {p['status_changed']} | "
                     f"{p.get('interfaces_changed', '')} |")
    cams = {k: e for k, e in result.items() if "images" in e}
    if cams:
        lines += ["", "## Images", "",
                  "RMS of the pixel differences against the most two independent renders of the same samples a "
                  "pixel would differ by (an object read in [0, 1]: a variance of at most p(1 − p)/N a render and "
                  "pixel).", "",
                  "| dataset | tracer | image | pixels equal | RMS new − old | RMS of independent renders | ratio | mean new − old |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, e in cams.items():
            for r in e["images"]:
                lines.append(f"| {name} | {e['tracer']} | {r['config']} | {r['equal_pixels']} of {r['pixels']} | "
                             f"{r['rms']:.4f} | {r['independent_rms']:.4f} | {r['ratio']:.2f} | {r['mean_diff']:+.4f} |")
    rows = [r for e in result.values() for n, _ in NUMBERS for r in e.get(n, [])]
    resolved = sum(r["resolved"] for r in rows)
    lines += ["", "## Published numbers", "",
              f"{resolved} of {len(rows)} paired differences resolved at 95 % each (about "
              f"{0.05 * len(rows):.1f} expected by chance alone where nothing moved but the rays' sampling); "
              f"{holm_resolved(r['p'] for r in rows)} resolved at a family-wise 95 % (Holm).", ""]
    for name, e in result.items():
        if "per_ray" not in e:
            continue
        lines += [f"### {name}", "",
                  "| value | number | unit | old | new | new − old [95 % CI] | woods | resolved |",
                  "|---|---|---|---|---|---|---|---|"]
        for num, unit in NUMBERS:
            for r in e.get(num, []):
                lines.append(f"| {r['value']} | {num} | {unit} | {r['old']:.3f} | {r['new']:.3f} | "
                             f"{r['diff']:+.3f} ± {r['half']:.3f} | {r['woods']} | {'**yes**' if r['resolved'] else 'no'} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, required=True, help="results folder before the version change")
    ap.add_argument("--new", type=Path, required=True, help="results folder after it")
    ap.add_argument("--out", type=Path, required=True, help="markdown table to write (a .json beside it)")
    a = ap.parse_args(argv)
    result = compare(a.old, a.new)
    a.out.write_text(markdown(result))
    a.out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    print(f"wrote {a.out} ({len(result)} datasets)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
