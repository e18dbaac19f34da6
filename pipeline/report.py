"""``results/REPORT.md``: the reproduction report, every number read from a dataset (``twray report``).

Sources, all committed: the Table 1 study Datasets (``results/paper/study-*.zarr``),
the camera Dataset (``results/paper/camera/figure5.zarr``), the trade-off
Dataset (``results/tradeoff.zarr``) and the benchmark record
(``results/bench.json``).  The numbers come from :mod:`pipeline.effects`; this
module writes them as Markdown.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .analysis import HAZE_ANGLE_DEG
from .effects import (N_BOOT, Effect, all_effects_of, camera_rows, experiment_rows, fibre_tip_rows, fine_voxel_rows,
                      method_rows, reference_index, table1_rows)
from .design import MAPS, glance_tables, window_table
from .effects import holm_resolved, p_value
from .figures import table1_structures
from .publish import open_dataset
from .report_tables import (balsa_reading_sentence, camera_markdown, camera_methods_markdown, effects_markdown,
                            experiment_markdown, fibre_tip_markdown, fibre_tip_sentence, method_markdown,
                            method_summary, minutes_text, table1_markdown, tradeoff_markdown, variation_markdown,
                            woods_text)
from .report_source import source_sections
from .report_scans import section_of as scans_section_of
from .report_wave import wave_section
from .result_sets import TABLE1, load_table1, study_dimension, traced_voxel_um_of, value_label

# What geometrical optics leads one to expect of each study, before running it; the
# report states whether twray's numbers agree.  (The source's own numbers are compared in
# "Against the source", pipeline/report_source.py.)
EXPECTED = {
    "study-1": ("widths and haze grow with thickness, the widths as √N of the interfaces N",
                "each interface adds a small deflection of either sign: a random walk of N steps spreads "
                "as √N (a Lorentz-tailed step would spread as N)"),
    "study-2": ("widths ∝ |ΔRI|, about equal for ±ΔRI to first order", "each refraction deflects by ≈ "
                "(ΔRI/n)·tan θi, odd in ΔRI, so the distribution of its size depends on |ΔRI| alone; but near "
                "grazing incidence total reflection traps rays in the thin walls for +ΔRI and in the wide lumens "
                "for −ΔRI, which need not scatter alike (a ray explanation; \"Where geometrical optics holds\" "
                "tests it with waves)"),
    "study-3": ("larger fibres scatter less: widths × about 1/√2", "half as many walls per mm along T: "
                "about half the interfaces per ray"),
    "study-4": ("thicker walls change little", "the same interfaces per ray (the fibre pitch is fixed); "
                "thicker walls only change the path between the two faces of a wall"),
    "study-5-1": ("without ray cells FWHM_L drops", "ray cells are the only walls that run across L, so "
                  "they are what deflects rays along L"),
    "study-5-2": ("without vessels scattering rises a little", "vessels are wide lumens with few "
                  "walls: replacing them by fibres adds interfaces"),
    "study-6": ("the laminate spreads light along L as well as R", "plies at ±45° and 90° turn "
                "fibre walls across L"),
}

# ------------------------------------------------------------------ tables
def _agreement(name: str, effs: list[Effect], tables: dict) -> str:
    """Whether the study's resolved effects go the way EXPECTED says (a sentence, from the numbers)."""
    def sign(value, quantity):
        e = next((e for e in effs if e.value == value and e.quantity == quantity), None)
        if e is None:
            return None
        return 0 if not e.resolved else (1 if e.change > 0 else -1)

    ds = tables[name]
    dim = study_dimension(ds)
    values = [value_label(v) for v in ds[dim].values]
    ref = values[reference_index(ds)]
    others = [v for v in values if v != ref]
    if name == "study-1":
        w = ds["FWHM_R"].values
        up = int(np.sum(np.diff(w) > 0))
        return f"FWHM_R rises at {up} of {len(w) - 1} steps in thickness; " + _ratio_sentence(ds)
    if name == "study-2":
        x = ds[dim].values.astype(float)
        w = ds["FWHM_R"].values
        pairs = [(v, -v) for v in x if v > 0 and -v in x]
        parts = [f"±{v:g}: {float(ds['FWHM_R'].sel({dim: m})):.2f}° / {float(ds['FWHM_R'].sel({dim: v})):.2f}°"
                 for v, m in pairs]
        small = min(abs(x))
        ratios = [f"{abs(v) / small:g}× |ΔRI| → {w[k] / w[np.argmin(abs(x - small))]:.2f}×"
                  for k, v in enumerate(x) if v > small]
        return ("FWHM_R at −ΔRI / +ΔRI: " + "; ".join(parts) + ". Against ΔRI " + f"{small:g}: "
                + ", ".join(ratios) + " in FWHM_R.")
    v = others[0]
    signs = {q: sign(v, q) for q in ("FWHM_R", "FWHM_L", "haze")}
    words = {1: "rises", -1: "falls", 0: "does not change resolvably", None: "—"}
    n = ds["interfaces_per_ray"].values
    k_ref, k_v = values.index(ref), values.index(v)
    return ("; ".join(f"{q} {words[s]}" for q, s in signs.items()) + f" ({ref} → {v}); interfaces per ray "
            f"{n[k_ref]:.0f} → {n[k_v]:.0f} ({n[k_v] / n[k_ref]:.2f}×, √ of it {math.sqrt(n[k_v] / n[k_ref]):.2f}), "
            f"FWHM_R {ds['FWHM_R'].values[k_v] / ds['FWHM_R'].values[k_ref]:.2f}×.")

