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
from pathlib import Path

import numpy as np

SCANS = {"clean": (0.0, 0.0), "blur 0.3 µm + noise 0.02": (0.3, 0.02)}
METHODS = ("iso", "iso smoothed 0.5 µm", "accurate", "fast")
SMOOTH_UM = 0.5  # σ of the pre-filter of "iso smoothed", traced on the noisy scans only


class Binarised:
    """A grey scan seen binarised at ``level`` (uint8, 1 = wall), read as lazily as the scan."""

    dtype = np.dtype(np.uint8)
    ndim = 3

    def __init__(self, scan, level: float):
        self.scan, self.level, self.shape = scan, level, scan.shape

    def __getitem__(self, region):
        return (self.scan[region] > self.level).astype(np.uint8)


def one_wood(seed: int, args) -> list[dict]:
    from pipeline.microstructure.grey import LazyGreyScan
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

    def run(voxel, scan_name, method, medium, centre, scan=None):
        settings = settings_for(method.split()[0], **({"refine": 1} if method in ("accurate", "fast") else {}))
        beam = square_beam(args.rays, args.beam_um, centre, seed=seed)
        made = 0.0
        if scan is not None:  # the scan's parts made as the rays read them; then the trace timed on them
            g0 = scan.generate_s
            trace(medium, beam, optics, settings)
            made = scan.generate_s - g0
        g1 = scan.generate_s if scan is not None else 0.0
        c0 = time.process_time()
        r = trace(medium, beam, optics, settings)
        # Without parts remade during it (a full tile cache drops some; then they are counted as made).
        again = (scan.generate_s - g1) if scan is not None else 0.0
        cpu = time.process_time() - c0 - again
        made += again
        s = summarize(r, seed=seed, n_boot=0)
        rows.append({"seed": seed, "voxel_um": voxel, "scan": scan_name, "method": method, "fwhm_r": s["fwhm_r_deg"],
                     "fwhm_l": s["fwhm_l_deg"], "haze": s["haze"], "transmitted": int(s["n_transmitted"]),
                     "interfaces": int(r.events.sum()), "cpu_s": cpu, "scan_s": made})

    exact = settings_for("exact")
    run(None, "-", "exact", wood_medium(params, seed=seed, thickness_um=t_um, voxel_um=0.5, settings=exact), (0.0, 0.0))
    chosen = args.methods.split(",") if args.methods else METHODS
    for h in (voxel_sizes(args) if set(chosen) - {"exact"} else []):  # `--methods exact`: exact's rows only
        n, nt = int(round(args.side_um / h)), int(round(t_um / h))
        grid = Grid((n, nt, n), h, (-n * h / 2, 0.0, -n * h / 2))  # the wood's R, L origin at the scan's centre
        for scan_name in args.scans.split(","):
            blur, noise = SCANS[scan_name]
            # Generated where the rays read it, bit for bit grey_volume's scan; iso reads it first.
            grey = LazyGreyScan(params, grid, seed=seed, supersample=args.supersample, blur_um=blur, noise=noise,
                                noise_seed=seed, cache_bytes=args.cache_mb * 2 ** 20)
            for method in METHODS:
                if method not in chosen:
                    continue
                if method.startswith("iso ") and not noise and not args.methods:
                    continue  # by default the pre-filter only where there is noise
                # Blocks and chunks of 16 and 32 voxels: they generate the least around the rays.
                medium = (IsoVolume(grey, voxel_um=h, iso=0.5, block=16,
                                    smooth_um=SMOOTH_UM if method.startswith("iso ") else 0.0)
                          if method.startswith("iso") else ArraySource(Binarised(grey, 0.5), voxel_um=h, chunks=(32, 32, 32)))
                run(h, scan_name, method, medium, (n * h / 2, n * h / 2), grey)
    return rows


def one_lattice(case) -> list[dict]:
    """One reference lattice of results/accuracy.md (family, wall in voxels at 0.5 µm, ΔRI) as a grey scan
    at 0.5 µm (each voxel's wall fraction from 4² points of its section), traced with iso and, binarised at ½,
    with accurate and fast on its voxels, against the independent exact tracer on the same 4000 rays."""
    import bench_accuracy as acc

    from pipeline.analysis import LORENTZ_MLE, fwhm, haze
    from pipeline.optics.iso import IsoVolume
    from pipeline.optics.rays import Beam, square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.sources import ArraySource
    from pipeline.optics.trace import trace

    family, wall, dri = case
    n_wall, n_poly = acc.INDICES[dri]
    lat, h, t_um = acc.lattice(family, wall), acc.VOXEL, 250.0
    beam = square_beam(4000, 150.0, seed=1)
    ex = lat.trace_independently(beam.origins, beam.unit_directions(), n_wall=n_wall, n_poly=n_poly, thickness_um=t_um)
    half = 250.0  # the scan spans R ∈ [-250, 250) µm, L ∈ [-80, 80) µm around the beam
    n_r, n_t, n_l = int(2 * half / h), int(round(t_um / h)), int(160 / h)
    section = lat.grey_section(voxel_um=h, r0_um=-half, n_r=n_r, n_t=n_t)
    scan = np.broadcast_to(section[:, :, None], (n_r, n_t, n_l))  # constant along L
    shifted = Beam(beam.origins + np.array([half, 0.0, 80.0]), beam.direction, beam.ray_ids)
    fe, he = fwhm(ex.theta_r[ex.transmitted], LORENTZ_MLE), haze(ex.direction[ex.transmitted])
    rows = []
    for method in ("iso", "accurate", "fast"):
        medium = (IsoVolume(scan, voxel_um=h, iso=0.5) if method == "iso"
                  else ArraySource(Binarised(scan, 0.5), voxel_um=h))
        c0 = time.process_time()
        r = trace(medium, shifted, Optics(n_wall, n_poly),
                  settings_for(method, **({} if method == "iso" else {"refine": 1})))
        cpu = time.process_time() - c0
        fv, hv = fwhm(r.theta_r[r.transmitted], LORENTZ_MLE), haze(r.direction[r.transmitted])
        rows.append({"family": family, "wall_vox": wall, "delta_ri": dri, "method": method,
                     "fwhm_r_exact_deg": fe, "fwhm_r_deg": fv, "fwhm_r_error": fv / fe - 1.0 if fe >= 0.05 else None,
                     "haze_exact": he, "haze": hv, "haze_error_points": 100.0 * (hv - he),
                     "interfaces_exact": int(ex.events.sum()), "interfaces": int(r.events.sum()),
                     "transmitted": int(r.transmitted.sum()), "cpu_s": cpu})
    return rows


