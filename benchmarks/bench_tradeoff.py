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

from pipeline.analysis import LORENTZ_MLE
from pipeline.effects import TRADEOFF_TARGETS, cheapest_meeting, paired_change, setting_label

BEAM_UM = 150.0
SEED = 1
N_BOOT = 100
# Every width of the sweep, its points' and their references' alike (its reference's widths were once
# the project's default estimator, half-max, against the points' Lorentz MLE: biases of 2-3° that were none).
ESTIMATOR = LORENTZ_MLE
LATTICE_THICKNESS_UM = 250.0


LAMINATE = (0.0, -45.0, 90.0, 45.0, 0.0)  # Table 1 study 6's plies


def scenes() -> dict:
    """name: (kind, what, thickness [µm], n_wall, n_poly)."""
    return {
        "birch_0.25mm": ("wood", "birch", 250.0, 1.50, 1.49),
        "birch_1mm": ("wood", "birch", 1000.0, 1.47, 1.49),
        "balsa_1mm": ("wood", "balsa", 1000.0, 1.50, 1.49),
        "laminate_0.5mm": ("wood", "laminate", 500.0, 1.50, 1.49),
        "tubes_exact": ("lattice", "tubes", LATTICE_THICKNESS_UM, 1.50, 1.49),
        "honeycomb_exact": ("lattice", "honeycomb", LATTICE_THICKNESS_UM, 1.50, 1.49),
    }


def wood_params(what: str):
    from pipeline.params import build_params

    if what == "laminate":
        return build_params("birch", overrides={"laminate": LAMINATE})
    return build_params(what)


def lattice(what: str):
    from pipeline.optics.lattice import honeycomb, tube_lattice

    if what == "tubes":
        return tube_lattice(14.5, 7.25, 2.0, rotation_deg=8.0)
    return honeycomb(14.5, 2.0, jitter=0.15, seed=3)


VOXELS = (1.0, 0.5, 0.25, 0.125)


def points(quick: bool = False) -> list[dict]:
    """Every (scene, method, voxel, rays, step) to trace.  A wood scene's reference is its `exact`
    trace with the most rays (the model's exact optics): every other point of the scene is
    compared with it on the rays both traced (ray i enters at the same point at every voxel)."""
    P = []

    def add(scene, method, voxel, rays, step=None):
        P.append({"scene": scene, "method": method, "voxel_um": voxel if method != "exact" else float("nan"),
                  "rays": rays, "step_vox": step if method == "paper" else float("nan"), "reference": False})

    if quick:  # a smoke run for the tests: seconds
        for m in ("fast", "accurate"):
            add("tubes_exact", m, 0.5, 100)
        add("tubes_exact", "paper", 0.5, 30, 2.0)
        add("birch_0.25mm", "exact", None, 40)
        add("birch_0.25mm", "fast", 1.0, 40)
        return P
    for sc in ("tubes_exact", "honeycomb_exact"):
        for m in ("fast", "accurate"):
            for v in VOXELS:
                add(sc, m, v, 1000)
        add(sc, "paper", 1.0, 300, 1.5)
        add(sc, "paper", 0.5, 300, 2.0)
        add(sc, "paper", 0.5, 300, 1.0)
        add(sc, "paper", 0.25, 300, 2.0)
    for sc, rays in (("birch_0.25mm", 1000), ("birch_1mm", 500), ("balsa_1mm", 500), ("laminate_0.5mm", 500)):
        for m in ("fast", "accurate"):
            for v in VOXELS:
                if not (sc == "balsa_1mm" and m == "fast" and v == 0.125):  # ~25 CPU-min; see TRADEOFF.md
                    add(sc, m, v, rays)
        add(sc, "paper", 1.0, 150, 1.5)
        add(sc, "paper", 0.5, 150, 2.0)
        add(sc, "exact", None, rays)
    add("birch_0.25mm", "paper", 0.25, 150, 2.0)
    for n in (100, 300, 3000):  # rays: the statistical part
        add("birch_0.25mm", "fast", 0.5, n)
        add("birch_0.25mm", "accurate", 0.25, n)
        add("birch_0.25mm", "exact", None, n)
    for sc in ("birch_1mm", "balsa_1mm", "laminate_0.5mm"):
        add(sc, "exact", None, 2000)
    return P