def _ratio_sentence(ds) -> str:
    th = ds["thickness"].values.astype(float)
    w = ds["FWHM_R"].values
    n = ds["interfaces_per_ray"].values
    k0, k1 = int(np.argmin(th)), int(np.argmax(th))
    slope = float(np.polyfit(np.log(n), np.log(w), 1)[0])
    return (f"from {th[k0]:g} to {th[k1]:g} mm ({th[k1] / th[k0]:.0f}× thicker) the interfaces per ray grow "
            f"{n[k1] / n[k0]:.1f}× and FWHM_R {w[k1] / w[k0]:.1f}×; over all thicknesses FWHM_R ∝ N^{slope:.2f} "
            "(least squares in log-log).")

# ------------------------------------------------------------------ the report
@dataclass
class ReportData:
    """Every dataset the report reads, opened once, and what is computed from them for several
    sections (:func:`load_report_data`)."""

    results: Path
    base: Path  # results/<scale_dir>
    scale_dir: str
    n_boot: int
    tables: dict  # Table 1: {study: Dataset}
    camera: object
    tradeoff: object
    bench: dict
    all_effects: dict
    rows: list
    experiment: list
    tips: list
    paper_tables: dict
    methods: list
    voxel_tables: dict | None
    voxel_rows: list
    maps: dict  # the design maps, by name of design.MAPS (all of them, or none)
    fig: str = "figures"

    @property
    def s1(self):
        return self.tables["study-1"]

    @property
    def settings(self) -> dict:
        return json.loads(self.s1.attrs["trace_settings"])

    @property
    def woods(self) -> dict:
        return {name: ds.sizes.get("realisation", 1) for name, ds in self.tables.items()}


def load_report_data(results: Path, *, scale_dir: str = "paper", n_boot: int = N_BOOT) -> ReportData:
    """Open the committed datasets under ``results`` and compute the rows the sections share."""
    results = Path(results)
    base = results / scale_dir
    tables = load_table1(base)
    paper_tables = load_table1(base / "paper-method")
    voxel_dir = base / "accurate"  # Table 1 as traced with `accurate`, beside `exact`
    voxel_tables = load_table1(voxel_dir) if voxel_dir.exists() else None
    maps = {n: open_dataset(base / "design" / f"{n}.zarr") for n in MAPS if (base / "design" / f"{n}.zarr").exists()}
    return ReportData(
        results=results, base=base, scale_dir=scale_dir, n_boot=n_boot, tables=tables,
        camera=open_dataset(base / "camera" / "figure5.zarr"), tradeoff=open_dataset(results / "tradeoff.zarr"),
        bench=json.loads((results / "bench.json").read_text()), all_effects=all_effects_of(tables, n_boot=n_boot),
        rows=table1_rows(tables), experiment=experiment_rows(base), tips=fibre_tip_rows(base, n_boot=n_boot),
        paper_tables=paper_tables, methods=method_rows(tables, paper_tables, n_boot=n_boot),
        voxel_tables=voxel_tables,
        voxel_rows=method_rows(tables, voxel_tables, n_boot=n_boot) if voxel_tables else [],
        maps=maps if len(maps) == len(MAPS) else {})


def build_report(results: Path, *, scale_dir: str = "paper", n_boot: int = N_BOOT) -> str:
    """The Markdown of ``results/REPORT.md`` from the datasets under ``results``: its sections in order."""
    d = load_report_data(results, scale_dir=scale_dir, n_boot=n_boot)
    sections = (opening, glance, provenance_line, microstructures, trajectories, table1_section, variation,
                trends, voxel_error, lambda d: scans_section_of(d.results, "##"),
                lambda d: source_sections(d.results, d.base, d.tables, d.methods),
                paper_method, measured_samples, fibre_tips, camera_section, design_section,
                lambda d: wave_section(d.results, d.scale_dir, d.fig), speed_against_accuracy, reproducing,
                differences)
    return "\n".join(line for section in sections for line in section(d))


