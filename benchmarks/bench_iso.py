"""Scans as accurate as the model? A grey-level scan of generated wood (its wall fraction per voxel,
supersampled; optionally blurred and noisy) traced with `iso`, and binarised at one half with
`accurate` and `fast`, beside `exact` on the same wood, beam and rays (docs/methods.md#iso-surfaces).

Prints, per wood and method, FWHM_R, FWHM_L (half-max) and haze, and each method's difference from
`exact` with the rays lost through the scan's sides; writes them to --out (JSON) when given.

    python benchmarks/bench_iso.py --preset birch --thickness-mm 0.25 --voxel-um 0.5 --woods 2
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from pipeline.microstructure.grey import grey_volume
from pipeline.optics.iso import IsoVolume
from pipeline.optics.media import wood_medium
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import Optics, settings_for
from pipeline.optics.sources import ArraySource
from pipeline.optics.trace import trace
from pipeline.params import Grid, build_params
from pipeline.summary import summarize


def one_wood(params, seed, args) -> list[dict]:
    t_um = 1000.0 * args.thickness_mm
    side = args.side_um
    n = int(round(side / args.voxel_um))
    nt = int(round(t_um / args.voxel_um))
    grid = Grid((n, nt, n), args.voxel_um, (-n * args.voxel_um / 2, 0.0, -n * args.voxel_um / 2))
    t0 = time.perf_counter()
    grey = grey_volume(params, grid, seed=seed, supersample=args.supersample, blur_um=args.blur_um,
                       noise=args.noise, noise_seed=seed)
    t_scan = time.perf_counter() - t0
    optics = Optics.of_delta(1.49, args.delta_ri, seed=seed)
    half = n * args.voxel_um / 2
    rows = []
    cases = [("exact", None), ("iso", None), ("accurate", "binary"), ("fast", "binary")]
    for method, _ in cases:
        settings = settings_for(method, **({"refine": 1} if method in ("accurate", "fast") else {}))
        if method == "exact":
            medium, centre = wood_medium(params, seed=seed, thickness_um=nt * args.voxel_um, voxel_um=args.voxel_um,
                                         settings=settings), (0.0, 0.0)
        elif method == "iso":
            medium, centre = IsoVolume(grey, voxel_um=args.voxel_um, iso=0.5), (half, half)
        else:
            medium, centre = ArraySource((grey > 0.5).astype(np.uint8), voxel_um=args.voxel_um), (half, half)
        beam = square_beam(args.rays, args.beam_um, centre, seed=seed)
        c0 = time.process_time()
        r = trace(medium, beam, optics, settings)
        cpu = time.process_time() - c0
        s = summarize(r, seed=seed, n_boot=0)
        interfaces = int(r.events.sum())
        rows.append({"seed": seed, "method": method, "fwhm_r": s["fwhm_r_deg"], "fwhm_l": s["fwhm_l_deg"],
                     "haze": s["haze"], "transmitted": int(s["n_transmitted"]), "rays": args.rays,
                     "interfaces": interfaces, "cpu_s": cpu, "us_per_interface": 1e6 * cpu / max(interfaces, 1),
                     "scan_s": t_scan})
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="birch")
    p.add_argument("--thickness-mm", type=float, default=0.25)
    p.add_argument("--voxel-um", type=float, default=0.5)
    p.add_argument("--supersample", type=int, default=4)
    p.add_argument("--blur-um", type=float, default=0.0)
    p.add_argument("--noise", type=float, default=0.0)
    p.add_argument("--delta-ri", type=float, default=0.01)
    p.add_argument("--side-um", type=float, default=160.0, help="the scan's R and L extent [µm]")
    p.add_argument("--beam-um", type=float, default=40.0)
    p.add_argument("--rays", type=int, default=300)
    p.add_argument("--woods", type=int, default=2)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    params = build_params(args.preset)
    rows = [row for seed in range(1, args.woods + 1) for row in one_wood(params, seed, args)]
    ex = {r["seed"]: r for r in rows if r["method"] == "exact"}
    print(f"{args.preset} {args.thickness_mm} mm, scan {args.voxel_um} µm (supersample {args.supersample}, blur "
          f"{args.blur_um} µm, noise {args.noise}), ΔRI {args.delta_ri}, {args.rays} rays a wood")
    for r in rows:
        e = ex[r["seed"]]
        print(f"  wood {r['seed']} {r['method']:8s} FWHM_R {r['fwhm_r']:7.3f}° ({100 * (r['fwhm_r'] / e['fwhm_r'] - 1):+6.1f} %)"
              f"  FWHM_L {r['fwhm_l']:6.3f}° ({100 * (r['fwhm_l'] / e['fwhm_l'] - 1):+6.1f} %)"
              f"  haze {100 * r['haze']:5.1f} % ({100 * (r['haze'] - e['haze']):+5.1f} pt)"
              f"  transmitted {r['transmitted']}/{r['rays']}  {r['us_per_interface']:.2f} µs/interface")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"args": vars(args), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