def run_point(p: dict) -> dict:
    """Trace one point cold in this process; its summary, its cost and its rays' angles."""
    from pipeline.analysis import fwhm, haze, haze_ci
    from pipeline.analysis import FwhmSpec
    from pipeline.summary import fwhm_ci, summarize
    from pipeline.optics.media import wood_medium
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace
    from pipeline.optics.voxels import trace_in_voxels

    kind, what, thickness, n_wall, n_poly = scenes()[p["scene"]]
    exact = p["method"] == "exact"
    v = 1.0 if exact else p["voxel_um"]  # the exact beam is in µm: the same entry points
    changes = {} if exact else {"refine": 1}
    if p["method"] == "paper":
        changes["step_vox"] = p["step_vox"]
    settings = settings_for(p["method"], **changes)
    beam = square_beam(p["rays"], BEAM_UM / v, seed=SEED)
    if kind == "wood":
        source = wood_medium(wood_params(what), seed=SEED, thickness_um=thickness, voxel_um=v, settings=settings)
    else:
        lat = lattice(what)
        source = lat.source(thickness_um=thickness, voxel_um=v)
    t0, c0 = time.perf_counter(), time.process_time()
    if exact:
        res = trace(source, beam, Optics(n_wall, n_poly, None, SEED), settings)
    else:
        res = trace_in_voxels(source, beam, n_wall=n_wall, n_poly=n_poly, settings=settings, seed=SEED)
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    # Its committed numbers are Lorentz maximum-likelihood widths (results/TRADEOFF.md says so).
    s = summarize(res, spec=FwhmSpec(ESTIMATOR), n_boot=N_BOOT, seed=SEED)
    out = {**p, "fwhm_r": s["fwhm_r_deg"], "fwhm_r_ci": s["fwhm_r_ci_deg"], "fwhm_l": s["fwhm_l_deg"],
           "fwhm_l_ci": s["fwhm_l_ci_deg"], "haze": s["haze"], "haze_ci": s["haze_ci"],
           "interfaces_per_ray": s["interfaces_per_ray"], "transmitted": s["n_transmitted"],
           "voxels_read": float(s.get("voxels_read", 0.0)),  # exact reads no voxels (no voxel diagnostics)
           "wall_s": wall_s, "cpu_s": cpu_s,
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
           "voxels_generated": float("nan"), "generated_fraction_of_box": float("nan")}
    if kind == "wood":
        out["angles"] = (res.theta_r, res.theta_l, res.transmitted)  # for the paired bias; not saved
        if not exact:
            cv = int(np.prod(source.chunks))
            out["voxels_generated"] = float(len(source.distinct) * cv)
            idx = np.array(sorted(source.distinct))
            box = np.prod(idx.max(axis=0) - idx.min(axis=0) + 1)
            out["generated_fraction_of_box"] = float(len(idx) / box)
        else:
            out["voxels_generated"] = 0.0
    else:
        ex = lat.trace_independently(beam.origins * v, beam.direction, n_wall=n_wall, n_poly=n_poly, thickness_um=thickness)
        t = ex.transmitted
        h = haze(ex.direction[t])
        out["exact"] = {"fwhm_r": fwhm(ex.theta_r[t], "lorentz-mle"), "fwhm_l": fwhm(ex.theta_l[t], "lorentz-mle"), "haze": h,
                        "fwhm_r_ci": list(fwhm_ci(ex.theta_r[t], n_boot=N_BOOT, seed=SEED, estimator="lorentz-mle")),
                        "haze_ci": list(haze_ci(h, int(t.sum())))}
    return out