def opening(d: ReportData) -> list[str]:
    return ["# twray reproduction report", "",
            "Generated by `make report` from the committed result datasets; no number below is typed by hand. "
            f"Datasets: `results/{d.scale_dir}/study-*.zarr` (Table 1), `results/{d.scale_dir}/camera/figure5.zarr` "
            "(camera), `results/tradeoff.zarr` (speed against accuracy), `results/bench.json` (costs). "
            "Figures: `make figures` → `results/figures/`.", ""]


def _maps_traced(d: ReportData) -> str:
    """How the design maps were traced, as the report says it."""
    d0 = next(iter(d.maps.values()))
    return (f"`make design`, `exact` version {d0.attrs['tracer_version']}, {d0.attrs['realisations']} woods × "
            f"{d0.attrs['rays']} rays a cell")


def glance(d: ReportData) -> list[str]:
    """The designer's first screen: the design maps' traced cells (none without the maps)."""
    if not d.maps:
        return []
    d0 = next(iter(d.maps.values()))
    return ["## At a glance: haze and FWHM_R of TW", "",
            f"What a sample scatters, from the design maps ({_maps_traced(d)}, beam at normal incidence; ΔRI = wall − polymer index, polymer "
            f"{float(json.loads(d0.attrs['scenes'])[0]['ri_polymer']):g}). Each cell: in air (what a "
            "hazemeter sees) / inside the sample (the paper's angles). Haze: share of the light deviated by more "
            "than 2.5°. Between cells, and with intervals, `twray design --thickness-mm T --delta-ri D` reads "
            "the maps; [Design maps](#design-maps-how-well-must-the-polymer-match) gives the ΔRI window for a "
            "haze limit.", ""] + glance_tables(d.maps)


def provenance_line(d: ReportData) -> list[str]:
    s1, settings = d.s1, d.settings
    first_seed = int(s1["seed_of_realisation"].values[0]) if "seed_of_realisation" in s1 else int(s1.attrs["seed"])
    target = json.loads(s1.attrs["target_ci"]) if "target_ci" in s1.attrs else None
    return [f"Table 1 was traced with twray {s1.attrs['twray_version']} (tracer version {s1.attrs['tracer_version']}, "
            f"generator version {s1.attrs['generator_version']}) at scale `{s1.attrs['scale']}`: "
            f"{s1.attrs['rays']} rays per value on each of {woods_text(d.woods, target, first_seed)}"
            f"{target_status(d.tables)}, method `{settings['method']}` "
            + (f"(wood traced on {traced_voxel_um_of(json.loads(s1.attrs['scenes'])[0]):g} µm voxels), "
               if settings["method"] != "exact" else "(the model's own surfaces, no voxels), ")
            + f"angles {s1.attrs['exit_angles']} (inside the sample).", ""]


def microstructures(d: ReportData) -> list[str]:
    out = ["## The microstructures", "",
           "Every structure of Table 1, generated from its parameters (docs/methods.md#the-microstructure-model): "
           "sections through a 300 × 500 × 600 µm block (R × T × L) and a 3D view of it (the paper's Figure 3).", ""]
    for slug, caption, _, _ in table1_structures(list(d.tables.values())):
        out += [f"**{caption}**", "", f"![{caption}]({d.fig}/microstructure-{slug}.png)", ""]
    return out


def trajectories(d: ReportData) -> list[str]:
    return ["## Rays through 1.5 mm of birch", "", f"![ray trajectories]({d.fig}/trajectories.png)", "",
            "Each ray goes straight inside one phase and turns at every wall it meets (Snell's law; total "
            "internal reflection where it applies). The lateral axes are stretched: the rays stay within "
            "a few degrees of +T.", ""]


def table1_section(d: ReportData) -> list[str]:
    out = ["## Table 1", "",
           f"Each number is its study's wood realisations pooled (the woods column): FWHM the width of the angle "
           f"distribution at half its maximum (`{d.s1.attrs.get('fwhm_estimator', 'half-max')}`, the source's "
           "definition; docs/methods.md#fwhm-and-haze), and haze the share of the transmitted rays deviating more "
           f"than {HAZE_ANGLE_DEG:g}°. Intervals are 95 %, from resampling the woods (each drawn wood with all its "
           "rays; Student t on woods − 1 degrees of freedom), so they hold the variation from one wood to the next "
           "and the sampling of rays, each once. They are intervals against sampling noise only: the estimator, the "
           "method and the wood model are systematic choices, measured in their own sections below. The "
           "last column is the range of the woods' own FWHM_R."
           + (" " + base_scene_sentence(d.rows) if len(set(d.woods.values())) > 1 else ""), ""]
    out += table1_markdown(d.rows) + [""]
    for name in TABLE1:
        out += [f"![{d.tables[name].attrs['title']}]({d.fig}/{name}.png)", ""]
    return out + ["Exit-angle distributions, their half-maximum widths and Lorentz fits (the paper's Figure S1):", "",
                  f"![angle histograms]({d.fig}/histograms.png)", ""]


