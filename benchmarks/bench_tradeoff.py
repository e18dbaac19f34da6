"""The speed/accuracy trade of every tracing setting (`make tradeoff`).

Writes results/tradeoff.zarr (an xarray Dataset, one entry per traced point),
results/figures/tradeoff.png (error against time, a Pareto front per scene)
and results/TRADEOFF.md (what to use for a given precision, and whether
Table 1's setting is converged).

Scenes: birch 0.25 mm (ΔRI +0.01) and 1 mm (ΔRI −0.02), balsa 1 mm
(ΔRI +0.01), and two exact references of many thin walls, 0.25 mm thick
(tubes touching on a square lattice and a jittered hexagonal honeycomb,
pitch 14.5 µm, walls 2 µm, ΔRI +0.01), whose answer is exact optics of the
same rays.  Axes: method (`paper`, `fast`, `accurate`), the voxel the wood
is traced on (1, 0.5, 0.25, 0.125 µm: the same physical wood, a function
of position), rays (100 … 4000) and the paper's marching step.  `accurate`
here is traced on the voxel named: the `accurate` preset of a study at
0.5 µm (refine 2) is the `accurate` point at 0.25 µm.

Each point runs in a fresh process (cold: its wood generated, its kernels
loaded from Numba's cache), two at a time on a 2-core machine.  Error =
systematic part (bias against the scene's reference: exact optics of the
same rays, or the finest setting with the most rays) and statistical part
(95 % CI half-width); total = sqrt(bias² + half-width²).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from pipeline.report import TRADEOFF_TARGETS, cheapest_meeting

BEAM_UM = 150.0
SEED = 1
N_BOOT = 100
LATTICE_THICKNESS_UM = 250.0


def scenes() -> dict:
    """name: (kind, what, thickness [µm], n_wall, n_poly)."""
    return {
        "birch_0.25mm": ("wood", "birch", 250.0, 1.50, 1.49),
        "birch_1mm": ("wood", "birch", 1000.0, 1.47, 1.49),
        "balsa_1mm": ("wood", "balsa", 1000.0, 1.50, 1.49),
        "tubes_exact": ("lattice", "tubes", LATTICE_THICKNESS_UM, 1.50, 1.49),
        "honeycomb_exact": ("lattice", "honeycomb", LATTICE_THICKNESS_UM, 1.50, 1.49),
    }


def lattice(what: str):
    from pipeline.optics.lattice import honeycomb, tube_lattice

    if what == "tubes":
        return tube_lattice(14.5, 7.25, 2.0, rotation_deg=8.0)
    return honeycomb(14.5, 2.0, jitter=0.15, seed=3)


def points(quick: bool = False) -> list[dict]:
    """Every (scene, method, voxel, rays, step) to trace; ``reference`` marks each wood scene's."""
    P = []

    def add(scene, method, voxel, rays, step=None, reference=False):
        P.append({"scene": scene, "method": method, "voxel_um": voxel, "rays": rays,
                  "step_vox": step if method == "paper" else float("nan"), "reference": reference})

    if quick:  # a smoke run for the tests: seconds
        for m in ("fast", "accurate"):
            add("tubes_exact", m, 0.5, 100)
        add("tubes_exact", "paper", 0.5, 30, 2.0)
        return P
    for sc in ("birch_0.25mm", "tubes_exact", "honeycomb_exact"):
        for m in ("fast", "accurate"):
            for v in (1.0, 0.5, 0.25, 0.125):
                add(sc, m, v, 1000)
        add(sc, "paper", 1.0, 300, 1.5)
        add(sc, "paper", 0.5, 300, 2.0)
        add(sc, "paper", 0.5, 300, 1.0)
        add(sc, "paper", 0.25, 300, 2.0)
    for n in (100, 300, 3000):  # rays: the statistical part
        add("birch_0.25mm", "fast", 0.5, n)
        add("birch_0.25mm", "accurate", 0.25, n)
    add("birch_0.25mm", "accurate", 0.125, 4000, reference=True)
    for sc, voxels in (("birch_1mm", (1.0, 0.5, 0.25)), ("balsa_1mm", (0.5, 0.25))):
        for m in ("fast", "accurate"):
            for v in voxels:
                add(sc, m, v, 500)
    add("birch_1mm", "accurate", 0.125, 500)  # the same 500 rays one step finer than Table 1's
    for sc in ("birch_1mm", "balsa_1mm"):
        add(sc, "paper", 0.5, 150, 2.0)
        add(sc, "accurate", 0.25, 2000, reference=True)
    return P