def _half(ci) -> float:
    return (ci[1] - ci[0]) / 2.0


def _angles_reduced(angles, n):
    from pipeline.effects import reduce_rays

    return reduce_rays(*(x[:n] for x in angles), np.arange(n), ESTIMATOR)


def errors(rows: list[dict]) -> None:
    """Add the reference, bias (systematic), half-width (statistical) and total error to each row.

    Lattices: against exact optics of the same rays (the independent lattice tracer).  Wood:
    against the scene's `exact` trace with the most rays, on the rays both traced, with the
    bias's 95 % interval from a paired bootstrap (``<q>_bias_pct`` / ``_ci``: FWHM in % of the
    reference, haze in points).  Rows without ``angles`` (read back from JSON) keep what they have."""
    refs = {}
    for r in rows:
        if r["method"] == "exact" and "angles" in r and r["rays"] > refs.get(r["scene"], {"rays": 0})["rays"]:
            refs[r["scene"]] = r
    for r in refs.values():
        r["reference"] = True
    for r in rows:
        if "exact" in r:
            ref = r["exact"]
            r["ref_kind"] = "exact optics, same rays (lattice tracer)"
        elif r["scene"] in refs and "angles" in r:
            e = refs[r["scene"]]
            n = r["rays"]
            v = _angles_reduced(e["angles"], n)
            ref = {"fwhm_r": float(v[0]), "fwhm_l": float(v[1]), "haze": float(v[2])}
            r["ref_kind"] = "`exact`, the same rays"
            change, ci = paired_change(tuple(x[:n] for x in e["angles"]), r["angles"], n_boot=N_BOOT, seed=SEED,
                                       estimator=ESTIMATOR)
            for j, q in enumerate(("fwhm_r", "fwhm_l", "haze")):
                r[f"{q}_bias_pct"], r[f"{q}_bias_ci"] = float(change[j]), [float(ci[j, 0]), float(ci[j, 1])]
        else:
            continue
        r["ref_fwhm_r"], r["ref_fwhm_l"], r["ref_haze"] = ref["fwhm_r"], ref["fwhm_l"], ref["haze"]
        for q in ("fwhm_r", "haze"):
            bias = r[q] - ref[q]
            half = _half(r[f"{q}_ci"])
            r[f"{q}_bias"], r[f"{q}_half"] = bias, half
            r[f"{q}_error"] = math.hypot(bias, half)
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
    "FWHM_R_bias_percent": ("fwhm_r_bias_pct", "wood: FWHM_R against `exact`, same rays (paired)", "percent"),
    "FWHM_L_bias_percent": ("fwhm_l_bias_pct", "wood: FWHM_L against `exact`, same rays (paired)", "percent"),
    "haze_bias_points": ("haze_bias_pct", "wood: haze against `exact`, same rays (paired)", "percent"),
    **{f"{q}_bias_{b}": (f"{k}_bias_ci_{i}", f"wood: {b} end of the paired 95 % interval of {q}'s bias",
                         "percent") for q, k in (("FWHM_R", "fwhm_r"), ("FWHM_L", "fwhm_l"), ("haze", "haze"))
       for i, b in enumerate(("lower", "upper"))},
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

    from pipeline import versions
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
    for r in rows:
        for q in ("fwhm_r", "fwhm_l", "haze"):
            for i, v in enumerate(r.get(f"{q}_bias_ci", (np.nan, np.nan))):
                r[f"{q}_bias_ci_{i}"] = v
    data = {name: ("point", np.array([r.get(key, np.nan) for r in rows], dtype=float),
                   {"long_name": ln, "units": u}) for name, (key, ln, u) in VARS.items()}
    ds = xr.Dataset(data, coords=coords, attrs={
        "title": "twray speed/accuracy trade", "description": __doc__.strip(),
        "seconds": seconds, "machine_cpus": os.cpu_count() or 1, "beam_um": BEAM_UM, "seed": SEED,
        "scenes": json.dumps(scenes()),
        "tracer_versions": json.dumps({m: versions.tracer(m) for m in sorted({r["method"] for r in rows})})})
    ds.attrs.update(provenance_attrs({"points": [{k: r[k] for k in ("scene", "method", "voxel_um", "rays",
                                                                      "step_vox")} for r in rows]}))
    return ds


