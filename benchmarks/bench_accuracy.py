"""Every tracing method against exact optics of many thin walls (docs/methods.md#accuracy-against-exact-optics).

Writes results/accuracy.json and results/accuracy.md:
- table: fast and accurate (4000 rays) and paper (500 rays, wall 4 voxels)
  against the exact trace of the same beam through lattices of tubes and
  honeycombs extruded along L (pitch 29 voxels, walls 1.5-8 voxels at
  0.5 µm, ΔRI ±0.01 and ±0.02, 0.25 mm thick): FWHM_R error, haze error
  [points], KS of θ_R (plain and at 0.25° resolution);
- pitch and thickness: pitch 20 and 80 voxels, and 1 mm thick, at wall 4;
- refinement: the same lattices voxelised at 0.25 and 0.125 µm (the walls
  2, 4 and 8 voxels thick at 0.5 µm), to show whether the error falls as
  the voxel shrinks;
- noise floor: the exact trace with its normals turned at random by 0.1-2°,
  what an unbiased estimator of that error would do;
- targets: per method and wall, whether FWHM_R is within 10 % (25 % for
  3-voxel walls), haze within 3 points and KS within 0.06 in every case
  (twice those for fast).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from pipeline import report_scans as scans
from pipeline.analysis import fwhm, haze
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import PRESETS, settings_for
from pipeline.optics.lattice import honeycomb, tube_lattice
from pipeline.optics.validation import compare_with_exact

VOXEL = 0.5  # µm: the studies' voxel
PITCH_VOX = 29  # birch's fibre pitch at 0.5 µm
WALLS_VOX = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
INDICES = {"+0.01": (1.50, 1.49), "-0.01": (1.49, 1.50), "+0.02": (1.51, 1.49), "-0.02": (1.49, 1.51)}
METHODS = ("paper", "fast", "accurate refine 1", "accurate")  # accurate: refine 2
FAMILIES = ("tubes_square_touching", "tubes_hex_merged", "honeycomb_hex_jittered", "honeycomb_square_rotated")


def lattice(family: str, wall_vox: float, pitch_vox: float = PITCH_VOX):
    """The reference of ``family`` with walls of ``wall_vox`` voxels at 0.5 µm (between two lumens
    for honeycombs; each tube's own wall for tubes, merged walls being twice as thick)."""
    p, w = pitch_vox * VOXEL, wall_vox * VOXEL
    if family == "tubes_square_touching":
        return tube_lattice(p, 0.5 * p, w, rotation_deg=8.0)
    if family == "tubes_hex_merged":
        return tube_lattice(p, 0.53 * p, w, packing="hex", rotation_deg=5.0)
    if family == "honeycomb_hex_jittered":
        return honeycomb(p, w, jitter=0.15, seed=3)
    if family == "honeycomb_square_rotated":
        return honeycomb(p, w, packing="square", rotation_deg=10.0, jitter=0.05, seed=5)
    raise ValueError(family)


def _case(args) -> dict:
    family, wall, pitch, dri, method, voxel, thickness, rays, *refine = args
    n_wall, n_poly = INDICES[dri]
    settings = settings_for(method, **({"refine": refine[0]} if refine else {}))
    r = compare_with_exact(lattice(family, wall, pitch), settings, voxel_um=voxel,
                           thickness_um=thickness, n_wall=n_wall, n_poly=n_poly, n_rays=rays)
    label = method if settings.refine == PRESETS[method].refine else f"{method} refine {settings.refine}"
    return {"family": family, "wall_vox": wall, "pitch_vox": pitch, "delta_ri": dri, "method": label,
            "refine": settings.refine, "voxel_um": voxel, "wall_vox_traced": wall * VOXEL / r["traced_voxel_um"],
            "thickness_um": thickness, "rays": rays, **r}


def _noise(args) -> dict:
    family, dri, deg = args
    n_wall, n_poly = INDICES[dri]
    lat = lattice(family, 4.0)
    beam = square_beam(4000, 150.0 / VOXEL, seed=1)
    a = lat.trace_independently(beam.origins * VOXEL, beam.direction, n_wall=n_wall, n_poly=n_poly, thickness_um=250.0)
    b = lat.trace_independently(beam.origins * VOXEL, beam.direction, n_wall=n_wall, n_poly=n_poly, thickness_um=250.0,
                  normal_noise_deg=deg)
    return {"family": family, "delta_ri": dri, "normal_noise_deg": deg,
            "fwhm_r_error": fwhm(b.theta_r[b.transmitted], "lorentz-mle") / fwhm(a.theta_r[a.transmitted], "lorentz-mle") - 1.0,
            "haze_error_points": 100.0 * (haze(b.direction[b.transmitted]) - haze(a.direction[a.transmitted]))}


def targets(rows: list[dict]) -> dict:
    """Per method and wall (voxels at 0.5 µm): the worst errors of the table, and whether they meet the targets."""
    out: dict = {}
    for method in METHODS:
        for wall in WALLS_VOX:
            sel = [r for r in rows if r["method"] == method and r["wall_vox"] == wall]
            if not sel:
                continue
            scale = 2.0 if method.startswith("fast") else 1.0
            f_tol = scale * (0.25 if wall < 4 else 0.10)
            worst_f = max((abs(r["fwhm_r_error"]) for r in sel if r["fwhm_r_error"] is not None), default=0.0)
            worst_h = max(abs(r["haze_error_points"]) for r in sel)
            worst_ks = max(r["ks"] for r in sel)
            out.setdefault(method, {})[f"{wall:g}"] = {
                "cases": len(sel), "worst_fwhm_r_error": worst_f, "median_abs_fwhm_r_error":
                float(np.median([abs(r["fwhm_r_error"]) for r in sel if r["fwhm_r_error"] is not None])),
                "worst_haze_error_points": worst_h,
                "worst_ks": worst_ks, "worst_ks_025deg": max(r["ks_025deg"] for r in sel),
                "meets_fwhm": worst_f <= f_tol, "meets_haze": worst_h <= 3.0 * scale,
                "meets_ks": worst_ks <= 0.06 * scale if wall >= 4 else None}
    return out


def table_md(rows: list[dict]) -> str:
    """Markdown: FWHM_R error [%] / haze error [points] per method × wall × sign of ΔRI (worst of the families)."""
    lines = ["| method | wall [voxels at 0.5 µm] | ΔRI > 0: worst FWHM_R error | worst haze error | "
             "ΔRI < 0: worst FWHM_R error | worst haze error | worst KS (0.25°) |", "|---|---|---|---|---|---|---|"]
    for method in METHODS:
        for wall in WALLS_VOX:
            cells = []
            sel_all = [r for r in rows if r["method"] == method and r["wall_vox"] == wall]
            if not sel_all:
                continue
            for sign in "+-":
                sel = [r for r in sel_all if r["delta_ri"].startswith(sign)]
                f = max((r["fwhm_r_error"] for r in sel if r["fwhm_r_error"] is not None), key=abs)
                h = max(sel, key=lambda r: abs(r["haze_error_points"]))["haze_error_points"]
                cells += [f"{100 * f:+.0f} %", f"{h:+.1f}"]
            ks = max(r["ks"] for r in sel_all)
            ks2 = max(r["ks_025deg"] for r in sel_all)
            lines.append(f"| {method} | {wall:g} | " + " | ".join(cells) + f" | {ks:.2f} ({ks2:.2f}) |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> dict:
    """Per method and family: rms and median |FWHM_R error| and haze error over the table, and how
    often each method is the closest to exact optics."""
    out: dict = {"rms": {}, "closest": {}}
    for method in METHODS:
        for family in ("all",) + FAMILIES:
            sel = [r for r in rows if r["method"] == method and family in ("all", r["family"])]
            f = [r["fwhm_r_error"] for r in sel if r["fwhm_r_error"] is not None]
            h = [r["haze_error_points"] for r in sel]
            if sel:
                out["rms"].setdefault(method, {})[family] = {
                    "cases": len(sel), "rms_fwhm_r_error": math.sqrt(np.mean(np.square(f))),
                    "median_abs_fwhm_r_error": float(np.median(np.abs(f))),
                    "rms_haze_error_points": math.sqrt(np.mean(np.square(h))),
                    "median_abs_haze_error_points": float(np.median(np.abs(h)))}
    rivals = ("fast", "accurate refine 1", "accurate")
    for what in ("fwhm_r_error", "haze_error_points"):
        count = dict.fromkeys(rivals, 0)
        for key in {(r["family"], r["wall_vox"], r["delta_ri"]) for r in rows}:
            case = {r["method"]: r for r in rows if (r["family"], r["wall_vox"], r["delta_ri"]) == key
                    and r["method"] in rivals}
            if len(case) == len(rivals) and all(c[what] is not None for c in case.values()):
                count[min(case, key=lambda m: abs(case[m][what]))] += 1
        out["closest"][what] = count
    return out


def summary_md(s: dict) -> str:
    lines = ["| method | cases | rms FWHM_R error | median abs. | rms haze error [points] | median abs. |"
             " closest to exact (FWHM_R, haze) |", "|---|---|---|---|---|---|---|"]
    for method, fams in s["rms"].items():
        a = fams["all"]
        closest = (f"{s['closest']['fwhm_r_error'].get(method, '–')}, "
                   f"{s['closest']['haze_error_points'].get(method, '–')}")
        lines.append(f"| {method} | {a['cases']} | {100 * a['rms_fwhm_r_error']:.0f} % | "
                     f"{100 * a['median_abs_fwhm_r_error']:.0f} % | {a['rms_haze_error_points']:.1f} | "
                     f"{a['median_abs_haze_error_points']:.1f} | {closest} |")
    lines += ["", "| family | " + " | ".join(s["rms"]) + " |", "|---|" + "---|" * len(s["rms"])]
    for family in FAMILIES:
        cells = [f"{100 * s['rms'][m][family]['rms_fwhm_r_error']:.0f} % / "
                 f"{s['rms'][m][family]['rms_haze_error_points']:.1f}" for m in s["rms"]]
        lines.append(f"| {family} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def refinement_md(rows: list[dict]) -> str:
    lines = ["| method | wall [µm] | voxel [µm] | wall [voxels] | rms FWHM_R error | rms haze error [points] | "
             "worst KS (0.25°) | trace [s] |", "|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["method"], r["wall_vox"] * VOXEL, r["voxel_um"]) for r in rows},
                  key=lambda k: (k[0], k[1], -k[2]))
    for method, wall_um, voxel in keys:
        sel = [r for r in rows if r["method"] == method and r["wall_vox"] * VOXEL == wall_um
               and r["voxel_um"] == voxel]
        f = math.sqrt(np.mean([r["fwhm_r_error"] ** 2 for r in sel if r["fwhm_r_error"] is not None]))
        h = math.sqrt(np.mean([r["haze_error_points"] ** 2 for r in sel]))
        lines.append(f"| {method} | {wall_um:g} | {voxel:g} | {wall_um / voxel:g} | {100 * f:.0f} % | {h:.1f} | "
                     f"{max(r['ks_025deg'] for r in sel):.2f} | {sum(r['seconds'] for r in sel):.0f} |")
    return "\n".join(lines)


def wood_section(tradeoff: Path) -> list[str]:
    """The voxel methods against `exact` on the wood itself, as `make tradeoff` measured them
    (results/tradeoff.json; traced there once, shown here beside the lattices)."""
    if not tradeoff.exists():
        return []
    import bench_tradeoff

    rows = json.loads(tradeoff.read_text())["rows"]
    return ["## On the wood itself: every voxel method against `exact`", "",
            "The lattices above stand in for wood; with `exact` the wood model has its own exact answer. "
            "From `make tradeoff` (details and costs in TRADEOFF.md): one wood per scene, a 150 µm beam, the bias "
            "of each setting against `exact` on the same rays with the 95 % interval of a paired bootstrap "
            "(FWHM in %, haze in points).", "", *bench_tradeoff.wood_errors_md(rows)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/accuracy.json")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--render", action="store_true",
                    help="only write the markdown (and the derived sections) from an existing --out")
    args = ap.parse_args()
    if args.render:
        doc = json.loads(Path(args.out).read_text())
        write(doc, Path(args.out))
        return
    t0 = time.perf_counter()
    main_cases = [(f, w, PITCH_VOX, d, m[0], VOXEL, 250.0, 4000, *m[1:])
                  for f in FAMILIES for w in WALLS_VOX for d in INDICES
                  for m in (("fast",), ("accurate", 1), ("accurate",))]
    paper_cases = [(f, 4.0, PITCH_VOX, d, "paper", VOXEL, 250.0, 500) for f in FAMILIES for d in ("+0.01", "-0.01")]
    geometry_cases = ([(f, 4.0, p, d, m, VOXEL, 250.0, 4000) for f in FAMILIES for p in (20, 80)
                       for d in ("+0.01", "-0.01") for m in ("fast", "accurate")]
                      + [(f, 4.0, PITCH_VOX, d, m, VOXEL, 1000.0, 4000) for f in FAMILIES
                         for d in ("+0.01", "-0.01") for m in ("fast", "accurate")])
    # Voxel size alone: every method on its own voxels (refine 1).
    refine_cases = [(f, w, PITCH_VOX, d, m, v, 250.0, 2000, 1) for f in FAMILIES for w in (2.0, 4.0, 8.0)
                    for d in ("+0.01", "-0.01") for m in ("fast", "accurate") for v in (0.5, 0.25, 0.125)]
    noise_cases = [(f, d, deg) for f in FAMILIES for d in ("+0.01", "-0.01") for deg in (0.1, 0.3, 1.0, 2.0)]
    with ProcessPoolExecutor(args.workers) as pool:
        # The slow ones first, so the workers finish together.
        paper = list(pool.map(_case, paper_cases))
        refine = list(pool.map(_case, refine_cases))
        table = list(pool.map(_case, main_cases))
        geometry = list(pool.map(_case, geometry_cases))
        noise = list(pool.map(_noise, noise_cases))
    doc = {
        "description": __doc__.strip(),
        "voxel_um": VOXEL, "pitch_vox": PITCH_VOX, "beam_um": 150.0,
        "table": table + paper, "geometry": geometry, "refinement": refine, "noise_floor": noise,
        "seconds": time.perf_counter() - t0, "workers": args.workers,
    }
    write(doc, Path(args.out))


def write(doc: dict, out: Path) -> None:
    """Add the derived sections to ``doc``, write it as JSON to ``out`` and its tables as markdown beside it."""
    rows, refine, noise = doc["table"], doc["refinement"], doc["noise_floor"]
    doc["targets"] = targets(rows)
    doc["summary"] = summary(rows)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    md = ["# Tracing methods against exact optics of many thin walls", "",
          f"Generated by `make bench-accuracy` ({doc['seconds'] / 60:.1f} min on {doc['workers']} workers); "
          "every number is in `accuracy.json`. Lattices of 4 families (tubes touching on a square lattice, "
          "tubes merged on a hexagonal one, a jittered hexagonal honeycomb, a rotated square one), pitch 29 "
          "voxels, walls 1.5-8 voxels at 0.5 µm, ΔRI ±0.01 and ±0.02, 0.25 mm thick, 4000 rays (`paper`: "
          "500 rays, walls of 4 voxels, ΔRI ±0.01). `accurate` traces on 0.25 µm voxels (refine 2), "
          "`accurate refine 1` on the studies' 0.5 µm.", "",
          "## Over all cases", "", summary_md(doc["summary"]), "",
          "## Worst errors per method, wall and sign of ΔRI", "",
          table_md(rows), "",
          "## Refinement: the same lattices at smaller voxels (rms over families and ΔRI ±0.01)", "",
          refinement_md(refine), "",
          "## Noise floor: exact optics with unbiased random normal errors", "",
          "| normal error [degree] | rms FWHM_R change | rms haze change [points] |", "|---|---|---|"]
    for deg in (0.1, 0.3, 1.0, 2.0):
        sel = [r for r in noise if r["normal_noise_deg"] == deg]
        md.append(f"| {deg:g} | {100 * math.sqrt(np.mean([r['fwhm_r_error'] ** 2 for r in sel])):.0f} % | "
                  f"{math.sqrt(np.mean([r['haze_error_points'] ** 2 for r in sel])):.1f} |")
    md += ["", *wood_section(out.parent / "tradeoff.json")]
    md += ["", *scans.section_of(out.parent, "##")]
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
