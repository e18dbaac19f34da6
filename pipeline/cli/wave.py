"""``twray wave``: rays against scalar waves on the same sections (docs/guide.md#where-rays-hold)."""

from __future__ import annotations

import sys
import time

from ..progress import mode as progress_mode
from .args import subparser
from .graphs import _absolute_paths, _cluster, add_cluster_options


def add_wave(sub):
    p = subparser(sub, "wave", help="where geometrical optics holds: exact rays against scalar waves on the "
                                    "same sections, into results/<file>.zarr")
    p.add_argument("file", metavar="FILE.yaml", help="regime file, e.g. studies/wave/regime.yaml")
    p.add_argument("--scale", default="paper", help="paper (the file's sections), quick (a quarter of each "
                                                     "thickness, a quarter of the rays) or small (a tenth; tests)")
    add_cluster_options(p)
    p.add_argument("--results", default="results", help="where <file>.zarr goes (default results)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.set_defaults(func=cmd_wave)


def cmd_wave(args) -> int:
    from ..wave.regime import load_regime
    from ..wave.run import compute, missing, write_regime

    _absolute_paths(args)
    regime = load_regime(args.file, scale=args.scale)
    t0 = time.perf_counter()
    todo = missing(regime, args.cache)
    if todo:
        print(f"twray wave: {len(todo)} of {len(regime.geometries) * regime.realisations} cases to compute "
              f"(geometry x realisation; the others are cached)", file=sys.stderr)
        with _cluster(args, "wave") as client:
            compute(regime, args.cache, client, progress=progress_mode(args.quiet))
    out = write_regime(regime, args.cache, args.results)
    import xarray as xr

    with xr.open_zarr(out) as ds:
        print(f"{out}: {regime.title} (scale {regime.scale}, {regime.realisations} realisations, "
              f"{ds.attrs['rays_per_realisation']} rays and {regime.wavelengths} wavelengths each)")
        inside = ds.sel(exit="internal")
        for g in ds.geometry.values:
            row = inside.sel(geometry=g)
            holds = [f"{d:+g}" for d, h in zip(ds.delta_ri.values, row["rays_hold"].values) if h]
            haze = [f"{d:+g}" for d, h, b in zip(ds.delta_ri.values, row["haze_holds"].values, row["rays_hold"].values)
                    if h and not b]
            print(f"  {g} ({float(row.thickness_mm):g} mm, angles inside): rays hold (haze within 2 points, FWHM_R "
                  f"within 10 % of the waves') {'at ΔRI ' + ', '.join(holds) if holds else 'at no ΔRI'}"
                  + (f"; haze alone at {', '.join(haze)}" if haze else ""))
    print(f"{len(todo)} cases computed in {time.perf_counter() - t0:.1f} s")
    return 0