def variation(d: ReportData) -> list[str]:
    return ["## Wood-to-wood variation", "",
            "One wood realisation is one sample. How much each value moves between its study's woods "
            "(coefficient of variation of the woods' own values; haze as a standard deviation in points), how much "
            "of that is the woods and how much the 1000 rays of each (variance components: the woods' variance "
            "minus the ray variance of one wood's value, docs/methods.md#realisations-and-intervals), and how much "
            "wider its FWHM_R interval is once the woods are in it:", ""] + variation_markdown(d.rows) + [""]


def trends(d: ReportData) -> list[str]:
    out = ["## The trends", "",
           "Each value against the study's reference value (the Table 1 default where the study has it). "
           "FWHM changes are relative (%), haze changes in points. Intervals: paired, from resampling woods "
           f"({d.n_boot} resamples, Student t): the same woods are drawn for every value (each value is "
           "traced on the same woods with the same beam), so the interval is that of the difference, wood-to-wood "
           "variation included. \"Not resolved\": the interval contains 0.", ""]
    out += effects_markdown(d.all_effects) + ["", multiple_comparisons_sentence(d.all_effects), "",
                                               "| study | what optics leads one to expect | why | what twray finds |",
                                               "|---|---|---|---|"]
    for name in TABLE1:
        exp, why = EXPECTED[name]
        cells = (name, exp, why, _agreement(name, d.all_effects[name], d.tables))
        out.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return out + ["", "The comparison above is with what geometrical optics predicts; the source's own published "
                  "numbers (docs/methods.md#the-source-s-published-numbers) are compared in \"Against the source\" "
                  "below.", ""]


def voxel_error(d: ReportData) -> list[str]:
    """Table 1 traced with `accurate` beside `exact` (none when not traced)."""
    if not d.voxel_rows:
        return []
    r0, v1 = d.voxel_rows[0], d.voxel_tables["study-1"]
    return [f"## `{r0['other']}` beside `{r0['ref']}`: the voxel error on the wood itself", "",
            f"Table 1 as traced with `{r0['other']}` (wood on "
            f"{traced_voxel_um_of(json.loads(v1.attrs['scenes'])[0]):g} µm voxels, `results/{d.scale_dir}/accurate/`), "
            f"beside the same values traced with `{r0['ref']}` on the same "
            f"{r0['realisations_common']} woods (the first of Table 1's) with the same "
            f"{r0['rays_common']} rays each, both pooled over those rays: the paired difference is the "
            "voxel method's error on each Table 1 scene, 95 % intervals from resampling the woods (paired, Student t).",
            ""] + method_markdown(d.voxel_rows) + ["", method_summary(d.voxel_rows), ""]


def paper_method(d: ReportData) -> list[str]:
    p1, method = d.paper_tables["study-1"], d.settings["method"]
    return [f"## The paper's method beside `{method}`", "",
            f"Table 1 traced again with the paper's method (`--method paper`: 2-voxel steps, the crossing at the "
            f"midpoint, a linear SVM normal on 6×6×6 voxels, wood on 0.5 µm voxels), {p1.attrs['rays']} rays on each "
            f"of the first {p1.sizes.get('realisation', 1)} of Table 1's woods (`results/{d.scale_dir}/paper-method/`). "
            "Both methods are pooled over the rays both traced, and the differences are paired: the same woods and the "
            "same rays (ray i of a beam enters at the same point "
            f"whatever the total), {d.methods[0]['rays_common']} per wood, 95 % intervals from resampling the woods "
            f"(paired, Student t). A difference here comes from the method alone; one between `{method}` and the "
            "published numbers that is not here comes from the wood model or the statistics.", ""] \
        + method_markdown(d.methods) + ["", method_summary(d.methods), ""]


def measured_samples(d: ReportData) -> list[str]:
    out = ["## Against the measured samples", "",
           "The paper measured the haze of two samples: birch-like TW 0.7 mm thick and balsa-like TW 1 mm thick. "
           "A hazemeter measures in air, so each is traced twice: angles inside the sample (as Table 1) and after "
           "refraction into air at the exit face (`trace.exit: air`; a deflection grows about 1.5× on leaving). "
           "Balsa is run with the paper's 1.2 µm wall and the preset's 1.4 µm; its quoted cell size 35.2 is read "
           "as a cell diameter in µm (pipeline/presets/balsa.yaml). Intervals as in Table 1 "
           f"({d.experiment[0]['realisations']} woods × {d.experiment[0]['rays']} rays).", ""]
    out += experiment_markdown(d.experiment) + [""]
    radius = d.base / "experiment" / "balsa-1mm-radius.zarr"
    if radius.exists():
        out += [balsa_reading_sentence(open_dataset(radius), open_dataset(d.base / "experiment" / "balsa-1mm.zarr")),
                ""]
    return out + ["The table gives what a hazemeter would read on these model woods; the source's measured hazes "
                  "are set beside them in \"Against the source\" above.", ""]


