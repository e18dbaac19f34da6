"""Scans as accurate as the model? A grey-level scan of generated wood (its wall fraction per voxel,
supersampled; clean, and blurred with noise) traced with `iso`, and binarised at one half with
`accurate` and `fast`, beside `exact` on the same wood, beam and rays (docs/methods.md#iso-surfaces).

Per wood and method: FWHM_R, FWHM_L (half-max) and haze. Then, per scan and method, the difference
from `exact` (relative for the widths, in points for haze), its mean over the woods and a 95 %
t interval over them: each wood's difference carries that wood's ray sampling too, so the interval
holds both. Woods are traced in parallel processes. Writes JSON with --out.

    python benchmarks/bench_iso.py --preset birch --thickness-mm 0.25 --voxel-um 0.5 --woods 5 --rays 1000
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

SCANS = {"clean": (0.0, 0.0), "blur 0.3 µm + noise 0.02": (0.3, 0.02)}
METHODS = ("iso", "accurate", "fast")


def one_wood(seed: int, args) -> list[dict]:
    from pipeline.microstructure.grey import degrade, grey_volume
    from pipeline.optics.iso import IsoVolume
    from pipeline.optics.media import wood_medium
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.sources import ArraySource
    from pipeline.optics.trace import trace
    from pipeline.params import Grid, build_params
    from pipeline.summary import summarize

    params = build_params(args.preset)
    t_um = 1000.0 * args.thickness_mm
    optics = Optics.of_delta(1.49, args.delta_ri, seed=seed)
    rows = []

    def run(voxel, scan_name, method, medium, centre, t_scan=0.0):
        settings = settings_for(method, **({"refine": 1} if method in ("accurate", "fast") else {}))
        c0 = time.process_time()
        r = trace(medium, square_beam(args.rays, args.beam_um, centre, seed=seed), optics, settings)
        cpu = time.process_time() - c0
        s = summarize(r, seed=seed, n_boot=0)
        rows.append({"seed": seed, "voxel_um": voxel, "scan": scan_name, "method": method, "fwhm_r": s["fwhm_r_deg"],
                     "fwhm_l": s["fwhm_l_deg"], "haze": s["haze"], "transmitted": int(s["n_transmitted"]),
                     "interfaces": int(r.events.sum()), "cpu_s": cpu, "scan_s": t_scan})

    exact = settings_for("exact")
    run(None, "-", "exact", wood_medium(params, seed=seed, thickness_um=t_um, voxel_um=0.5, settings=exact), (0.0, 0.0))
    for h in voxel_sizes(args):
        n, nt = int(round(args.side_um / h)), int(round(t_um / h))
        grid = Grid((n, nt, n), h, (-n * h / 2, 0.0, -n * h / 2))  # the wood's R, L origin at the scan's centre
        t0 = time.perf_counter()
        clean = grey_volume(params, grid, seed=seed, supersample=args.supersample)
        t_scan = time.perf_counter() - t0
        for scan_name, (blur, noise) in SCANS.items():
            grey = degrade(clean, h, blur_um=blur, noise=noise, noise_seed=seed)
            for method in METHODS:
                medium = (IsoVolume(grey, voxel_um=h, iso=0.5) if method == "iso"
                          else ArraySource((grey > 0.5).astype(np.uint8), voxel_um=h))
                run(h, scan_name, method, medium, (n * h / 2, n * h / 2), t_scan)
    return rows


def voxel_sizes(args) -> list[float]:
    return [float(v) for v in str(args.voxels).split(",")]


def table(rows: list[dict]) -> list[dict]:
    """Per voxel size, scan and method: the mean difference from exact over the woods and its 95 % t
    interval."""
    from scipy.special import stdtrit

    ex = {r["seed"]: r for r in rows if r["method"] == "exact"}
    voxels = sorted({r["voxel_um"] for r in rows if r["voxel_um"] is not None}, reverse=True)
    out = []
    for voxel, scan, method in [(v, sc, m) for v in voxels for sc in SCANS for m in METHODS]:
        mine = [r for r in rows if r["voxel_um"] == voxel and r["scan"] == scan and r["method"] == method]
        entry = {"voxel_um": voxel, "scan": scan, "method": method, "woods": len(mine)}
        for q, rel in (("fwhm_r", True), ("fwhm_l", True), ("haze", False)):
            d = np.array([(r[q] / ex[r["seed"]][q] - 1.0) * 100 if rel else (r[q] - ex[r["seed"]][q]) * 100
                          for r in mine])
            half = float(stdtrit(len(d) - 1, 0.975)) * float(np.std(d, ddof=1)) / math.sqrt(len(d))
            entry[q] = [float(d.mean()), half]
        entry["us_per_interface"] = 1e6 * sum(r["cpu_s"] for r in mine) / max(1, sum(r["interfaces"] for r in mine))
        entry["interfaces"] = sum(r["interfaces"] for r in mine)
        entry["lost"] = sum(r["rays"] - r["transmitted"] for r in mine)
        out.append(entry)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="birch")
    p.add_argument("--thickness-mm", type=float, default=0.25)
    p.add_argument("--voxels", default="1,0.5", help="the scans' voxel sizes [µm], comma-separated")
    p.add_argument("--supersample", type=int, default=4)
    p.add_argument("--delta-ri", type=float, default=0.01)
    p.add_argument("--side-um", type=float, default=160.0, help="the scan's R and L extent [µm]")
    p.add_argument("--beam-um", type=float, default=40.0)
    p.add_argument("--rays", type=int, default=1000)
    p.add_argument("--woods", type=int, default=5)
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--out", default=None, help="JSON of every row and the table")
    p.add_argument("--md", default=None, help="the table as Markdown (results/iso.md)")
    p.add_argument("--from-json", default=None, help="write --md from this JSON of an earlier run, tracing nothing")
    args = p.parse_args()
    if args.from_json:
        with open(args.from_json) as f:
            doc = json.load(f)
        a = {"processes": 2, **doc["args"]}
        with open(args.md, "w") as f:
            f.write(markdown(a, doc["rows"], doc["table"], doc.get("seconds", float("nan"))))
        return
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = [r for part in pool.map(one_wood, range(1, args.woods + 1), [args] * args.woods) for r in part]
    for r in rows:
        r["rays"] = args.rays
    summary = table(rows)
    text = markdown(vars(args), rows, summary, time.perf_counter() - t0)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"args": vars(args), "rows": rows, "table": summary, "seconds": time.perf_counter() - t0}, f,
                      indent=1)
    if args.md:
        with open(args.md, "w") as f:
            f.write(text)


def markdown(a: dict, rows: list[dict], summary: list[dict], seconds: float) -> str:
    """results/iso.md: the table of differences from exact, and how it was made."""
    ex = [r for r in rows if r["method"] == "exact"]
    lines = [
        "# Grey-level scans against `exact` on the same wood", "",
        f"Generated by `make bench-iso` ({seconds / 60:.1f} min on {a['processes']} processes); every number is in "
        f"`iso.json`. {a['preset'].capitalize()} {a['thickness_mm']} mm at ΔRI {a['delta_ri']}, {a['woods']} woods x "
        f"{a['rays']} rays, a {a['beam_um']:g} µm beam in the middle of a {a['side_um']:g} µm scan (each voxel's wall "
        f"fraction from {a['supersample']}³ fine voxels of the generator's own wood). `iso` traces the scan's "
        "iso-surface at ½ (docs/methods.md#iso-surfaces); `accurate` and `fast` trace it binarised at ½ on its own "
        "voxels. Each cell: the difference from `exact` on the same wood, beam and rays (relative for the half-max "
        "widths, in points for haze), its mean over the woods ± a 95 % t interval over them (each wood's difference "
        "carries its own ray sampling, so the interval holds both).", "",
        "| voxel [µm] | scan | method | FWHM_R [%] | FWHM_L [%] | haze [points] | interfaces met [% of exact's] "
        "| µs an interface | rays not transmitted (sides, reflected, trapped) |",
        "|---|---|---|---|---|---|---|---|---|"]
    n_exact = sum(r["interfaces"] for r in ex)
    for e in summary:
        lines.append(f"| {e['voxel_um']:g} | {e['scan']} | {e['method']} | {e['fwhm_r'][0]:+.1f} ± {e['fwhm_r'][1]:.1f} | "
                     f"{e['fwhm_l'][0]:+.1f} ± {e['fwhm_l'][1]:.1f} | {e['haze'][0]:+.2f} ± {e['haze'][1]:.2f} | "
                     f"{100 * (e['interfaces'] / n_exact - 1):+.1f} | {e['us_per_interface']:.2f} | "
                     f"{e['lost']} of {a['woods'] * a['rays']} |")
    vals = {q: [r[q] for r in ex] for q in ("fwhm_r", "fwhm_l", "haze")}
    scans = {v: np.mean([r["scan_s"] for r in rows if r["voxel_um"] == v]) for v in {e["voxel_um"] for e in summary}}
    lines += ["", f"`exact` itself on these woods: FWHM_R {min(vals['fwhm_r']):.2f}-{max(vals['fwhm_r']):.2f}°, "
              f"FWHM_L {min(vals['fwhm_l']):.3f}-{max(vals['fwhm_l']):.3f}°, haze "
              f"{100 * min(vals['haze']):.1f}-{100 * max(vals['haze']):.1f} %; {n_exact:,} interfaces, "
              f"{1e6 * sum(r['cpu_s'] for r in ex) / n_exact:.1f} µs each. A clean scan took "
              + ", ".join(f"{t:.0f} s a wood at {v:g} µm" for v, t in sorted(scans.items(), reverse=True)) + ".", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
