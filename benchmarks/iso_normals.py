"""How far `iso`'s normals stray on a partial-volume scan of a flat wall (results/iso_normals.json).

A half-space of wall, its normal turned by ``beta`` in the R-T plane and tilted by ``alpha`` towards
L, is scanned as a µCT would record it (each voxel's wall fraction from 4³ points, as ``twray
generate --grey`` does) and traced with `iso` at ½, with and without a one-voxel ``--smooth-um``
(:func:`pipeline.optics.validation.iso_wall_normals`).  Each ray's refraction gives the normal it
was refracted by; its angle from the wall's, and the part of that along L, say how much a scan's
facets deflect rays sideways (θ_L) where the wall is flat.  At half the voxel the angles are the
same: the facets scale with the voxel.  ``python benchmarks/iso_normals.py [OUT]`` (seconds).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pipeline.optics.validation import iso_wall_normals

VOXEL = 0.5  # µm
RAYS = 4000


def measure(alpha: float, beta: float, smooth_um: float, voxel: float = VOXEL) -> dict:
    w = iso_wall_normals(alpha, beta, voxel_um=voxel, smooth_um=smooth_um, rays=RAYS)

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    return {"voxel_um": voxel, "alpha_deg": alpha, "beta_deg": beta, "smooth_um": smooth_um,
            "rays_one_interface": int(w["angle_deg"].size), "angle_rms_deg": rms(w["angle_deg"]),
            "angle_p95_deg": float(np.quantile(w["angle_deg"], 0.95)), "along_l_rms_deg": rms(w["along_l_deg"]),
            "along_l_mean_deg": float(np.mean(w["along_l_deg"])), "across_rms_deg": rms(w["across_deg"])}


def main(out: Path) -> None:
    rows = [measure(a, b, s) for s in (0.0, VOXEL) for b in (0.0, 20.0) for a in (0.0, 1.0, 5.0, 20.0)]
    rows += [measure(a, 20.0, s, VOXEL / 2) for s in (0.0, VOXEL / 2) for a in (1.0, 5.0)]
    out.write_text(json.dumps({"supersample": 4, "rays": RAYS, "rows": rows}, indent=1) + "\n")
    print("| voxel [µm] | smooth [µm] | tilt to L [°] | tilt in R-T [°] | angle RMS [°] | angle 95 % [°] | "
          "along L RMS [°] | across RMS [°] |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['voxel_um']:g} | {r['smooth_um']:g} | {r['alpha_deg']:g} | {r['beta_deg']:g} | "
              f"{r['angle_rms_deg']:.3f} | {r['angle_p95_deg']:.3f} | {r['along_l_rms_deg']:.3f} | "
              f"{r['across_rms_deg']:.3f} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("results/iso_normals.json"))
