"""The report's tables as Markdown: Table 1, its woods and their spread, two methods side by side,
the measured samples, the fibre tips and the trends (numbers from :mod:`pipeline.effects`)."""

from __future__ import annotations

import json
import math

import numpy as np

from .effects import TRADEOFF_TARGETS, Effect, cheapest_meeting, setting_label
from .result_sets import study_dimension

def _f(x, nd=2) -> str:
    return f"{x:.{nd}f}"

def with_ci(x: float, ci, nd: int = 2) -> str:
    """``x [lo, hi]`` at ``nd`` decimals."""
    return f"{_f(x, nd)} [{_f(ci[0], nd)}, {_f(ci[1], nd)}]"

def table1_markdown(rows: list[dict]) -> list[str]:
    lines = ["| study | parameter | value | FWHM_R (°) [95 % CI] | FWHM_L (°) [95 % CI] | haze (%) [95 % CI] "
             "| woods | transmitted | interfaces per ray | FWHM_R of the woods (°) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        each = r["FWHM_R_each"]
        lines.append(
            f"| {r['study']} | {r['parameter']} | {r['value']} | {with_ci(r['FWHM_R'], r['FWHM_R_ci'])} | "
            f"{with_ci(r['FWHM_L'], r['FWHM_L_ci'])} | {with_ci(r['haze'], r['haze_ci'], 1)} | {each.size} | "
            f"{r['transmitted']}/{r['rays']} | {_f(r['interfaces_per_ray'], 1)} | "
            f"{_f(each.min())} – {_f(each.max())} |")
    return lines

def woods_text(woods: dict, target: dict | None, first_seed: int) -> str:
    """How many woods each study traced, and why."""
    lo, hi = min(woods.values()), max(woods.values())
    if lo == hi:
        return (f"{hi} wood realisations (seeds {first_seed}-{first_seed + hi - 1}: every value of every study is "
                f"traced on the same {hi} woods)")
    why = ""
    if target is not None and target.get("over") == "woods":
        asked = []
        if target.get("haze") is not None:
            asked.append(f"±{100 * target['haze']:g} haze point{'s' if 100 * target['haze'] != 1 else ''}")
        if target.get("fwhm_r_rel") is not None:
            asked.append(f"±{100 * target['fwhm_r_rel']:g} % FWHM_R")
        why = (f", as many as {' and '.join(asked)} with the woods ask for (`target_ci` over woods, at most "
               f"{target['max_realisations']})")
    each = ", ".join(f"{name} {n}" for name, n in woods.items())
    return (f"{lo}-{hi} wood realisations per study ({each}{why}; seeds {first_seed}, {first_seed + 1}, …: the "
            "wood of a seed is the same in every study and for every value of a study)")

def variation_markdown(rows: list[dict]) -> list[str]:
    """How much each value moves from one wood to the next, split into what the woods and what each
    wood's 1000 rays contribute (variance components), and what that does to its interval."""
    lines = ["| study | value | FWHM_R: spread of the woods (CV) | of it, between woods · rays of one wood (SD, °) "
             "| FWHM_L: CV | haze: SD of the woods (points) | of it, between woods · rays of one wood (points) "
             "| FWHM_R interval, rays alone → with the woods |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        def cv(v):
            return f"{100 * np.std(v, ddof=1) / np.mean(v):.0f} %" if v.size > 1 and np.mean(v) > 0 else "—"
        ray, both = r["FWHM_R_ray_ci"], r["FWHM_R_ci"]
        c = r.get("components", {})
        fr = f"{c['FWHM_R'][0]:.2f} · {c['FWHM_R'][1]:.2f}" if "FWHM_R" in c else "—"
        hz = f"{100 * c['haze'][0]:.1f} · {100 * c['haze'][1]:.1f}" if "haze" in c else "—"
        lines.append(f"| {r['study']} | {r['parameter']} {r['value']} | {cv(r['FWHM_R_each'])} | {fr} | "
                     f"{cv(r['FWHM_L_each'])} | "
                     f"{np.std(r['haze_each'], ddof=1) if r['haze_each'].size > 1 else float('nan'):.1f} | {hz} | "
                     f"±{(ray[1] - ray[0]) / 2:.2f}° → ±{(both[1] - both[0]) / 2:.2f}° |")
    return lines

def method_markdown(rows: list[dict]) -> list[str]:
    ref, other = rows[0]["ref"], rows[0]["other"]
    both, minus = f"{ref} · {other}", f"{other} − {ref}"
    lines = [f"| study | value | FWHM_R (°): {both} | {minus} | FWHM_L (°): {both} | {minus} | haze (%): {both} "
             f"| {minus} |", "|---|---|---|---|---|---|---|---|"]

    def change(c, unit):
        d, (lo, hi) = c
        return f"{d:+.0f}{unit} [{lo:+.0f}, {hi:+.0f}]" + ("" if lo > 0 or hi < 0 else " (not resolved)")

    for r in rows:
        lines.append(
            f"| {r['study']} | {r['parameter']} {r['value']} | {r['FWHM_R_ref']:.2f} · {r['FWHM_R_other']:.2f} | "
            f"{change(r['FWHM_R_change'], ' %')} | {r['FWHM_L_ref']:.2f} · {r['FWHM_L_other']:.2f} | "
            f"{change(r['FWHM_L_change'], ' %')} | {r['haze_ref']:.1f} · {r['haze_other']:.1f} | "
            f"{change(r['haze_change'], ' pts')} |")
    return lines

def method_summary(rows: list[dict]) -> str:
    """How many of the values each quantity differs for (interval excluding 0), and by how much."""
    parts = []
    for q, unit in (("FWHM_R", " %"), ("FWHM_L", " %"), ("haze", " points")):
        hit = [r for r in rows if r[f"{q}_change"][1][0] > 0 or r[f"{q}_change"][1][1] < 0]
        span = "" if not hit else (f" (from {min(r[f'{q}_change'][0] for r in hit):+.0f} to "
                                   f"{max(r[f'{q}_change'][0] for r in hit):+.0f}{unit})")
        parts.append(f"{q} for {len(hit)} of {len(rows)} values{span}")
    return f"`{rows[0]['other']}` differs from `{rows[0]['ref']}` beyond its interval in " + "; ".join(parts) + "."

def balsa_reading_sentence(radius, diameter) -> str:
    """The balsa sample with its quoted 35.2 µm read as a radius (70.4 µm cells) beside the preset's
    reading as a diameter, value by value (walls)."""
    def haze(one) -> str:
        return with_ci(100 * float(one["haze"]), (100 * float(one["haze_ci_lower"]),
                                                    100 * float(one["haze_ci_upper"])), 1)

    dim = study_dimension(radius)
    parts = []
    for k in range(radius.sizes[dim]):
        a, b = radius.isel({dim: k}), diameter.isel({dim: k})
        parts.append(f"{float(a[dim]):g} µm walls: haze {haze(a)} % against {haze(b)} %, "
                     f"FWHM_R {float(a['FWHM_R']):.2f}° against {float(b['FWHM_R']):.2f}°")
    return ("The source's \"fibre radius of around 35.2 µm\" can also be read as a radius: 70.4 µm cells "
            "(`studies/experiment/balsa-1mm-radius.yaml`, angles inside, the same seeds and beam). Against the "
            "preset's reading as a diameter: " + "; ".join(parts) + ". The preset keeps the diameter reading, "
            "by analogy with birch, whose quoted 14.5 is its fibre diameter.")

def experiment_markdown(rows: list[dict]) -> list[str]:
    lines = ["| sample | wall (µm) | haze inside (%) [95 % CI] | haze in air (%) [95 % CI] | haze in air, each wood (%) "
             "| FWHM_R inside → in air (°) |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['wood']} TW, {r['thickness_mm']:g} mm, {r['fibre_um']:g} µm cells | {r['wall_um']:g} | "
            f"{with_ci(r['haze_inside'], r['haze_inside_ci'], 1)} | {with_ci(r['haze_air'], r['haze_air_ci'], 1)} | "
            f"{', '.join(f'{v:.0f}' for v in r['haze_air_each'])} | "
            f"{r['FWHM_R_inside']:.2f} → {r['FWHM_R_air']:.2f} |")
    return lines

def fibre_tip_markdown(rows: list[dict]) -> list[str]:
    lines = ["| ray cells | fibre tips λ (µm) | tip wall to L | FWHM_R (°) [95 % CI] | FWHM_L (°) [95 % CI] "
             "| haze (%) [95 % CI] | FWHM_R against flat ends | FWHM_L against flat ends | haze against flat ends |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ch = r["change"]
        cells = [_effect_cell(ch[q]) if ch[q] is not None else "reference" for q in ("FWHM_R", "FWHM_L", "haze")]
        lines.append(
            f"| {'yes' if r['ray_cells'] else 'no'} | {r['tip_um']:g}{' (flat ends)' if not r['tip_um'] else ''} | "
            f"{r['angle_deg']:.1f}° | {with_ci(r['FWHM_R'], r['FWHM_R_ci'])} | {with_ci(r['FWHM_L'], r['FWHM_L_ci'])} | "
            f"{with_ci(r['haze'], r['haze_ci'], 1)} | " + " | ".join(cells) + " |")
    return lines

def fibre_tip_sentence(rows: list[dict]) -> str:
    """What overlapping tips do to FWHM_L, with and without ray cells, read from the rows."""
    parts = []
    for ray_cells in (True, False):
        mine = [r for r in rows if r["ray_cells"] == ray_cells]
        flat = next(r for r in mine if not r["tip_um"])
        tipped = [r for r in mine if r["tip_um"]]
        resolved = [r for r in tipped if r["change"]["FWHM_L"].resolved]
        moves = ", ".join(f"{_effect_cell(r['change']['FWHM_L'])} at λ = {r['tip_um']:g} µm" for r in tipped)
        parts.append(f"{'with' if ray_cells else 'without'} ray cells, FWHM_L of {flat['FWHM_L']:.2f}° with flat "
                     f"ends changes by {moves} ({len(resolved)} of {len(tipped)} resolved)")
    mine = [r for r in rows if r["ray_cells"]]
    flat, longest = mine[0], max(mine, key=lambda r: r["tip_um"])
    grow = longest["interfaces_per_ray"] / flat["interfaces_per_ray"]
    return ("; ".join(parts) + ". The oblique walls are also walls to cross: with ray cells, a ray meets "
            f"{flat['interfaces_per_ray']:.0f} interfaces with flat ends and {longest['interfaces_per_ray']:.0f} at "
            f"λ = {longest['tip_um']:g} µm ({100 * (grow - 1):+.0f} %); a random walk (FWHM_R ∝ √N, as over "
            f"thickness in study 1) predicts FWHM_R {100 * (math.sqrt(grow) - 1):+.0f} %, against "
            f"{longest['change']['FWHM_R'].change:+.0f} % measured.")

def _effect_cell(e: Effect) -> str:
    unit = " pts" if e.quantity == "haze" else " %"
    mark = "" if e.resolved else " (not resolved)"
    return f"{e.change:+.1f}{unit} [{e.ci[0]:+.1f}, {e.ci[1]:+.1f}]{mark}"

def effects_markdown(all_effects: dict) -> list[str]:
    lines = ["| study | change | FWHM_R | FWHM_L | haze |", "|---|---|---|---|---|"]
    for name, effs in all_effects.items():
        by_value: dict = {}
        for e in effs:
            by_value.setdefault(e.value, {})[e.quantity] = e
        for value, q in by_value.items():
            e0 = q["FWHM_R"]
            lines.append(f"| {name} | {e0.parameter} {e0.reference} → {value} | {_effect_cell(q['FWHM_R'])} | "
                         f"{_effect_cell(q['FWHM_L'])} | {_effect_cell(q['haze'])} |")
    return lines


def camera_markdown(rows: list[dict]) -> list[str]:
    lines = ["| image | focal length (mm) | gap (µm) | ΔRI | object | interfaces per ray | contrast "
             "(ideal) | RMS error vs ideal |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['config']} | {r['focal_mm']:g} | {r['gap_um']:g} | {r['delta_ri']:.3g} | "
                     f"“{r['object']}”, {r['object_size_mm']:g} mm | {r['interfaces_per_ray']:.1f} | "
                     f"{r['contrast']:.2f} ({r['ideal_contrast']:.2f}) | {r['rmse']:.3f} |")
    return lines


def camera_methods_markdown(fast: list[dict], exact: list[dict]) -> list[str]:
    """Each image traced with `fast` and with `exact` on the same aperture samples."""
    lines = ["| image | interfaces per ray, fast / exact | contrast, fast / exact (ideal) | "
             "RMS error vs ideal, fast / exact |", "|---|---|---|---|"]
    for f, e in zip(fast, exact):
        lines.append(f"| {f['config']} | {f['interfaces_per_ray']:.1f} / {e['interfaces_per_ray']:.1f} | "
                     f"{f['contrast']:.2f} / {e['contrast']:.2f} ({e['ideal_contrast']:.2f}) | "
                     f"{f['rmse']:.3f} / {e['rmse']:.3f} |")
    return lines


def tradeoff_markdown(ds) -> list[str]:
    """The cheapest swept setting (cold wall time) meeting each of the two looser targets, per scene."""
    targets = TRADEOFF_TARGETS[1:]
    lines = ["| scene | " + " | ".join(t for t, _, _ in targets) + " |", "|---|" + "---|" * len(targets)]
    for scene in json.loads(ds.attrs["scenes"]):
        sel = ds.where((ds["scene"] == scene) & np.isfinite(ds["haze_error"]), drop=True)
        rows = [{"method": str(p["method"].values), "voxel_um": float(p["voxel_um"]), "rays": int(p["rays"]),
                 "step_vox": float(p["step_vox"]), "wall_s": float(p["wall_time"]),
                 "haze_error": float(p["haze_error"]),
                 "fwhm_r_rel_error": float(p["FWHM_R_error"] / p["reference_FWHM_R"])}
                for p in (sel.isel(point=k) for k in range(sel.sizes.get("point", 0)))]
        cells = []
        for _, h, f in targets:
            b = cheapest_meeting(rows, h, f) if rows else None
            if b is None:
                cells.append("none of the swept settings" if rows else "—")
                continue
            cells.append(f"{setting_label(b['method'], b['voxel_um'], b['rays'], b['step_vox'])}: {b['wall_s']:.1f} s "
                         f"(haze ±{100 * b['haze_error']:.1f} pts, FWHM_R ±{100 * abs(b['fwhm_r_rel_error']):.0f} %)")
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return lines


def minutes_text(s: float) -> str:
    return f"{s / 60:.1f} min" if s >= 90 else f"{s:.0f} s"
