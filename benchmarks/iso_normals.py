"""How far `iso`'s normals stray on a partial-volume scan of a flat wall (results/iso_normals.json).

A half-space of wall, its normal tilted by ``beta`` in the R-T plane and by ``alpha`` towards L, is
scanned as a µCT would record it (each voxel's wall fraction from supersample³ points, as
``twray generate --grey`` does) and traced with `iso` at ½, with and without ``--smooth-um``.  Rays
along +T cross it once; at a refraction n2·d_out − n1·d_in is along the normal used, so each ray
gives the normal `iso` refracted it by.  Its angle from the true normal, and the part of that along
L, say how much a wall's voxel staircase deflects rays sideways (θ_L) where the model's wall is
flat.  ``python benchmarks/iso_normals.py`` (about a minute on one core).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from pipeline.optics.iso import IsoVolume
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import Optics, settings_for
from pipeline.optics.trace import trace

VOXEL = 0.5  # µm; a second run at VOXEL / 2 shows the angles do not depend on it
SHAPE = (64, 48, 64)  # voxels (R, T, L)
SUPERSAMPLE = 4
N_WALL, N_POLY = 1.6, 1.5  # any indices give the normal; a large ΔRI keeps n2·d_out − n1·d_in well away from 0
RAYS = 4000


def normal_of(alpha_deg: float, beta_deg: float) -> np.ndarray:
    a, b = math.radians(alpha_deg), math.radians(beta_deg)
    return np.array([math.sin(b) * math.cos(a), math.cos(b) * math.cos(a), math.sin(a)])


def wall_fraction(n: np.ndarray, offset_um: float, voxel: float) -> np.ndarray:
    """Each voxel's fraction of wall (n·x > offset) from SUPERSAMPLE³ points at its sub-voxels' centres."""
    axes = [(np.arange(k) + 0.5) * voxel for k in SHAPE]
    base = (n[0] * axes[0][:, None, None] + n[1] * axes[1][None, :, None] + n[2] * axes[2][None, None, :])
    sub = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    out = np.zeros(SHAPE)
    for i in sub:
        for j in sub:
            for k in sub:
                out += base + voxel * (n[0] * i + n[1] * j + n[2] * k) > offset_um
    return out / SUPERSAMPLE ** 3


def measure(alpha: float, beta: float, smooth_um: float, voxel: float = VOXEL) -> dict:
    n = normal_of(alpha, beta)
    centre = np.array(SHAPE) * voxel / 2.0
    vol = IsoVolume(wall_fraction(n, float(n @ centre), voxel), voxel_um=voxel, iso=0.5, smooth_um=smooth_um)
    width = 0.5 * min(SHAPE[0], SHAPE[2]) * voxel
    beam = square_beam(RAYS, width, (centre[0], centre[2]), seed=7)
    r = trace(vol, beam, Optics(N_WALL, N_POLY), settings_for("iso"))
    one = r.events == 1
    d_in = beam.unit_directions()[one]
    m = N_WALL * r.direction[one] - N_POLY * d_in
    m /= np.linalg.norm(m, axis=1)[:, None]
    m *= np.sign(m @ n)[:, None]
    angle = np.degrees(np.arccos(np.clip(m @ n, -1.0, 1.0)))
    along_l = np.degrees(np.arcsin(np.clip(m[:, 2], -1, 1)) - math.asin(n[2]))
    across = np.degrees(np.arctan2(m[:, 0], m[:, 1]) - math.atan2(n[0], n[1]))
    return {"voxel_um": voxel, "alpha_deg": alpha, "beta_deg": beta, "smooth_um": smooth_um, "rays_one_interface": int(one.sum()),
            "angle_rms_deg": float(np.sqrt(np.mean(angle ** 2))), "angle_p95_deg": float(np.quantile(angle, 0.95)),
            "along_l_rms_deg": float(np.sqrt(np.mean(along_l ** 2))), "along_l_mean_deg": float(np.mean(along_l)),
            "across_rms_deg": float(np.sqrt(np.mean(across ** 2)))}


def main(out: Path) -> None:
    rows = [measure(a, b, s) for s in (0.0, VOXEL) for b in (0.0, 20.0) for a in (0.0, 1.0, 5.0, 20.0)]
    rows += [measure(a, 20.0, s, VOXEL / 2) for s in (0.0, VOXEL / 2) for a in (1.0, 5.0)]
    out.write_text(json.dumps({"supersample": SUPERSAMPLE, "rays": RAYS, "rows": rows}, indent=1)
                   + "\n")
    print("| voxel [µm] | smooth [µm] | tilt to L [°] | tilt in R-T [°] | angle RMS [°] | angle 95 % [°] | along L RMS [°] | "
          "across RMS [°] |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['voxel_um']:g} | {r['smooth_um']:g} | {r['alpha_deg']:g} | {r['beta_deg']:g} | {r['angle_rms_deg']:.3f} | "
              f"{r['angle_p95_deg']:.3f} | {r['along_l_rms_deg']:.3f} | {r['across_rms_deg']:.3f} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("results/iso_normals.json"))