def run_point(p: dict) -> dict:
    """Trace one point cold in this process; its summary and its cost."""
    from pipeline.analysis import fwhm, fwhm_ci, haze, haze_ci, summarize
    from pipeline.optics.sources import WoodSource
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import settings_for
    from pipeline.optics.voxels import trace_beam
    from pipeline.params import build_params

    kind, what, thickness, n_wall, n_poly = scenes()[p["scene"]]
    v = p["voxel_um"]
    changes = {"refine": 1}
    if p["method"] == "paper":
        changes["step_vox"] = p["step_vox"]
    settings = settings_for(p["method"], **changes)
    beam = square_beam(p["rays"], BEAM_UM / v, seed=SEED)
    if kind == "wood":
        source = WoodSource(build_params(what), thickness_um=thickness, voxel_um=v, seed=SEED)
    else:
        lat = lattice(what)
        source = lat.source(thickness_um=thickness, voxel_um=v)
    t0, c0 = time.perf_counter(), time.process_time()
    res = trace_beam(source, beam, n_wall=n_wall, n_poly=n_poly, settings=settings, seed=SEED)
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    s = summarize(res, n_boot=N_BOOT, seed=SEED)
    out = {**p, "fwhm_r": s["fwhm_r_deg"], "fwhm_r_ci": s["fwhm_r_ci_deg"], "fwhm_l": s["fwhm_l_deg"],
           "fwhm_l_ci": s["fwhm_l_ci_deg"], "haze": s["haze"], "haze_ci": s["haze_ci"],
           "interfaces_per_ray": s["interfaces_per_ray"], "transmitted": s["n_transmitted"],
           "voxels_read": float(s["voxels_read"]),
           "wall_s": wall_s, "cpu_s": cpu_s,
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if kind == "wood":
        cv = int(np.prod(source.chunks))
        out["voxels_generated"] = float(len(source.distinct) * cv)
        idx = np.array(sorted(source.distinct))
        box = np.prod(idx.max(axis=0) - idx.min(axis=0) + 1)
        out["generated_fraction_of_box"] = float(len(idx) / box)
    else:
        out["voxels_generated"] = float("nan")
        out["generated_fraction_of_box"] = float("nan")
        ex = lat.trace(beam.origins * v, beam.direction, n_wall=n_wall, n_poly=n_poly, thickness_um=thickness)
        t = ex.transmitted
        h = haze(ex.direction[t])
        out["exact"] = {"fwhm_r": fwhm(ex.theta_r[t]), "fwhm_l": fwhm(ex.theta_l[t]), "haze": h,
                        "fwhm_r_ci": list(fwhm_ci(ex.theta_r[t], n_boot=N_BOOT, seed=SEED)),
                        "haze_ci": list(haze_ci(h, int(t.sum())))}
    return out


def _half(ci) -> float:
    return (ci[1] - ci[0]) / 2.0


def errors(rows: list[dict]) -> None:
    """Add the reference, bias (systematic), half-width (statistical) and total error to each row."""
    refs = {r["scene"]: r for r in rows if r["reference"]}
    for r in rows:
        ref = r.get("exact") or refs.get(r["scene"])
        if ref is None:
            continue
        r["ref_fwhm_r"], r["ref_fwhm_l"], r["ref_haze"] = ref["fwhm_r"], ref["fwhm_l"], ref["haze"]
        r["ref_kind"] = "exact optics, same rays" if "exact" in r else "finest setting, most rays"
        for q in ("fwhm_r", "haze"):
            bias = r[q] - ref[q]
            half = _half(r[f"{q}_ci"])
            r[f"{q}_bias"], r[f"{q}_half"] = bias, half
            r[f"{q}_error"] = math.hypot(bias, half) if not r["reference"] else half
        r["fwhm_r_rel_error"] = r["fwhm_r_error"] / ref["fwhm_r"]


# ---------------------------------------------------------------------- outputs
VARS = {  # name: (row key, long_name, units)
    "FWHM_R": ("fwhm_r", "FWHM of the Lorentz fit to theta_R", "degree"),
    "FWHM_L": ("fwhm_l", "FWHM of the Lorentz fit to theta_L", "degree"),
    "haze": ("haze", "fraction deviating more than 2.5 degree", "1"),
    "reference_FWHM_R": ("ref_fwhm_r", "the scene's reference FWHM_R", "degree"),
    "reference_haze": ("ref_haze", "the scene's reference haze", "1"),
    "FWHM_R_bias": ("fwhm_r_bias", "systematic error of FWHM_R (against the reference)", "degree"),
    "FWHM_R_halfwidth": ("fwhm_r_half", "statistical error of FWHM_R (95 % CI half-width)", "degree"),
    "FWHM_R_error": ("fwhm_r_error", "total error of FWHM_R, sqrt(bias^2 + halfwidth^2)", "degree"),
    "haze_bias": ("haze_bias", "systematic error of haze (against the reference)", "1"),
    "haze_halfwidth": ("haze_half", "statistical error of haze (Wilson 95 % half-width)", "1"),
    "haze_error": ("haze_error", "total error of haze, sqrt(bias^2 + halfwidth^2)", "1"),
    "interfaces_per_ray": ("interfaces_per_ray", "mean interfaces met per ray", "1"),
    "wall_time": ("wall_s", "wall time of the trace, cold (wood generated as it is read)", "s"),
    "cpu_time": ("cpu_s", "CPU time of the trace", "s"),
    "peak_rss": ("peak_rss_mb", "peak resident memory of the process", "MiB"),
    "voxels_generated": ("voxels_generated", "wood voxels generated for the trace", "1"),
    "voxels_read": ("voxels_read", "voxels the tracer read: paths and normal neighbourhoods", "1"),
    "generated_fraction": ("generated_fraction_of_box", "generated chunks / chunks of their bounding box", "1"),
}


def dataset(rows: list[dict], seconds: float):
    import xarray as xr

    from pipeline.provenance import provenance_attrs

    n = len(rows)
    coords = {
        "point": ("point", np.arange(n)),
        "scene": ("point", np.array([r["scene"] for r in rows], dtype=object)),
        "method": ("point", np.array([r["method"] for r in rows], dtype=object)),
        "voxel_um": ("point", np.array([r["voxel_um"] for r in rows]), {"units": "um",
                     "long_name": "voxel the wood is traced on"}),
        "rays": ("point", np.array([r["rays"] for r in rows])),
        "step_vox": ("point", np.array([r["step_vox"] for r in rows]), {"long_name": "paper marching step"}),
        "reference": ("point", np.array([r["reference"] for r in rows])),
    }
    data = {name: ("point", np.array([r.get(key, np.nan) for r in rows], dtype=float),
                   {"long_name": ln, "units": u}) for name, (key, ln, u) in VARS.items()}
    ds = xr.Dataset(data, coords=coords, attrs={
        "title": "twray speed/accuracy trade", "description": __doc__.strip(),
        "seconds": seconds, "machine_cpus": os.cpu_count() or 1, "beam_um": BEAM_UM, "seed": SEED,
        "scenes": json.dumps(scenes())})
    ds.attrs.update(provenance_attrs({"points": [{k: r[k] for k in ("scene", "method", "voxel_um", "rays",
                                                                      "step_vox")} for r in rows]}))
    return ds


def _label(r: dict) -> str:
    step = f", step {r['step_vox']:g}" if r["method"] == "paper" else ""
    return f"`{r['method']}` at {r['voxel_um']:g} µm, {r['rays']} rays{step}"


TARGETS = TRADEOFF_TARGETS  # (name, haze error [points], FWHM_R relative)


def recommend(rows: list[dict]) -> list[str]:
    lines = ["| scene | target | cheapest setting that meets it | wall time (cold, 1 core) | its errors |",
             "|---|---|---|---|---|"]
    for sc in scenes():
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r and not r["reference"]]
        for name, h, f in TARGETS:
            b = cheapest_meeting(sel, h, f)
            if b is None:
                lines.append(f"| {sc} | {name} | none of the swept settings | | |")
                continue
            lines.append(f"| {sc} | {name} | {_label(b)} | {b['wall_s']:.1f} s | haze ±{100 * b['haze_error']:.1f} "
                         f"points, FWHM_R ±{100 * abs(b['fwhm_r_rel_error']):.0f} % |")
    return lines