def _label(r: dict) -> str:
    return setting_label(r["method"], r["voxel_um"], r["rays"], r["step_vox"])


TARGETS = TRADEOFF_TARGETS  # (name, haze error [points], FWHM_R relative)


def recommend(rows: list[dict]) -> list[str]:
    lines = ["| scene | target | cheapest setting that meets it | wall time (cold, 1 core) | its errors |",
             "|---|---|---|---|---|"]
    for sc in scenes():
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r]
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
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r and r["method"] != "exact"]
        if not sel:
            continue
        h = min(sel, key=lambda r: r["haze_error"])
        f = min(sel, key=lambda r: abs(r["fwhm_r_rel_error"]))
        lines.append(f"| {sc} | {sel[0]['ref_kind']} | ±{100 * h['haze_error']:.1f} points | {_label(h)} | "
                     f"±{100 * abs(f['fwhm_r_rel_error']):.0f} % | {_label(f)} |")
    return lines


def _pick(rows, sc, method, voxel=None, step=None):
    """The point of ``sc`` with this method (voxel, paper step) and the most rays, or None."""
    sel = [r for r in rows if r["scene"] == sc and r["method"] == method and "haze_error" in r
           and (voxel is None or r["voxel_um"] == voxel) and (step is None or r["step_vox"] == step)]
    return max(sel, key=lambda r: r["rays"]) if sel else None


def paper_vs(rows: list[dict]) -> list[str]:
    lines = ["| scene | `paper` (0.5 µm, step 2) | its haze / FWHM_R error | `accurate` at 0.25 µm | "
             "its haze / FWHM_R error | `exact` | its haze / FWHM_R error | time per ray, paper : accurate : exact |",
             "|---|---|---|---|---|---|---|---|"]
    for sc in scenes():
        trio = [_pick(rows, sc, "paper", 0.5, 2.0), _pick(rows, sc, "accurate", 0.25), _pick(rows, sc, "exact")]
        if trio[0] is None or trio[1] is None:
            continue
        cells = []
        for r in trio:
            if r is None:
                cells += ["", ""]
                continue
            cells += [f"{r['wall_s']:.1f} s ({r['rays']} rays)",
                      f"±{100 * r['haze_error']:.1f} pts / ±{100 * abs(r['fwhm_r_rel_error']):.0f} %"]
        per = [r["wall_s"] / r["rays"] for r in trio if r is not None]
        ratio = " : ".join(f"{x / per[-1]:.3g}" for x in per)
        lines.append(f"| {sc} | " + " | ".join(cells) + f" | {ratio} |")
    return lines


def _ci(v, ci, unit) -> str:
    return f"{v:+.0f}{unit} [{ci[0]:+.0f}, {ci[1]:+.0f}]" if unit == " %" else \
        f"{v:+.1f} [{ci[0]:+.1f}, {ci[1]:+.1f}]"


