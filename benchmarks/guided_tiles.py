"""Tiles built by rays guided along R: per scene of birch into air (one wood, 500 rays of a 150 µm
beam, `exact`), by thickness and ΔRI, the distortion tiles built (from none kept), the CPU and the
rays past 400 interfaces; beside them what limits.guided_tiles_per_ray fits to them
(docs/performance.md#rays-guided-along-r).  A scene's tiles beyond its beam's region are those it
builds minus the region's, taken as proportional to the thickness from 1 mm at ΔRI 0.01 (no ray
guided there).

    python benchmarks/guided_tiles.py --out results/guided_tiles.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

THICKNESS_MM = (1.0, 1.5, 2.0)
DELTA_RI = (0.01, 0.02, 0.03, -0.03)
RAYS, BEAM_UM = 500, 150.0


def main(argv=None) -> int:
    from pipeline import limits
    from pipeline.microstructure import model
    from pipeline.optics.media import wood_medium
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace
    from pipeline.params import build_params

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    params, settings = build_params("birch"), settings_for("exact", exit="air")
    beam = square_beam(RAYS, BEAM_UM, (0.0, 0.0), seed=1)
    warm = wood_medium(params, seed=1, thickness_um=20.0, voxel_um=0.5, settings=settings)
    trace(warm, square_beam(5, 10.0, (0.0, 0.0), seed=1), Optics.of_delta(1.49, 0.01, seed=1), settings)  # compiled
    rows = []
    for t_mm in THICKNESS_MM:
        for dri in DELTA_RI:
            model.clear_tiles()
            medium = wood_medium(params, seed=1, thickness_um=1000.0 * t_mm, voxel_um=0.5, settings=settings)
            c0 = time.process_time()
            r = trace(medium, beam, Optics.of_delta(1.49, dri, seed=1), settings)
            rows.append({"thickness_mm": t_mm, "delta_ri": dri, "tiles": model.tiles_held(),
                         "cpu_s": time.process_time() - c0, "interfaces": int(r.events.sum()),
                         "past_400": int((r.events > 400).sum())})
    region = next(r["tiles"] for r in rows if r["thickness_mm"] == 1.0 and r["delta_ri"] == 0.01)
    print("| thickness [mm] | ΔRI | tiles | beyond the region, a ray | fitted | CPU [s] | rays past 400 interfaces |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        r["beyond_per_ray"] = max(0.0, r["tiles"] - region * r["thickness_mm"]) / RAYS
        r["fitted_per_ray"] = limits.guided_tiles_per_ray(1000.0 * r["thickness_mm"], r["delta_ri"])
        print(f"| {r['thickness_mm']:g} | {r['delta_ri']:+g} | {r['tiles']} | {r['beyond_per_ray']:.2f} | "
              f"{r['fitted_per_ray']:.2f} | {r['cpu_s']:.1f} | {r['past_400']} |")
    if a.out:
        a.out.write_text(json.dumps({"rays": RAYS, "beam_um": BEAM_UM, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