def best(rows: list[dict]) -> list[str]:
    lines = ["| scene | reference | smallest haze error | by | smallest FWHM_R error | by |", "|---|---|---|---|---|---|"]
    for sc in scenes():
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r and not r["reference"]]
        if not sel:
            continue
        h = min(sel, key=lambda r: r["haze_error"])
        f = min(sel, key=lambda r: abs(r["fwhm_r_rel_error"]))
        lines.append(f"| {sc} | {sel[0]['ref_kind']} | ±{100 * h['haze_error']:.1f} points | {_label(h)} | "
                     f"±{100 * abs(f['fwhm_r_rel_error']):.0f} % | {_label(f)} |")
    return lines


def paper_vs(rows: list[dict]) -> list[str]:
    lines = ["| scene | `paper` (0.5 µm, step 2) | its haze / FWHM_R error | `accurate` at 0.25 µm "
             "(the studies' preset) | its haze / FWHM_R error | time ratio paper / accurate per ray |",
             "|---|---|---|---|---|---|"]
    for sc in scenes():
        p = [r for r in rows if r["scene"] == sc and r["method"] == "paper" and r["voxel_um"] == 0.5
             and r["step_vox"] == 2.0 and "haze_error" in r]
        a = [r for r in rows if r["scene"] == sc and r["method"] == "accurate" and r["voxel_um"] == 0.25
             and not r["reference"] and "haze_error" in r]
        if not p or not a:
            continue
        p, a = p[0], max(a, key=lambda r: r["rays"])
        ratio = (p["wall_s"] / p["rays"]) / (a["wall_s"] / a["rays"])
        lines.append(f"| {sc} | {p['wall_s']:.1f} s ({p['rays']} rays) | ±{100 * p['haze_error']:.1f} pts / "
                     f"±{100 * abs(p['fwhm_r_rel_error']):.0f} % | {a['wall_s']:.1f} s ({a['rays']} rays) | "
                     f"±{100 * a['haze_error']:.1f} pts / ±{100 * abs(a['fwhm_r_rel_error']):.0f} % | {ratio:.1f} |")
    return lines