def fibre_tips(d: ReportData) -> list[str]:
    tips, woods = d.tips, d.woods
    out = ["## Fibre tips and scattering along L", "",
           "In the generator (docs/methods.md#fibre-ends) a fibre is straight along L and ends in a flat plate, so "
           "its walls are almost parallel to L (docs/methods.md, \"Fibre tips\", measures their normals) and FWHM_L "
           "comes mostly from the ray cells. Birch fibres end in long tapering tips that overlap their neighbours'. "
           "With `fibre_tip_um` = λ, consecutive fibres of a file overlap over 2λ and meet along an oblique wall "
           "inclined to L by atan(w/λ), w the lumen's half-width (docs/methods.md, \"Fibre tips\"). The Table 1 "
           "default wood (birch, 1 mm, ΔRI 0.01) with and without ray cells, over λ (`make fibre-tips`; "
           f"{tips[0]['realisations']} woods × {tips[0]['rays']} rays, the same woods as Table 1; changes are paired "
           "against flat ends, 95 % intervals from resampling the woods):", ""]
    out += fibre_tip_markdown(tips) + [""]
    tip_text = fibre_tip_sentence(tips)
    flat = ("so its woods and numbers are the ones above at λ = 0" if tips[0]["realisations"] == woods["study-1"]
            else f"so the rows at λ = 0 are its default wood on the first {tips[0]['realisations']} of its "
                 f"{woods['study-1']} woods")
    return out + [tip_text[0].upper() + tip_text[1:] + " Table 1 keeps flat fibre ends "
                  f"(λ = 0, docs/methods.md#fibre-tips), {flat}.", ""]


def camera_section(d: ReportData) -> list[str]:
    camera = d.camera
    out = ["## The virtual camera (Figure 5)", "",
           f"A thin-lens camera looks through a {float(camera['thickness_um'].max()) / 1000:g} mm birch TW sheet "
           f"at a character card just behind it ({camera.attrs['samples_per_pixel']} aperture samples per pixel). "
           "Contrast is Michelson's, (light − dark)/(light + dark), between the pixels the ideal thin-lens "
           "image shows light and dark; the control is the same scene through an index-matched sheet.", ""]
    out += camera_markdown(camera_rows(camera)) + ["", f"![camera images]({d.fig}/camera.png)", ""]
    method = camera.attrs.get("tracing_method", "fast")
    fast_path = d.base / "camera" / "fast" / "figure5.zarr"
    if method == "exact" and fast_path.exists():
        fast = open_dataset(fast_path)
        return out + ["The images above are traced with `exact`, on the wood's own surfaces. The same aperture "
                      f"samples ({fast.attrs['samples_per_pixel']} a pixel) traced with `fast` on 0.5 µm voxels "
                      "(`make camera-fast`), beside them:", ""] \
            + camera_methods_markdown(camera_rows(fast), camera_rows(camera)) + [""]
    return out + [f"The images above are traced with `{method}`.", ""]


def design_section(d: ReportData) -> list[str]:
    if not d.maps:
        return []
    d0 = next(iter(d.maps.values()))
    return ["## Design maps: how well must the polymer match?", "",
            f"Haze and FWHM_R over thickness × ΔRI ({_maps_traced(d)}; docs/methods.md#design-maps). At ΔRI = 0 haze is 0 exactly. The "
            "largest |ΔRI| that keeps haze at or below 10 %, interpolated on the maps (`twray design` answers "
            "the same for any thickness and limit). † marks an edge below the map's smallest traced |ΔRI| "
            f"({float(abs(d0['delta_ri']).min()):g}): it is read on the straight line from haze 0 at ΔRI = 0, which "
            "no cell traced, so it has no interval; add smaller values to the maps' `vary.delta_ri` (only the new "
            "cells are traced) to measure it.", ""] + window_table(d.maps) + [
        "", f"![design maps]({d.fig}/design-maps.png)", f"![ΔRI windows]({d.fig}/design-windows.png)", ""]


def speed_against_accuracy(d: ReportData) -> list[str]:
    tradeoff = d.tradeoff
    return ["## Speed against accuracy", "",
            f"From `make tradeoff` ({len(tradeoff['point'])} settings, each traced cold in its own process on a "
            f"{tradeoff.attrs['machine_cpus']}-core host; details in [TRADEOFF.md](TRADEOFF.md)). The cheapest "
            "swept setting that meets each precision target, the error being √(bias² + CI half-width²) against "
            "exact optics of the same rays (the lattice tracer for lattices, `exact` for wood):", ""] \
        + tradeoff_markdown(tradeoff) + ["", f"![speed against accuracy]({d.fig}/tradeoff.png)", ""]


