"""Grey-level scans against `exact` (results/iso.json from `make bench-iso`), as Markdown for
results/iso.md, results/accuracy.md and REPORT.md (docs/methods.md#iso-surfaces)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def configurations(doc: dict) -> list[dict]:
    """The measured configurations of an iso.json (one per preset and thickness), thinnest first."""
    configs = doc["configs"] if "configs" in doc else [doc]
    return sorted(configs, key=lambda c: (c["args"]["preset"], c["args"]["thickness_mm"]))


def read(path: Path) -> list[dict]:
    """The configurations in ``path``, or none when it does not exist."""
    return configurations(json.loads(Path(path).read_text())) if Path(path).exists() else []


def read_lattices(path: Path) -> list[dict]:
    """The reference lattices' rows in ``path`` (none when not measured)."""
    if not Path(path).exists():
        return []
    return json.loads(Path(path).read_text()).get("lattices", {}).get("rows", [])


def read_normals(path: Path) -> list[dict]:
    """The rows of `iso`'s normals on a flat wall's scan in ``path`` (results/iso_normals.json from
    ``benchmarks/iso_normals.py``; none when not measured)."""
    if not Path(path).exists():
        return []
    return json.loads(Path(path).read_text())["rows"]


NORMALS = ("Why `iso`'s FWHM_L comes out high: its normals on a partial-volume scan of a flat wall "
           "(`benchmarks/iso_normals.py`, results/iso_normals.json). A half-space of wall, its normal tilted "
           "in the R-T plane and towards L, scanned at 0.5 µm and 0.25 µm as above (4³ points a voxel), traced with `iso` "
           "at ½ by rays along T. Each ray crosses the wall once, and its refraction gives the normal it was "
           "refracted by, n_wall·d_out − n_poly·d_in. The table gives how far that normal is from the "
           "wall's, in all and along L (the part that deflects θ_L).")

NORMALS_AFTER = (
    "The trilinear iso-surface of a partial-volume scan is faceted. A flat wall turned 20° from the grid has "
    "normals 6-8° off RMS (12-15° at the 95th percentile); tilted 1-5° towards L, as fibre walls are along their "
    "length, it has normals 2-5° off. Along L, the part that deflects θ_L, the error is 0.9-6° RMS. The angles are "
    "the same at 0.25 µm as at 0.5 µm, because the facets scale with the voxel. That is why finer scans did not shrink "
    "`iso`'s FWHM_L excess above: it is positive in all six clean rows (+12 to +39 %, two resolved alone), +33 % "
    "at 0.25 µm as at 0.5 µm. A pre-filter of σ one voxel (0.5 µm here) leaves about 1.3° RMS, 0.1-1.4° along L. "
    "With it the excess at 0.25-0.5 µm is +3 to +23 %, none resolved. The size fits:\n"
    "- at ΔRI 0.01, a normal off by δ turns a ray by about (ΔRI/n)·δ ≈ 0.0065·δ;\n"
    "- about 30 walls of birch 0.25 mm, each off by 1-2° along L, add about 0.04-0.07° RMS to θ_L, which is "
    "0.1-0.17° as a Gaussian FWHM;\n"
    "- `exact`'s FWHM_L there is 0.07-0.40°;\n"
    "- FWHM_R, at 5-9°, does not notice.")


def normals_table(rows: list[dict]) -> list[str]:
    out = ["| voxel [µm] | pre-filter σ [µm] | wall tilted to L [°] | wall turned in R-T [°] | normal off, RMS [°] | "
           "95 % [°] | along L, RMS [°] | in R-T, RMS [°] |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['voxel_um']:g} | {r['smooth_um']:g} | {r['alpha_deg']:g} | {r['beta_deg']:g} | {r['angle_rms_deg']:.2f} | "
                   f"{r['angle_p95_deg']:.2f} | {r['along_l_rms_deg']:.2f} | {r['across_rms_deg']:.2f} |")
    return out


