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
WAVE_NUMBERS = (("FWHM_R_half_max_ray", "°"), ("haze_ray", "%"))  # the wave regime's ray side
LISTED = 60  # a dataset with more paired differences lists its resolved and its largest few
SHOWN = 5e-4  # a difference below this (in the number's unit) rounds away in the tables' three decimals
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
    scale = 100.0 if name.startswith("haze") else 1.0
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
        # Every wood moved alike (one ray across the haze cut in each, say): a zero spread gives the t
        # interval zero width, which says nothing; such a change is flagged, not resolved, and has no p.
        alike = bool(r > 1 and se == 0 and mean != 0)
        pval = (float(2.0 * stats.t.sf(abs(mean) / se, r - 1)) if se > 0 else (1.0 if mean == 0 else math.nan)) \
            if r > 1 else math.nan
        label = ", ".join(f"{dim} {float(old[dim].values[i]):g}"
                          if old[dim].dtype.kind in "fiu" else f"{dim} {old[dim].values[i]}" for dim, i in at.items())
        rows.append({"value": label, "old": float(old[name].values[idx]) * scale,
                     "new": float(new[name].values[idx]) * scale, "woods": r, "diff": mean, "half": half, "p": pval,
                     "resolved": bool(r > 1 and half == half and not alike and abs(mean) > half), "alike": alike,
                     "shown": bool(abs(mean) >= SHOWN)})
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


def wave(old: xr.Dataset, new: xr.Dataset) -> dict:
    """The wave regime's ray side (its waves are not traced): per ray-side number (per geometry, exit
    and ΔRI, over its woods) the paired difference; and how many verdicts "rays hold" changed."""
    entry = {}
    for name, _ in WAVE_NUMBERS:
        o = old[name].mean("realisation")
        n = new[name].mean("realisation")
        pair = xr.Dataset({name: o, f"{name}_per_realisation": old[name].transpose(*o.dims, "realisation")})
        pair_new = xr.Dataset({name: n, f"{name}_per_realisation": new[name].transpose(*n.dims, "realisation")})
        entry[name] = paired(pair.assign_coords(realisation=old["realisation"]),
                             pair_new.assign_coords(realisation=new["realisation"]), name)
    for verdict in ("rays_hold", "haze_holds"):
        if verdict in old and verdict in new:
            entry[f"{verdict}_changed"] = int((old[verdict].values != new[verdict].values).sum())
            entry[f"{verdict}_cells"] = int(old[verdict].size)
    return entry


def tradeoff(old: xr.Dataset, new: xr.Dataset) -> list[dict]:
    """The trade-off's `exact` points (one wood, its rays not kept): the reference numbers old and
    new beside the old point's own interval half-width (a difference within it is not resolved)."""
    rows = []
    for i in np.flatnonzero(new["method"].values == "exact"):
        match = np.flatnonzero((old["method"].values == "exact") & (old["scene"].values == new["scene"].values[i])
                               & (old["rays"].values == new["rays"].values[i]))
        if not len(match):
            continue
        j = int(match[0])
        for name, half, scale in (("FWHM_R", "FWHM_R_halfwidth", 1.0), ("haze", "haze_halfwidth", 100.0)):
            a, b = float(old[name].values[j]) * scale, float(new[name].values[i]) * scale
            h = float(old[half].values[j]) * scale
            rows.append({"value": f"{new['scene'].values[i]}, {int(new['rays'].values[i])} rays", "number": name,
                         "old": a, "new": b, "diff": b - a, "half": h, "within": bool(abs(b - a) <= h)})
    return rows


