"""The wave solver's cost beside `exact` on the same section, its convergence in the sampling steps, and
what a 3-D (R, L) field would cost -> section "wave" of results/bench.json.

Cost: one birch section (0.1 and 0.25 mm, the regime's beam and window), the index map sampled
once, five wavelengths propagated together, against `exact` tracing the regime's 4000 rays at one
ΔRI; both cold in this process after a warm-up.  Convergence: one regime case (tubes and birch,
0.1 mm, every ΔRI of the regime file) at the default sampling, at half dx and dz, and at twice dz.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time

import numpy as np
from _bench_json import write_section

from pipeline.wave.regime import POSITION_SPACING_UM, load_regime, ray_angles, ray_origins, run_case
from pipeline.wave.sections import slices
from pipeline.wave.solver import Sampling, absorber, gaussian_beam, propagate
from pipeline.wave.spectrum import white_light

REGIME = "studies/wave/regime.yaml"


def cost(regime, name: str) -> dict:
    """Seconds for a section's index map, for propagating five wavelengths, and for `exact`'s rays."""
    from scipy import fft as sfft

    g = next(x for x in regime.geometries if x.name == name)
    section, make_medium = g.section(regime.seed)
    s = regime.sampling
    nx = sfft.next_fast_len(int(math.ceil(regime.window_um(g) / s.dx_um)))
    nz = int(round(g.thickness_um / s.dz_um))
    t0 = time.perf_counter()
    maps = list(slices(section, r0_um=0.0, nx=nx, nz=nz, sampling=s))
    t_map = time.perf_counter() - t0
    lam = white_light(regime.wavelengths)
    x = (np.arange(nx) + 0.5) * s.dx_um
    u0 = np.tile(gaussian_beam(x, x[nx // 2], regime.beam_um), (lam.size, 1))
    t0 = time.perf_counter()
    propagate(u0, maps, k0=2 * math.pi / lam, delta_n=np.full(lam.size, 0.01), n0=np.full(lam.size, 1.49),
              sampling=s, mask=absorber(nx, s.dx_um))
    t_wave = time.perf_counter() - t0
    origins = np.vstack([ray_origins(regime, regime.seed, p, p * POSITION_SPACING_UM + x[nx // 2]) for p in range(regime.positions)])
    t0 = time.perf_counter()
    ray_angles(make_medium(0.0, regime.positions * POSITION_SPACING_UM + nx * s.dx_um), origins, regime.ri_polymer, 0.01)
    t_rays = time.perf_counter() - t0
    rows_cells = lam.size * nx * nz
    return {"section": name, "thickness_mm": g.thickness_um / 1e3, "nx": nx, "nz": nz, "index_map_s": round(t_map, 2),
            "waves_s": round(t_wave, 2), "wavelengths": int(lam.size), "ns_per_row_cell": round(1e9 * t_wave / rows_cells, 2),
            "exact_rays": int(len(origins)), "exact_s": round(t_rays, 2)}


def convergence(regime, name: str) -> dict:
    """A case's haze and half-max at the default sampling against half dx and dz and twice dz."""
    g = dataclasses.replace(next(x for x in regime.geometries if x.name == name))
    one = dataclasses.replace(regime, realisations=1, positions=1, wavelengths=3)
    base = run_case(one, g, 0)
    out = {"section": name, "delta_ri": list(regime.delta_ri)}
    s = regime.sampling
    for label, samp in (("half_dx_dz", Sampling(s.sub_um / 2, s.per_dx, s.per_dz)),
                        ("twice_dz", Sampling(s.sub_um, s.per_dx, 2 * s.per_dz))):
        other = run_case(dataclasses.replace(one, sampling=samp), g, 0)
        dh = 100 * (other["haze_wave_internal"] - base["haze_wave_internal"])
        dw = other["half-max_wave_internal"] / base["half-max_wave_internal"] - 1
        out[label] = {"haze_points_max": round(float(np.max(np.abs(dh))), 3),
                      "half_max_rel_max": round(float(np.max(np.abs(dw))), 4),
                      "haze_points": [round(float(v), 3) for v in dh], "half_max_rel": [round(float(v), 4) for v in dw]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    args = ap.parse_args()
    regime = load_regime(REGIME)
    warm = dataclasses.replace(regime, rays=50, wavelengths=1, positions=1)
    run_case(warm, dataclasses.replace(regime.geometries[0], thickness_um=5.0), 0)  # compile the kernels
    run_case(warm, dataclasses.replace(next(g for g in regime.geometries if g.preset), thickness_um=5.0), 0)
    costs = [cost(regime, n) for n in ("birch-0.1mm", "birch-0.25mm")]
    conv = [convergence(regime, n) for n in ("tubes-14.5-w2", "birch-0.1mm")]
    per = float(np.median([c["ns_per_row_cell"] for c in costs]))
    # A 3-D field over (R, L): a 500 x 500 µm window of 1 mm birch at the same dx and dz, one wavelength.
    cells_3d = (500 / regime.sampling.dx_um) ** 2 * (1000 / regime.sampling.dz_um)
    c = costs[-1]
    summary = (f"a 2-D case of {c['thickness_mm']:g} mm birch costs {c['index_map_s']:g} s for its index map and "
               f"{c['waves_s']:g} s for {c['wavelengths']} wavelengths ({per:.1f} ns a row and cell), against "
               f"{c['exact_s']:g} s for `exact`'s {c['exact_rays']} rays at one ΔRI; halving dx and dz moves haze by "
               f"at most {max(v['half_dx_dz']['haze_points_max'] for v in conv):g} points and half-max FWHM_R by "
               f"{100 * max(v['half_dx_dz']['half_max_rel_max'] for v in conv):.1f} %; a 3-D (R, L) field of 1 mm birch "
               f"would take about {per * cells_3d / 3.6e12:.0f} CPU-h a wavelength at the same steps.")
    write_section(args.out, "wave", {"cpus": os.cpu_count(), "cost": costs, "convergence": conv,
                                     "ns_per_row_cell": per, "summary": summary})


if __name__ == "__main__":
    main()
