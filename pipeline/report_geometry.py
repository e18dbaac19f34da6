"""The report's section on twray's birch against the source's own generator.

Built only from ``results/geometry.json`` (written by
``benchmarks/port_geometry.py``); nothing is recomputed here.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

# (key in geometry.json, label, unit, scale applied to the stored value)
ROWS = [
    ("wall_fraction", "wall fraction", "%", 100.0),
    ("wall_fraction_outside_vessels", "wall fraction outside vessel lumens", "%", 100.0),
    ("fibre_lumen_d_um_median", "fibre lumen eq. diameter, median", "µm", 1.0),
    ("fibre_lumen_d_um_q25", "fibre lumen eq. diameter, 25th pct", "µm", 1.0),
    ("fibre_lumen_d_um_q75", "fibre lumen eq. diameter, 75th pct", "µm", 1.0),
    ("vessel_area_fraction", "vessel area (lumens > 30 µm)", "%", 100.0),
    ("double_wall_r_um_median", "wall between lumens along R, median run", "µm", 1.0),
    ("double_wall_t_um_median", "wall between lumens along T, median run", "µm", 1.0),
    ("wall_ridge_um_median", "wall thickness at the medial ridge, median", "µm", 1.0),
    ("wall_ridge_um_q25", "wall thickness at the medial ridge, 25th pct", "µm", 1.0),
    ("interfaces_per_mm_t", "interfaces per mm along T", "/mm", 1.0),
    ("normal_l_median", "wall normal |n_L|, median", "", 1.0),
    ("normal_l_p90", "wall normal |n_L|, 90th pct", "", 1.0),
    ("normal_l_p99", "wall normal |n_L|, 99th pct", "", 1.0),
    ("normal_l_share_gt_0.1", "share of wall surface with |n_L| > 0.1", "%", 100.0),
    ("ray_slice_share", "L slices crossing a ray-cell lumen", "%", 100.0),
    ("ray_lumen_t_um_median", "ray-cell lumen T extent, median", "µm", 1.0),
]
TRACE_ROWS = [("haze", "haze", "%", 100.0), ("fwhm_r_deg", "FWHM_R", "°", 1.0),
              ("fwhm_l_deg", "FWHM_L", "°", 1.0)]


def _fmt(x, scale=1.0) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    y = x * scale
    a = abs(y)
    return f"{y:.3g}" if a < 1 else f"{y:.1f}" if a < 100 else f"{y:.0f}"


def _cell(s: dict | None, scale: float) -> str:
    if not s or s.get("mean") is None:
        return "–"
    lo, hi = s.get("ci95") or (None, None)
    if lo is None:
        return f"{_fmt(s['mean'], scale)} (n = {s.get('n', 1)})"
    lo = max(lo, 0.0)  # every statistic here is at least 0 (a t-interval over few seeds is not)
    return f"{_fmt(s['mean'], scale)} [{_fmt(lo, scale)}, {_fmt(hi, scale)}]"


def _ratio(a: dict | None, b: dict | None) -> str:
    if not a or not b or a.get("mean") is None or b.get("mean") is None or b["mean"] == 0:
        return "–"
    return f"{a['mean'] / b['mean']:.2f}"


def _resolved(a: dict | None, b: dict | None) -> bool:
    """Whether the two 95 % intervals over seeds are disjoint."""
    try:
        (alo, ahi), (blo, bhi) = a["ci95"], b["ci95"]
        return None not in (alo, ahi, blo, bhi) and (ahi < blo or bhi < alo)
    except (KeyError, TypeError, ValueError):
        return False


def _label(label: str, unit: str) -> str:
    label = label.replace("|", "\\|")  # |n_L| inside a Markdown table cell
    return f"{label} [{unit}]" if unit else label


def geometry_section(results: Path) -> str:
    """Markdown section "Geometry against the source's generator" from ``results/geometry.json``.

    Parameters
    ----------
    results : Path
        The results folder (holding ``geometry.json``) or the json file itself.

    Returns
    -------
    str
        The section, or "" when the json is missing or unreadable.
    """
    path = Path(results)
    path = path / "geometry.json" if path.is_dir() else path
    try:
        doc = json.loads(path.read_text())
        port, tw = doc["port"], doc["twray"]
    except (OSError, ValueError, KeyError):
        return ""
    ps, ts = port.get("stats", {}), tw.get("stats", {})
    size = "×".join(f"{s:g}" for s in port.get("size_um", []))
    lines = [
        "### Geometry against the source's generator",
        "",
        f"The source's generator (its public Python port, default birch parameters) and twray's birch "
        f"preset, {len(port.get('per_seed', []))} and {len(tw.get('seeds', []))} seeds of {size} µm "
        f"(R×T×L) at {port.get('voxel_um', '?')} and {tw.get('voxel_um', '?')} µm voxels, measured the same "
        "way (`pipeline/geometry_stats.py`). Mean over seeds [95 % t-interval].",
        "",
        "| statistic | port | twray | twray/port |",
        "|---|---|---|---|",
    ]
    resolved = []
    for key, label, unit, scale in ROWS:
        a, b = ts.get(key), ps.get(key)
        if a is None and b is None:
            continue
        lines.append(f"| {_label(label, unit)} | {_cell(b, scale)} | {_cell(a, scale)} | {_ratio(a, b)} |")
        if _resolved(a, b) and max(abs(a["mean"]), abs(b["mean"])) * scale >= 1e-3:  # not both ~0
            resolved.append((key, label, a["mean"], b["mean"], unit, scale))

    tr = doc.get("trace", {}).get("stats")
    if tr:
        t = doc["trace"]
        lines += ["", f"Traced as scans (Δn = {t.get('delta_ri')}, {t.get('rays')} rays, beam "
                      f"{t.get('beam_um')} µm, through the {t.get('thickness_um')} µm T extent; FWHM by "
                      f"{t.get('fwhm_estimator', 'half-max')}; mean over seeds [95 % t-interval]):", "",
                  "| method | quantity | port | twray | twray/port |", "|---|---|---|---|---|"]
        for method in ("accurate", "paper"):
            for key, label, unit, scale in TRACE_ROWS:
                a = tr.get(f"twray/{method}", {}).get(key)
                b = tr.get(f"port/{method}", {}).get(key)
                if a is None and b is None:
                    continue
                lines.append(f"| {method} | {_label(label, unit)} | {_cell(b, scale)} | {_cell(a, scale)} "
                             f"| {_ratio(a, b)} |")
                if _resolved(a, b):
                    resolved.append((f"{method}/{key}", f"{label} ({method})", a["mean"], b["mean"], unit, scale))

    lines.append("")
    if resolved:
        big = sorted(resolved, key=lambda r: -abs(math.log(abs(r[2] / r[3]))) if r[2] and r[3] else 0)
        parts = [f"{lab} ({_fmt(tv, sc)} vs {_fmt(pv, sc)}{' ' + u if u else ''}, ×{tv / pv:.2f})"
                 if pv else f"{lab} ({_fmt(tv, sc)} vs {_fmt(pv, sc)})" for _, lab, tv, pv, u, sc in big[:4]]
        n = len(resolved)
        lines.append(f"{n} difference{'s are' if n > 1 else ' is'} resolved (intervals over seeds do not overlap); "
                     f"the largest: {'; '.join(parts)}.")
        n_rows = len([r for r in ROWS if r[0] in ts or r[0] in ps])
        n_other = n_rows - len([r for r in resolved if "/" not in r[0]])
        lines.append(f"The other {n_other} geometry statistic{'s' if n_other != 1 else ''} "
                     "agree within the seed-to-seed spread (overlapping intervals).")
    else:
        lines.append("No difference is resolved: every pair of intervals over seeds overlaps.")
    keys = {r[0] for r in resolved}
    if "wall_fraction" in keys and "wall_fraction_outside_vessels" not in keys and ps.get("vessel_area_fraction"):
        pv, tv = ps["vessel_area_fraction"].get("mean"), ts.get("vessel_area_fraction", {}).get("mean")
        if pv is not None and tv is not None:
            lines.append(f"The wall fraction goes with the vessel share ({_fmt(tv, 100)} % of the area in twray, "
                         f"{_fmt(pv, 100)} % in the port): outside vessel lumens the intervals overlap.")
    for c in doc.get("size_check", []):
        pc, tc = c.get("port", {}), c.get("twray", {})
        size = "×".join(f"{x:g}" for x in c.get("size_um", []))
        lines.append(f"At {size} µm (one seed): vessel area {_fmt(pc.get('vessel_area_fraction'), 100)} % (port) "
                     f"vs {_fmt(tc.get('vessel_area_fraction'), 100)} % (twray), wall fraction outside vessels "
                     f"{_fmt(pc.get('wall_fraction_outside_vessels'), 100)} % vs "
                     f"{_fmt(tc.get('wall_fraction_outside_vessels'), 100)} %.")
    nrc = doc.get("no_ray_cells")
    if nrc:
        pn, tn = nrc["port"]["stats"], nrc["twray"]["stats"]
        lines += ["", f"Without ray cells (the port with `isExistRayCell` 0, twray with `ray_cells: false`; "
                      f"{len(nrc.get('seeds', []))} seeds each): the fibres' own walls, where FWHM_L without ray "
                      "cells comes from.", "", "| statistic | port | twray | twray/port |", "|---|---|---|---|"]
        for key, label, unit, scale in ROWS:
            if key.startswith(("normal_l", "wall_fraction", "interfaces")) and (key in pn or key in tn):
                lines.append(f"| {_label(label, unit)} | {_cell(pn.get(key), scale)} | {_cell(tn.get(key), scale)} "
                             f"| {_ratio(tn.get(key), pn.get(key))} |")
        lines.append("")
    val = doc.get("ray_detector_validation")
    if val:
        rec = [v["recall"] for v in val if v.get("recall") is not None]
        fp = [v["false_positive_share"] for v in val if v.get("false_positive_share") is not None]
        if rec or fp:
            lines.append(f"The ray-slice detector, checked on twray's volumes against the same seeds without "
                         f"ray cells, found {_fmt(min(rec) * 100 if rec else None)}–"
                         f"{_fmt(max(rec) * 100 if rec else None)} % of the slices that cross a ray group, "
                         f"with at most {_fmt(max(fp) * 100 if fp else None)} % false positives.")
    return "\n".join(lines) + "\n"