def reproducing(d: ReportData) -> list[str]:
    """Each item's command and its cost, from results/bench.json or the dataset."""
    st, cam = d.bench["study"], d.bench["camera"]["figure5"]
    out = ["## Reproducing each item", "", "| item | command | cost on 2 cores (from `results/bench.json` or the dataset) |",
           "|---|---|---|"]
    add = out.append
    if "table1_quick" in st:
        add(f"| Table 1, the quick start (the paper's samples, 5 woods, 50 rays a wood) | `make table1` | "
            f"{minutes_text(st['table1_quick']['cold_s'])} cold, {minutes_text(st['table1_quick']['warm_s'])} when cached |")
    add(f"| Table 1, a tenth of the thickness (tests) | `make table1 SCALE=small` | "
        f"{minutes_text(st['table1_small']['cold_s'])} cold, {minutes_text(st['table1_small']['warm_s'])} when cached |")
    add(f"| the measured samples | `make experiment SCALE=paper YES=1` | {minutes_text(st['experiment_paper']['cold_s'])} cold |"
        if "experiment_paper" in st else "| the measured samples | `make experiment SCALE=paper YES=1` | not recorded |")
    add(f"| fibre tips, with and without ray cells | `make fibre-tips SCALE=paper YES=1` | {minutes_text(st['fibre_tips_paper']['cold_s'])} "
        + ("(flat ends cached by Table 1) |" if st["fibre_tips_paper"].get("flat_ends_cached", True) else "cold |")
        if "fibre_tips_paper" in st
        else "| fibre tips, with and without ray cells | `make fibre-tips SCALE=paper YES=1` | not recorded |")
    if "table1_paper_method" in st:
        pm = st["table1_paper_method"]
        add(f"| Table 1, the paper's method | `make table1-paper-method YES=1` | {minutes_text(pm['cold_s'])} cold on "
            f"{pm['cores']} cores |")
    if "table1_paper" in st:
        add(f"| Table 1, this report's scale | `make table1 SCALE=paper YES=1` | "
            f"{minutes_text(st['table1_paper']['cold_s'])} cold |")
    else:
        add("| Table 1, this report's scale | `make table1 SCALE=paper YES=1` | not recorded |")
    exact_cam = d.bench["camera"].get("figure5_exact")
    if exact_cam:
        add(f"| Figure 5 (`exact`) | `make camera SCALE=paper YES=1` | {minutes_text(exact_cam['wall_s'])} cold |")
    add(f"| Figure 5 with `fast` | `make camera-fast` | {minutes_text(cam['cold_s'])} cold |")
    if "design_paper" in st:
        add(f"| design maps | `make design SCALE=paper YES=1` | {minutes_text(st['design_paper']['cold_s'])} cold |")
    add(f"| speed against accuracy | `make tradeoff` | {minutes_text(float(d.tradeoff.attrs['seconds']))} |")
    add("| figures | `make figures` | about 1 min (sections and trajectories are computed) |")
    add("| this report | `make report` | about 30 s (the bootstraps of the effects and the methods) |")
    return out + [""]


def differences(d: ReportData) -> list[str]:
    """Where twray differs from the paper, and why."""
    out = ["## Where twray differs from the paper, and why", ""]
    add = out.append
    woods, method = d.woods, d.settings["method"]
    if method == "exact":
        add("- **Method.** Table 1 here uses `exact`: rays meet the model's own wall surfaces (the inequalities "
            "the generator decides each point's phase by), each crossing found to 1e-9 µm with a proven step "
            "bound and its normal from the model itself (docs/methods.md#the-exact-method). No voxel enters. "
            "The paper traced 0.5 µm voxels (2-voxel steps, midpoint crossing, a linear SVM normal on 6×6×6 "
            "voxels): `--method paper`, compared above on the same woods and rays.")
        add("- **Resolution.** None: thin walls, corners and tips are traced as the model draws them. The voxel "
            "methods' error on these very scenes is the `accurate` table above (and results/accuracy.md on "
            "lattices).")
    else:
        add(f"- **Method.** Table 1 here uses `{method}`: exact voxel traversal (no wall skipped) and "
            "normals from a Gaussian-smoothed wall indicator, on wood generated at half the paper's voxel. "
            "The paper's method (2-voxel steps, midpoint crossing, a linear SVM on 6×6×6 voxels) is "
            "`--method paper`; against exact optics on thin-walled lattices it is several times less accurate "
            "(results/accuracy.md, TRADEOFF.md).")
        add("- **Resolution.** The paper's 0.5 µm voxel puts 4 voxels across a 2 µm wall; the smoothed normal "
            "needs about 2.7 voxels of wall to see both faces, so `accurate` traces 0.25 µm voxels of the same "
            "wood (the model is a function of position).")
    add("- **Statistics.** Every number of Table 1, the trends, the methods and the measured samples carries a 95 % "
        "interval over woods and rays (the camera's contrast and RMS error do not: one wood, one image); the "
        "trends are paired differences with their own intervals. The intervals are against sampling noise; the "
        "estimator, method and geometry are systematic and measured separately. The paper reports single values.")
    add("- **Wood.** The microstructure model follows docs/methods.md#the-microstructure-model; every value is "
        + (f"{min(woods.values())}" if min(woods.values()) == max(woods.values())
           else f"{min(woods.values())}-{max(woods.values())}")
        + " realisations of it (its study's woods), pooled. Switching ray cells or vessels off leaves every other "
        "structure where it was (tests/test_microstructure.py), so studies 5-1 and 5-2 change one factor each.")
    fine = fine_voxel_sentence(fine_voxel_rows(d.results, n_boot=d.n_boot))
    add(_convergence_sentence(d.results, fine_done=bool(fine), of_voxels=method == "exact"))
    if fine:
        add(fine)
    add("- **Angles.** Measured inside the sample, as the paper's models do; a hazemeter measures in air "
        "(`trace.exit: air` refracts each ray out of the exit face).")
    return out + [""]