def wood_errors_md(rows: list[dict]) -> list[str]:
    """Per wood scene, method and voxel: the bias of FWHM_R, FWHM_L (%) and haze (points) against
    `exact` on the same rays, with paired 95 % intervals, and the cold wall time; `exact`'s own
    cost on the same rays closes each scene."""
    lines = ["| scene | setting | FWHM_R vs exact | FWHM_L vs exact | haze vs exact [points] | wall [s], cold, 1 core |",
             "|---|---|---|---|---|---|"]
    for sc, (kind, *_) in scenes().items():
        if kind != "wood":
            continue
        sel = [r for r in rows if r["scene"] == sc and "fwhm_r_bias_pct" in r and r["method"] != "exact"]
        sel.sort(key=lambda r: ({"paper": 0, "fast": 1, "accurate": 2}[r["method"]], -r["voxel_um"], r["rays"]))
        for r in sel:
            lines.append(f"| {sc} | {_label(r)} | {_ci(r['fwhm_r_bias_pct'], r['fwhm_r_bias_ci'], ' %')} | "
                         f"{_ci(r['fwhm_l_bias_pct'], r['fwhm_l_bias_ci'], ' %')} | "
                         f"{_ci(r['haze_bias_pct'], r['haze_bias_ci'], '')} | {r['wall_s']:.1f} |")
        for r in (x for x in rows if x["scene"] == sc and x["method"] == "exact" and x["rays"] in {y["rays"] for y in sel}):
            lines.append(f"| {sc} | {_label(r)} | 0 (reference) | 0 | 0 | {r['wall_s']:.1f} |")
    return lines