def lattices(args) -> None:
    """Every lattice case of results/accuracy.md as a grey scan; the rows go to --out's "lattices"."""
    import bench_accuracy as acc

    cases = [(f, w, d) for f in acc.FAMILIES for w in acc.WALLS_VOX for d in acc.INDICES]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = [r for part in pool.map(one_lattice, cases) for r in part]
    from pipeline.report_scans import lattice_table

    print("\n".join(lattice_table(rows)))
    if args.out:
        doc = json.loads(Path(args.out).read_text()) if Path(args.out).exists() else {}
        if "configs" not in doc:
            doc = {"configs": [doc] if doc else []}
        doc["lattices"] = {"rows": rows, "seconds": time.perf_counter() - t0}
        Path(args.out).write_text(json.dumps(doc, indent=1))


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
        if not mine:
            continue
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
    p.add_argument("--scans", default=",".join(SCANS), help=f"comma-separated, of: {', '.join(SCANS)}")
    p.add_argument("--supersample", type=int, default=4)
    p.add_argument("--delta-ri", type=float, default=0.01)
    p.add_argument("--side-um", type=float, default=160.0, help="the scan's R and L extent [µm]")
    p.add_argument("--beam-um", type=float, default=40.0)
    p.add_argument("--rays", type=int, default=1000)
    p.add_argument("--woods", type=int, default=5)
    p.add_argument("--first-wood", type=int, default=1, help="the woods are seeds first-wood, first-wood + 1, ... "
                                                               "(with --merge: a run split into parts)")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--cache-mb", type=int, default=2048, help="tiles of a scan each process keeps")
    p.add_argument("--methods", default=None, help=f"comma-separated, of: {', '.join(METHODS)} (default: all, the "
                                                   "smoothed iso on noisy scans only; given, on every scan); "
                                                   "`exact` alone: only exact's rows (exact is always traced)")
    p.add_argument("--merge", action="store_true", help="add this run's rows to the configuration already in --out "
                                                        "(rows of the same wood, voxel, scan and method replaced)")
    p.add_argument("--out", default=None, help="JSON: this configuration (preset, thickness) added to or replaced in it")
    p.add_argument("--md", default=None, help="every configuration of --out as Markdown (results/iso.md)")
    p.add_argument("--lattices", action="store_true", help="the reference lattices of results/accuracy.md as grey "
                                                           "scans, against their exact tracer (into --out)")
    args = p.parse_args()
    if args.lattices:
        lattices(args)
        if args.md:
            write_md(args)
        return
    for name in args.scans.split(","):
        if name not in SCANS:
            p.error(f"--scans: {name!r} is none of {', '.join(SCANS)}")
    for name in (args.methods.split(",") if args.methods else []):
        if name not in (*METHODS, "exact"):
            p.error(f"--methods: {name!r} is none of exact, {', '.join(METHODS)}")
    if args.md and not args.woods:
        return write_md(args)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.processes) as pool:
        rows = [r for part in pool.map(one_wood, range(args.first_wood, args.first_wood + args.woods),
                                                     [args] * args.woods) for r in part]
    for r in rows:
        r["rays"] = args.rays
    config = {"args": vars(args), "rows": rows, "table": table(rows), "seconds": time.perf_counter() - t0}
    from pipeline.report_scans import difference_table

    print("\n".join(difference_table([config])))
    if args.out:
        from pipeline.report_scans import read

        key = (args.preset, args.thickness_mm)
        old = [c for c in read(Path(args.out)) if (c["args"]["preset"], c["args"]["thickness_mm"]) == key]
        kept = [c for c in read(Path(args.out)) if (c["args"]["preset"], c["args"]["thickness_mm"]) != key]
        if args.merge and old:
            def ident(r):
                return r["seed"], r["voxel_um"], r["scan"], r["method"]
            new_ids = {ident(r) for r in rows}
            rows = [r for r in old[0]["rows"] if ident(r) not in new_ids] + rows
            config = {"args": {**old[0]["args"], "merged": [*old[0]["args"].get("merged", []), vars(args)]},
                      "rows": rows, "table": table(rows), "seconds": old[0]["seconds"] + config["seconds"]}
        doc = json.loads(Path(args.out).read_text()) if Path(args.out).exists() else {}
        Path(args.out).write_text(json.dumps({**({"lattices": doc["lattices"]} if "lattices" in doc else {}),
                                              "configs": kept + [config]}, indent=1))
    if args.md:
        write_md(args)


def write_md(args) -> None:
    """results/iso.md from every measurement beside --out (iso.json and the files that go with it)."""
    from pipeline.report_scans import section_of

    text = ["# Grey-level scans against `exact` on the same wood", "",
            "Generated by `make bench-iso`; every number is in the `iso*.json` files beside this one.", "",
            *section_of(Path(args.out).parent, "##")[2:]]
    Path(args.md).write_text("\n".join(text))


if __name__ == "__main__":
    main()