def lattice_table(rows: list[dict]) -> list[str]:
    """Per method and wall: rms and worst FWHM_R error (Lorentz MLE, as results/accuracy.md) and haze
    error over the families and ΔRI ±0.01, ±0.02; the last rows over every wall."""
    if not rows:
        return []
    lines = ["| method | wall [voxels at 0.5 µm] | cases | rms FWHM_R error | worst | rms haze error [points] | worst |"
             " interfaces met [% of exact's] |", "|---|---|---|---|---|---|---|---|"]
    walls = sorted({r["wall_vox"] for r in rows})
    for method in ("iso", "accurate", "fast"):
        for wall in walls + [None]:
            sel = [r for r in rows if r["method"] == method and wall in (None, r["wall_vox"])]
            f = np.array([r["fwhm_r_error"] for r in sel if r["fwhm_r_error"] is not None])
            hz = np.array([r["haze_error_points"] for r in sel])
            met = sum(r["interfaces"] for r in sel) / sum(r["interfaces_exact"] for r in sel) - 1.0
            lines.append(f"| {method} | {'all' if wall is None else f'{wall:g}'} | {len(sel)} | "
                         f"{100 * np.sqrt(np.mean(f ** 2)):.0f} % | {100 * f[np.argmax(abs(f))]:+.0f} % | "
                         f"{np.sqrt(np.mean(hz ** 2)):.1f} | {hz[np.argmax(abs(hz))]:+.1f} | {100 * met:+.1f} |")
    return lines


def _scene(a: dict) -> str:
    return f"{a['preset']} {a['thickness_mm']:g} mm"