def compare(old_dir: Path, new_dir: Path) -> dict:
    result = {}
    for new_path in sorted(new_dir.rglob("*.zarr")):
        rel = new_path.relative_to(new_dir)
        old_path = old_dir / rel
        if not old_path.exists() or any(p.suffix == ".zarr" for p in rel.parents):
            continue
        new = _open(new_path)
        if "reference_haze" in new and "method" in new.coords:  # the speed/accuracy trade-off
            old = _open(old_path)
            rows = tradeoff(old, new)
            if any(r["diff"] != 0 for r in rows):
                was = json.loads(old.attrs.get("tracer_versions", "{}")).get("exact", "not recorded")
                now = json.loads(new.attrs.get("tracer_versions", "{}")).get("exact", "?")
                result[str(rel)] = {"tracer": f"{was} -> {now}", "tradeoff": rows}
            continue
        if (new.attrs.get("tracing_method") != "exact" or not ({"realisation", "config"} & set(new.dims))
                or not ({"theta_r", "image", "haze_ray"} & set(new.data_vars))):
            continue
        old = _open(old_path)
        if old.attrs.get("tracer_version") == new.attrs.get("tracer_version"):
            continue  # not retraced
        tracer = f"{old.attrs.get('tracer_version')} -> {new.attrs.get('tracer_version')}"
        if "image" in new and "config" in new.dims:
            result[str(rel)] = {"tracer": tracer, "images": images(old, new)}
            continue
        if "haze_ray" in new:
            result[str(rel)] = {"tracer": tracer, **wave(old, new)}
            continue
        entry = {"tracer": tracer, "per_ray": per_ray(old, new)}
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
    numbers = NUMBERS + WAVE_NUMBERS
    rows = [r for e in result.values() for n, _ in numbers for r in e.get(n, [])]
    resolved = sum(r["resolved"] for r in rows)
    tiny = sum(r["resolved"] and not r.get("shown", True) for r in rows)
    alike = sum(r.get("alike", False) for r in rows)
    lines += ["", "## Published numbers", "",
              f"{resolved} of {len(rows)} paired differences resolved at 95 % each (about "
              f"{0.05 * len(rows):.1f} expected by chance alone where nothing moved but the rays' sampling"
              f"{f'; {tiny} of them smaller than {SHOWN:g} in their unit, rounding that every wood shares' if tiny else ''}); "
              f"{holm_resolved(r['p'] for r in rows)} resolved at a family-wise 95 % (Holm)"
              f"{f'; {alike} moved by the same amount in every wood, which no interval over woods can judge (listed)' if alike else ''}. "
              f"A dataset with more "
              f"than {LISTED} lists those resolved and its {LISTED // 10} largest in units of their half-width; "
              "every one is in RETRACE.json.", ""]
    for name, e in result.items():
        own = [(num, unit, r) for num, unit in numbers for r in e.get(num, [])]
        if not own:
            continue
        lines += [f"### {name}", ""]
        if len(own) > LISTED:
            ratio = [abs(r["diff"]) / r["half"] if r["half"] > 0 else (0.0 if r["diff"] == 0 else math.inf)
                     for _, _, r in own]
            order = np.argsort(ratio)[::-1]
            keep = sorted({int(i) for i in order[:LISTED // 10]}
                          | {i for i, (_, _, r) in enumerate(own) if r["resolved"] or r.get("alike")})
            lines += [f"{len(own)} paired differences, {sum(r['resolved'] for _, _, r in own)} resolved; the "
                      f"largest |new − old| is {ratio[order[0]]:.2f} of its half-width.", ""]
            own = [own[i] for i in keep]
        for verdict in ("rays_hold", "haze_holds"):
            if f"{verdict}_changed" in e:
                lines += [f"Verdict `{verdict}` changed in {e[f'{verdict}_changed']} of {e[f'{verdict}_cells']} cells.", ""]
        lines += ["| value | number | unit | old | new | new − old [95 % CI] | woods | resolved |",
                  "|---|---|---|---|---|---|---|---|"]
        for num, unit, r in own:
            lines.append(f"| {r['value']} | {num} | {unit} | {r['old']:.3f} | {r['new']:.3f} | "
                         f"{r['diff']:+.3f} ± {r['half']:.3f} | {r['woods']} | {_resolved(r)} |")
        lines.append("")
    trade = {k: e for k, e in result.items() if "tradeoff" in e}
    for name, e in trade.items():
        lines += [f"### {name} (`exact` {e['tracer']})", "",
                  "The trade-off's `exact` points trace one wood and keep no rays, so no paired interval: the old "
                  "point's own 95 % half-width (over its rays) beside the change.", "",
                  "| point | number | old | new | new − old | old half-width | within it |", "|---|---|---|---|---|---|---|"]
        for r in e["tradeoff"]:
            unit = "%" if r["number"] == "haze" else "°"
            lines.append(f"| {r['value']} | {r['number']} [{unit}] | {r['old']:.3f} | {r['new']:.3f} | {r['diff']:+.3f} | "
                         f"{r['half']:.3f} | {'yes' if r['within'] else '**no**'} |")
        lines.append("")
    return "\n".join(lines)


def _resolved(r: dict) -> str:
    if r.get("alike"):
        return "alike in every wood (no spread)"
    if not r["resolved"]:
        return "no"
    return "**yes**" if r.get("shown", True) else f"yes, by under {SHOWN:g}"


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