def _convergence_sentence(results: Path, *, fine_done: bool = False, of_voxels: bool = False) -> str:
    """What `make convergence` found (results/convergence.zarr), or that it has not run; ``of_voxels``:
    Table 1 itself is exact, and these numbers are those of the voxel method it replaced."""
    path = Path(results) / "convergence.zarr"
    if not path.exists():
        return ("- **Convergence.** Not measured value by value yet (`make convergence`); the ray-only "
                "intervals (`FWHM_R_ray_ci_*`) bound what more rays would move.")
    ds = open_dataset(path)

    def moved(name, variant):
        d = np.abs(ds[f"{name}_change_{variant}"].values)
        lo, hi = ds[f"{name}_change_{variant}_ci_lower"].values, ds[f"{name}_change_{variant}_ci_upper"].values
        return float(np.median(d)), float(d.max()), int(np.sum((lo > 0) | (hi < 0)))

    n = ds.sizes["value"]
    r, v, lv, hv = (moved("FWHM_R", "rays_4x"), moved("FWHM_R", "voxel_0.5"), moved("FWHM_L", "voxel_0.5"),
                    moved("haze", "voxel_0.5"))
    what = "Convergence of `accurate`" if of_voxels else "Convergence"
    return (f"- **{what}** ([CONVERGENCE.md](CONVERGENCE.md), realisation 0). With 4× the rays FWHM_R moves "
            f"by a median {r[0]:.1f} % (resolved for {r[2]} of {n} values). With the wood traced on 0.5 µm "
            f"instead of 0.25 µm voxels FWHM_R moves by a median {v[0]:.1f} % (at most {v[1]:.0f} %, resolved for "
            f"{v[2]} of {n}), haze by {hv[0]:.1f} points, and FWHM_L by a median {lv[0]:.0f} % (resolved for "
            f"{lv[2]} of {n}): FWHM_L is not converged in the voxel, and the 0.25 µm values may be off by about as "
            "much again; " + ("study 5-1 on 0.125 µm voxels (8× the wood) below says how far." if fine_done
                              else "a run on 0.125 µm voxels (8× the wood) would say."))

def fine_voxel_sentence(rows: list[dict]) -> str:
    if not rows:
        return ""
    parts = []
    gaps = []  # exact against the zero-voxel extrapolation, %
    for r in rows:
        step1, step2 = r["FWHM_L_0.5"] - r["FWHM_L_0.25"], r["FWHM_L_0.25"] - r["FWHM_L_0.125"]
        order = ""
        if step1 * step2 > 0 and abs(step1) > abs(step2):
            p = math.log2(step1 / step2)
            if r.get("FWHM_L_exact") is not None:
                gaps.append(100 * (r["FWHM_L_exact"] / (r["FWHM_L_0.125"] - step2 / (2 ** p - 1)) - 1))
            order = (f", an error falling as h^{p:.1f}, which extrapolates to {r['FWHM_L_0.125'] - step2 / (2 ** p - 1):.2f}° "
                     "at zero voxel")
        exact = "" if r.get("FWHM_L_exact") is None else f", `exact` {r['FWHM_L_exact']:.3f}°"
        parts.append(f"ray cells {r['value']}: {r['FWHM_L_0.5']:.3f}° → {r['FWHM_L_0.25']:.3f}° → {r['FWHM_L_0.125']:.3f}° "
                     f"({r['change']:+.1f} % [{r['ci'][0]:+.1f}, {r['ci'][1]:+.1f}] from 0.25 to 0.125 µm{order}; "
                     f"FWHM_R {r['FWHM_R_change']:+.1f} %, haze {r['haze_change']:+.1f} pts{exact})")
    return ("- **FWHM_L on 0.125 µm voxels** (study 5-1, wood realisation 0, the same 1000 rays; "
            "`studies/convergence/study-5-1-0.125um.yaml`), FWHM_L on 0.5 → 0.25 → 0.125 µm voxels: "
            + "; ".join(parts) + ". FWHM_L still falls as the voxel shrinks, so `accurate`'s values (0.25 µm) are "
            "upper bounds; a change between two values is measured on one voxel, but its size may shrink with it "
            "too." + ("" if not gaps else " `exact` on the same wood and rays lies within "
                      f"{max(abs(g) for g in gaps):.0f} % of each zero-voxel extrapolation; the two tracers share "
                      "only the interface physics (Snell's law, total reflection), which only a tracer from outside "
                      "the project would test."))