def convergence(rows: list[dict]) -> list[str]:
    """Per wood scene: `accurate`'s FWHM_R, FWHM_L and haze against `exact` as its voxel shrinks (the
    same rays), so a reader sees whether a finer voxel approaches the exact value."""
    out = []
    for sc, (kind, *_) in scenes().items():
        ladder = sorted((r for r in rows if r["scene"] == sc and r["method"] == "accurate" and "fwhm_r_bias_pct" in r
                         and r["rays"] == max(x["rays"] for x in rows if x["scene"] == sc and x["method"] == "accurate"
                                              and not math.isnan(x["voxel_um"]) and x["voxel_um"] == 0.125)),
                        key=lambda r: -r["voxel_um"]) if kind == "wood" else []
        if not ladder:
            continue
        steps = " → ".join(f"{r['voxel_um']:g} µm: FWHM_R {r['fwhm_r_bias_pct']:+.0f} %, FWHM_L "
                           f"{r['fwhm_l_bias_pct']:+.0f} %, haze {r['haze_bias_pct']:+.1f} pts" for r in ladder)
        out.append(f"- **{sc}**, `accurate` against `exact` on the same {ladder[0]['rays']} rays: {steps}.")
    return out


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [sc for sc in scenes() if any(r["scene"] == sc and "haze_error" in r for r in rows)]
    fig, axes = plt.subplots(2, len(names), figsize=(4.0 * len(names), 7.0), squeeze=False)
    markers = {"paper": "s", "fast": "o", "accurate": "^", "exact": "D"}
    for j, sc in enumerate(names):
        sel = [r for r in rows if r["scene"] == sc and "haze_error" in r]
        for i, (key, scale, label) in enumerate((("haze_error", 100.0, "haze error [points]"),
                                                 ("fwhm_r_rel_error", 100.0, "FWHM_R error [%]"))):
            ax = axes[i, j]
            for m, mk in markers.items():
                pts = [r for r in sel if r["method"] == m]
                ax.scatter([], [], marker=mk, facecolors="w", edgecolors="k", label=m)
                if m == "exact":  # no voxel: red
                    ax.scatter([r["wall_s"] for r in pts], [abs(r[key]) * scale for r in pts], marker=mk,
                               c="tab:red", edgecolors="k", linewidths=0.5)
                    continue
                ax.scatter([r["wall_s"] for r in pts], [abs(r[key]) * scale for r in pts], marker=mk,
                           c=[math.log2(r["voxel_um"]) for r in pts], cmap="viridis", vmin=-3, vmax=0,
                           edgecolors="k", linewidths=0.5)
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
                ax.legend(title="colour: voxel, dark 0.125 µm, yellow 1 µm;\nred: exact", fontsize=7, title_fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def report(rows: list[dict], seconds: float, workers: int) -> str:
    md = ["# Speed against accuracy", "",
          f"Generated by `make tradeoff` ({seconds / 60:.1f} min on {workers} processes, each point cold in its "
          "own process); every number is in `results/tradeoff.zarr` (`xr.open_zarr`), the figure is "
          "`results/figures/tradeoff.png`. Error = sqrt(bias² + CI half-width²), the bias against exact optics "
          "of the same rays: the independent lattice tracer for the lattices, `exact` (the model's own "
          "surfaces) for the wood, whose `exact` points therefore carry their interval alone. Voxel = the "
          "voxel the wood is traced on (the `accurate` preset of a study traces on half the study's voxel). "
          "Wood scenes: a 150 µm beam, birch 0.25 mm at ΔRI +0.01, birch 1 mm at −0.02, balsa 1 mm at +0.01, "
          "Table 1's [0/-45/90/45/0] birch laminate 0.5 mm at +0.01; one wood (seed 1) each.", "",
          "![error against time](figures/tradeoff.png)", "",
          "## What to use", "", *recommend(rows), "",
          "## Every voxel method on the wood, against `exact`", "",
          "Bias on the same rays, with the 95 % interval of a paired bootstrap over rays (FWHM in % of "
          "`exact`'s, haze in points). `fast` at 0.125 µm on balsa is not swept (about 25 CPU-min for a "
          "point whose 0.25 µm neighbour is already further off than `accurate`'s).", "",
          *wood_errors_md(rows), "",
          "## The best any voxel setting reaches", "", *best(rows), "",
          "Against exact optics the error of a voxel method does not fall steadily as the voxel shrinks: "
          "binary voxels alias walls into staircases whose smoothed normals err by degrees "
          "(results/accuracy.md). Values that settle as the voxel shrinks are not thereby right.", "",
          "Times are one process on one core; a study spreads shards over every core.", "",
          "## Where `paper` stands", "", *paper_vs(rows), "",
          "## Does a finer voxel approach `exact`?", "", *convergence(rows), "",
          "## Every point", "",
          "| scene | method | voxel [µm] | rays | step | FWHM_R [°] | haze [%] | haze error [pts] | "
          "FWHM_R error [%] | wall [s] | peak RSS [MiB] | voxels generated |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        step = "" if math.isnan(r["step_vox"]) else f"{r['step_vox']:g}"
        gen = "" if math.isnan(r["voxels_generated"]) else f"{r['voxels_generated']:.2g}"
        err_h = f"{100 * r['haze_error']:.1f}" if "haze_error" in r else ""
        err_f = f"{100 * abs(r['fwhm_r_rel_error']):.0f}" if "fwhm_r_rel_error" in r else ""
        vox = "" if math.isnan(r["voxel_um"]) else f"{r['voxel_um']:g}"
        md.append(f"| {r['scene']}{' (reference)' if r['reference'] else ''} | {r['method']} | {vox} | "
                  f"{r['rays']} | {step} | {r['fwhm_r']:.2f} | "
                  f"{100 * r['haze']:.1f} | {err_h} | {err_f} | {r['wall_s']:.1f} | {r['peak_rss_mb']:.0f} | "
                  f"{gen} |")
    return "\n".join(md) + "\n"


def _guess_cost(p: dict) -> float:
    """A rough relative cost, to start the slowest points first."""
    thick = scenes()[p["scene"]][2] / 250.0
    if p["method"] == "exact":
        return p["rays"] * thick * thick * 0.02
    gen = thick * (3.0 if "balsa" in p["scene"] else 1.0) / p["voxel_um"] ** 3
    return gen * 30.0 + p["rays"] / p["voxel_um"] ** 2 * (30 if p["method"] == "paper" else 1)


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
    order = sorted(range(len(todo)), key=lambda i: -_guess_cost(todo[i]))
    with ProcessPoolExecutor(args.workers, max_tasks_per_child=1) as pool:
        done = dict(zip(order, pool.map(run_point, [todo[i] for i in order])))
    rows = [done[i] for i in range(len(todo))]
    errors(rows)
    for r in rows:
        r.pop("angles", None)
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