def _overlap(a: dict, b: dict) -> bool:
    """Whether both the FWHM_R and the haze intervals of ``a`` and ``b`` overlap."""
    return all(a[k][0] <= b[k][1] and b[k][0] <= a[k][1] for k in ("fwhm_r_ci", "haze_ci"))


def convergence(rows: list[dict]) -> list[str]:
    """Table 1's setting (the `accurate` preset at 0.5 µm = traced at 0.25 µm, 1000 rays): how far its
    values move one voxel step finer (the same rays), and how wide their intervals are at 1000 rays."""
    out = []
    for sc in ("birch_0.25mm", "birch_1mm"):
        acc = {}
        for r in rows:
            if r["scene"] == sc and r["method"] == "accurate" and not r["reference"]:
                acc.setdefault(r["rays"], {})[r["voxel_um"]] = r
        ladder = max(acc.items(), key=lambda kv: (0.125 in kv[1], len(kv[1])), default=(None, {}))
        n, by_voxel = ladder
        if not by_voxel or 0.25 not in by_voxel:
            continue
        steps = " → ".join(f"{v:g} µm: FWHM_R {r['fwhm_r']:.2f}°, haze {100 * r['haze']:.1f} %"
                           for v, r in sorted(by_voxel.items(), reverse=True))
        line = f"- **{sc}**, `accurate`, the same {n} rays at each voxel: {steps}."
        if 0.125 in by_voxel:
            a, b = by_voxel[0.25], by_voxel[0.125]
            line += (f" From Table 1's 0.25 µm to 0.125 µm FWHM_R moves {b['fwhm_r'] - a['fwhm_r']:+.2f}° "
                     f"({100 * (b['fwhm_r'] / a['fwhm_r'] - 1):+.0f} %) and haze {100 * (b['haze'] - a['haze']):+.1f} "
                     f"points.")
        ref = next((r for r in rows if r["scene"] == sc and r["reference"]), None)
        finest = by_voxel[min(by_voxel)]
        if ref is not None and ref["voxel_um"] > finest["voxel_um"]:
            line += (f" The finest, {finest['fwhm_r']:.2f}° [{finest['fwhm_r_ci'][0]:.2f}, "
                     f"{finest['fwhm_r_ci'][1]:.2f}] and {100 * finest['haze']:.1f} % [{100 * finest['haze_ci'][0]:.1f}, "
                     f"{100 * finest['haze_ci'][1]:.1f}], against Table 1's voxel with {ref['rays']} rays, "
                     f"{ref['fwhm_r']:.2f}° [{ref['fwhm_r_ci'][0]:.2f}, {ref['fwhm_r_ci'][1]:.2f}] and "
                     f"{100 * ref['haze']:.1f} % [{100 * ref['haze_ci'][0]:.1f}, {100 * ref['haze_ci'][1]:.1f}]: "
                     f"{'the intervals overlap' if _overlap(finest, ref) else 'the intervals do not overlap'}.")
        if ref is not None:
            scale = math.sqrt(ref["rays"] / 1000.0)  # intervals narrow as 1/sqrt(rays)
            line += (f" At 1000 rays the 95 % half-widths are about ±{_half(ref['fwhm_r_ci']) * scale:.2f}° "
                     f"(±{100 * _half(ref['fwhm_r_ci']) * scale / ref['fwhm_r']:.0f} %) for FWHM_R and "
                     f"±{100 * _half(ref['haze_ci']) * scale:.1f} points for haze (from {_label(ref)}, scaled as "
                     f"1/√rays).")
        out.append(line)
    return out


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [sc for sc in scenes() if any(r["scene"] == sc and "haze_error" in r for r in rows)]
    fig, axes = plt.subplots(2, len(names), figsize=(4.0 * len(names), 7.0), squeeze=False)
    markers = {"paper": "s", "fast": "o", "accurate": "^"}
    for j, sc in enumerate(names):
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r and not r["reference"]]
        for i, (key, scale, label) in enumerate((("haze_error", 100.0, "haze error [points]"),
                                                 ("fwhm_r_rel_error", 100.0, "FWHM_R error [%]"))):
            ax = axes[i, j]
            for m, mk in markers.items():
                pts = [r for r in sel if r["method"] == m]
                ax.scatter([r["wall_s"] for r in pts], [abs(r[key]) * scale for r in pts], marker=mk,
                           c=[math.log2(r["voxel_um"]) for r in pts], cmap="viridis", vmin=-3, vmax=0,
                           edgecolors="k", linewidths=0.5)
                ax.scatter([], [], marker=mk, facecolors="w", edgecolors="k", label=m)
            front, best = [], math.inf
            for r in sorted(sel, key=lambda r: r["wall_s"]):
                e = abs(r[key]) * scale
                if e < best:
                    best = e
                    front.append((r["wall_s"], e))
            if front:
                ax.step(*zip(*front), where="post", color="0.4", lw=1)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall time, cold [s]")
            ax.set_ylabel(label)
            if i == 0:
                ax.set_title(sc)
            if i == 0 and j == 0:
                ax.legend(title="colour: voxel, dark 0.125 µm, yellow 1 µm", fontsize=7, title_fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def report(rows: list[dict], seconds: float, workers: int) -> str:
    md = ["# Speed against accuracy", "",
          f"Generated by `make tradeoff` ({seconds / 60:.1f} min on {workers} processes, each point cold in its "
          "own process); every number is in `results/tradeoff.zarr` (`xr.open_zarr`), the figure is "
          "`results/figures/tradeoff.png`. Error = sqrt(bias² + CI half-width²): the bias is against exact "
          "optics of the same rays (lattices) or against the scene's finest setting with the most rays "
          "(wood). Voxel = the voxel the wood is traced on (the `accurate` preset of a study traces on half "
          "the study's voxel).", "",
          "![error against time](figures/tradeoff.png)", "",
          "## What to use", "", *recommend(rows), "",
          "## The best any swept setting reaches", "", *best(rows), "",
          "Against exact optics of thin walls (the lattices) the error does not fall steadily as the voxel "
          "shrinks: binary voxels alias walls into staircases whose smoothed normals err by degrees "
          "(results/accuracy.md). Against the wood's own finest setting, values settle; settling is not "
          "the same as being right.", "",
          "Times are one process on one core; a study spreads shards over every core.", "",
          "## Where `paper` stands", "", *paper_vs(rows), "",
          "## Is Table 1 converged?", "", *convergence(rows), "",
          "## Every point", "",
          "| scene | method | voxel [µm] | rays | step | FWHM_R [°] | haze [%] | haze error [pts] | "
          "FWHM_R error [%] | wall [s] | peak RSS [MiB] | voxels generated |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        step = "" if math.isnan(r["step_vox"]) else f"{r['step_vox']:g}"
        gen = "" if math.isnan(r["voxels_generated"]) else f"{r['voxels_generated']:.2g}"
        err_h = f"{100 * r['haze_error']:.1f}" if "haze_error" in r else ""
        err_f = f"{100 * abs(r['fwhm_r_rel_error']):.0f}" if "fwhm_r_rel_error" in r else ""
        md.append(f"| {r['scene']}{' (reference)' if r['reference'] else ''} | {r['method']} | {r['voxel_um']:g} | "
                  f"{r['rays']} | {step} | {r['fwhm_r']:.2f} | "
                  f"{100 * r['haze']:.1f} | {err_h} | {err_f} | {r['wall_s']:.1f} | {r['peak_rss_mb']:.0f} | "
                  f"{gen} |")
    return "\n".join(md) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--quick", action="store_true", help="a few cheap points (smoke run)")
    ap.add_argument("--render", action="store_true", help="only write the outputs again from results/tradeoff.json")
    ap.add_argument("--figure", action="store_true",
                    help="only draw results/figures/tradeoff.png again from results/tradeoff.json (`make figures`)")
    args = ap.parse_args()

    results = Path(args.results)
    if args.figure:
        doc = json.loads((results / "tradeoff.json").read_text())
        figure(doc["rows"], results / "figures" / "tradeoff.png")
        print(f"wrote {results / 'figures' / 'tradeoff.png'}")
        return
    if args.render:
        doc = json.loads((results / "tradeoff.json").read_text())
        write(doc["rows"], doc["seconds"], doc["workers"], results)
        return
    t0 = time.perf_counter()
    todo = points(args.quick)
    # The slow ones first, so the processes finish together; one point per process (cold).
    order = sorted(range(len(todo)), key=lambda i: -(todo[i]["rays"] / (todo[i]["voxel_um"] ** 2)
                                                     * (30 if todo[i]["method"] == "paper" else 1)))
    with ProcessPoolExecutor(args.workers, max_tasks_per_child=1) as pool:
        done = dict(zip(order, pool.map(run_point, [todo[i] for i in order])))
    rows = [done[i] for i in range(len(todo))]
    errors(rows)
    seconds = time.perf_counter() - t0
    results.mkdir(parents=True, exist_ok=True)
    (results / "tradeoff.json").write_text(json.dumps({"rows": rows, "seconds": seconds, "workers": args.workers},
                                                      indent=0) + "\n")
    write(rows, seconds, args.workers, results)


def write(rows: list[dict], seconds: float, workers: int, results: Path) -> None:
    """The Dataset, the figure and the Markdown report of ``rows``."""
    import shutil

    from pipeline.publish import write_zarr

    out = results / "tradeoff.zarr"
    if out.exists():
        shutil.rmtree(out)
    write_zarr(dataset(rows, seconds), out)
    figure(rows, results / "figures" / "tradeoff.png")
    (results / "TRADEOFF.md").write_text(report(rows, seconds, workers))
    print((results / "TRADEOFF.md").read_text())


if __name__ == "__main__":
    main()