def target_status(tables: dict) -> str:
    """Which studies meet their target with today's estimator and intervals (the woods were chosen under
    the Lorentz maximum-likelihood width and a nested interval, pool version 1), and how many woods the
    interval's 1/√woods scaling says would meet it."""
    unmet, need = [], []
    for name, ds in tables.items():
        if "target_ci_met" not in ds.attrs or int(ds.attrs["target_ci_met"]):
            continue
        unmet.append(name)
        t = json.loads(ds.attrs["target_ci"])
        ratios = [((ds.haze_ci_upper - ds.haze_ci_lower).values / 2 / t["haze"]).max()] if t.get("haze") else []
        if t.get("fwhm_r_rel"):
            ratios.append(((ds.FWHM_R_ci_upper - ds.FWHM_R_ci_lower).values / 2 / (t["fwhm_r_rel"] * ds.FWHM_R.values)).max())
        need.append(math.ceil(ds.sizes.get("realisation", 1) * max(ratios) ** 2))
    if not unmet:
        return ""
    cap = json.loads(tables[unmet[0]].attrs["target_ci"]).get("max_realisations")
    return (f" (chosen for the Lorentz maximum-likelihood FWHM_R; with today's `half-max` FWHM_R, noisier, and "
            f"intervals over woods, {', '.join(unmet)} no longer meet that target: by the interval's 1/√woods "
            f"scaling they would need {min(need)}-{max(need)} woods, against the files' cap of {cap})")


def base_scene_sentence(rows: list[dict]) -> str:
    """The base scene (1 mm, ΔRI 0.01) as pooled by each study that holds it, and whether the rows agree."""
    base = [r for r in rows if r["value"] in ("1", "1.0", "0.01") and r["study"] in ("study-1", "study-2")]
    if len(base) < 2:
        return ""
    parts = ", ".join(f"{r['study']} {r['FWHM_R']:.2f}° [{r['FWHM_R_ci'][0]:.2f}, {r['FWHM_R_ci'][1]:.2f}]" for r in base)
    apart = [a["study"] + "/" + b["study"] for i, a in enumerate(base) for b in base[i + 1:]
             if not (a["FWHM_R_ci"][0] <= b["FWHM_R"] <= a["FWHM_R_ci"][1]
                     and b["FWHM_R_ci"][0] <= a["FWHM_R"] <= b["FWHM_R_ci"][1])]
    return ("The base scene (1 mm, ΔRI 0.01) is a value of several studies, each pooled over its own woods (the "
            f"first woods shared): FWHM_R {parts}; "
            + ("each lies inside the others' intervals." if not apart else
               f"{', '.join(apart)} lie outside each other's intervals, as two samples of overlapping woods may "
               "one time in several at 95 %."))


def multiple_comparisons_sentence(all_effects: dict) -> str:
    """How many effects are resolved, how many 5 % would be by chance, and how many survive Holm's correction."""
    effs = [e for effs in all_effects.values() for e in effs]
    ps = np.array([p_value(e) for e in effs])
    ps = ps[np.isfinite(ps)]
    n = ps.size
    resolved = sum(1 for e in effs if e.resolved)
    holm = holm_resolved(ps)
    return (f"**Multiple comparisons.** {n} changes are tested above; {resolved} are resolved at 95 %, against "
            f"about {0.05 * n:.0f} that would be by chance if no change were real. {holm} stay resolved with Holm's "
            f"correction for all {n} tests (family-wise error 5 %). \"Resolved\" means resolved against sampling "
            "noise, not against the systematic choices of estimator, method and geometry.")


def figure_links(markdown: str) -> list[str]:
    """The image paths a report links, relative to its folder."""
    import re

    return re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown)