def difference_table(configs: list[dict]) -> list[str]:
    """One table of every configuration: each method's difference from `exact` on the same wood, beam and
    rays, mean over the woods ± a 95 % t interval over them."""
    lines = ["| scene | voxel [µm] | scan | method | FWHM_R [%] | FWHM_L [%] | haze [points] | "
             "interfaces met [% of exact's] | µs an interface | rays not transmitted |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in configs:
        a = c["args"]
        n_exact = sum(r["interfaces"] for r in c["rows"] if r["method"] == "exact")
        for e in c["table"]:
            lines.append(f"| {_scene(a)} | {e['voxel_um']:g} | {e['scan']} | {e['method']} | "
                         f"{e['fwhm_r'][0]:+.1f} ± {e['fwhm_r'][1]:.1f} | {e['fwhm_l'][0]:+.1f} ± {e['fwhm_l'][1]:.1f} | "
                         f"{e['haze'][0]:+.2f} ± {e['haze'][1]:.2f} | {100 * (e['interfaces'] / n_exact - 1):+.1f} | "
                         f"{e['us_per_interface']:.2f} | {e['lost']} of {e['woods'] * a['rays']} |")
    return lines


def how_made(configs: list[dict]) -> list[str]:
    """Per configuration: the scene, the scan, `exact`'s own values and what the scans cost."""
    out = []
    for c in configs:
        a, rows = c["args"], c["rows"]
        ex = [r for r in rows if r["method"] == "exact"]
        n_exact = sum(r["interfaces"] for r in ex)
        vals = {q: [r[q] for r in ex] for q in ("fwhm_r", "fwhm_l", "haze")}
        voxels = sorted({r["voxel_um"] for r in rows if r["voxel_um"] is not None}, reverse=True)
        scans = {v: np.mean([r["scan_s"] for r in rows if r["voxel_um"] == v and r["scan"] == "clean"
                             and r["method"] == "iso"]) for v in voxels}
        out.append(f"* **{_scene(a)}** at ΔRI {a['delta_ri']}: {len(ex)} woods x {a['rays']} rays, a {a['beam_um']:g} µm "
                   f"beam in the middle of a {a['side_um']:g} µm wide scan ({a['supersample']}³ fine voxels a voxel); "
                   f"`exact` FWHM_R {min(vals['fwhm_r']):.2f}-{max(vals['fwhm_r']):.2f}°, FWHM_L "
                   f"{min(vals['fwhm_l']):.3f}-{max(vals['fwhm_l']):.3f}°, haze {100 * min(vals['haze']):.1f}-"
                   f"{100 * max(vals['haze']):.1f} %, {n_exact:,} interfaces at "
                   f"{1e6 * sum(r['cpu_s'] for r in ex) / n_exact:.1f} µs; making the parts of the clean scan that "
                   "`iso`'s rays read (the first traced) took " + ", ".join(f"{scans[v]:.0f} s a wood at {v:g} µm" for v in voxels)
                   + f" ({c.get('seconds', float('nan')) / 60:.1f} min in all).")
    return out


def cost_table(configs: list[dict]) -> list[str]:
    """Per scene, voxel and method: µs an interface (warm, the scan's parts already made) and the CPU
    seconds a wood's scan took to make where that method's rays read it."""
    lines = ["| scene | voxel [µm] | scan | method | µs an interface, warm | making the parts read [s a wood] |",
             "|---|---|---|---|---|---|"]
    for c in configs:
        a, rows = c["args"], c["rows"]
        ex = [r for r in rows if r["method"] == "exact"]
        lines.append(f"| {_scene(a)} | – | – | exact | {1e6 * sum(r['cpu_s'] for r in ex) / sum(r['interfaces'] for r in ex):.2f} | – |")
        for e in c["table"]:
            mine = [r for r in rows if r["voxel_um"] == e["voxel_um"] and r["scan"] == e["scan"]
                    and r["method"] == e["method"]]
            lines.append(f"| {_scene(a)} | {e['voxel_um']:g} | {e['scan']} | {e['method']} | "
                         f"{e['us_per_interface']:.2f} | {np.mean([r['scan_s'] for r in mine]):.0f} |")
    return lines


INTRO = ("A grey-level scan of generated wood (each voxel's wall fraction from fine voxels of the generator's own "
         "wood; clean, or blurred with noise) traced with `iso` on its iso-surface at ½, and binarised at ½ with "
         "`accurate` and `fast` on its own voxels (and `iso` on the scan pre-filtered by a Gaussian of σ 0.5 µm, "
         "`--smooth-um 0.5`: on the noisy scans, and on birch 0.25 mm's clean scan at 0.5 µm; what `twray trace "
         "--method iso` does unless told, where the rows named `iso` are its `--smooth-um 0`), beside `exact` on "
         "the same wood, beam and rays "
         "(docs/methods.md#iso-surfaces). Each cell: the difference from `exact` (relative for the half-max widths, "
         "in points for haze), its mean over the woods ± a 95 % t interval over them; each wood's difference "
         "carries its own ray sampling, so the interval holds both. Rays not transmitted left through the scan's "
         "sides, were reflected or trapped.")


LATTICES = ("The reference lattices of the tables above (4 families, walls 1.5-8 voxels at 0.5 µm, ΔRI ±0.01 and "
            "±0.02, 0.25 mm, 4000 rays) as grey scans at 0.5 µm, each voxel's wall fraction from 4² points of its "
            "section: `iso` at ½, and `accurate` and `fast` on the same scan binarised at ½, against the lattices' "
            "independent exact tracer on the same rays (FWHM_R by Lorentz MLE, as above).")


MANY_WOODS = ("The aim at 0.5 µm, on 25 woods (results/iso_25woods.json, `make bench-iso`): the same scene as "
              "the first rows above, its clean scan traced with `iso`, with `iso` after a pre-filter of σ one voxel "
              "(`--smooth-um 0.5`) and binarised with `accurate`, against `exact` on the same woods, beam and rays; "
              "the aim is 5 % in FWHM_R and FWHM_L and 1 point in haze. The smoothed rows were a second run on "
              "the same `exact` rows (bit for bit), so their µs an interface are not comparable with the others'.")


def section(configs: list[dict], heading: str = "##", lattice_rows: list[dict] | None = None,
            normal_rows: list[dict] | None = None, many_woods: list[dict] | None = None) -> list[str]:
    """The section of results/accuracy.md and REPORT.md (none without measurements)."""
    if not configs and not lattice_rows and not normal_rows and not many_woods:
        return []
    out = [f"{heading} Grey-level scans: `iso` and the binarised voxel methods against `exact`", ""]
    if configs:
        out += [INTRO, "", *difference_table(configs), "", *how_made(configs), ""]
    if many_woods:
        out += [MANY_WOODS, "", *difference_table(many_woods), ""]
    if lattice_rows:
        out += [LATTICES, "", *lattice_table(lattice_rows), ""]
    if normal_rows:
        out += [NORMALS, "", *normals_table(normal_rows), "", NORMALS_AFTER, ""]
    return out


def section_of(results: Path, heading: str = "##") -> list[str]:
    """The section from what ``make bench-iso`` wrote under ``results`` (iso.json, iso_25woods.json,
    iso_normals.json)."""
    results = Path(results)
    return section(read(results / "iso.json"), heading, read_lattices(results / "iso.json"),
                   read_normals(results / "iso_normals.json"), read(results / "iso_25woods.json"))
