"""Design maps: haze and FWHM_R over thickness × ΔRI, and the ΔRI window that keeps haze below a
limit (docs/methods.md#design-maps).

A design map is a grid study (``studies/design/``) whose Dataset has the
dimensions ``thickness`` [mm] and ``delta_ri``.  At ΔRI = 0 the wall and the
polymer are one medium: no ray is deviated, haze and FWHM_R are 0 exactly, and
the maps use that as their centre line.  Between grid values haze is
interpolated linearly, first along the thickness, then along |ΔRI| on each
side of 0; the window's interval comes from the same interpolation of the
haze interval's bounds (its upper bound crosses the limit first: the smallest
|ΔRI| the data allow; its lower bound last: the largest).  Below the smallest
traced |ΔRI| the maps know only the straight line to ΔRI = 0, which the traced
cells show is not how haze grows there: an edge or a value read on that line
is marked as extrapolated and given no interval.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .params import ParameterError

MAPS = ("birch", "birch-air", "balsa", "balsa-air")  # studies/design/<name>.yaml → results/<scale>/design/<name>.zarr
HAZE_LEVELS = (0.1, 0.2, 0.5)  # the contours drawn on the maps


def map_name(preset: str, exit: str) -> str:
    """The design map of ``preset`` with angles ``exit`` ("internal" or "air")."""
    return preset if exit == "internal" else f"{preset}-{exit}"


@dataclass(frozen=True)
class Edge:
    """The largest |ΔRI| on one side of 0 that keeps haze at or below the limit, with its 95 %
    interval; ``beyond``: the haze stays below the limit over the whole map on that side (the
    value is then the map's last |ΔRI|, a lower bound)."""

    value: float
    lo: float  # nan when ``below``: no interval on a line the map did not trace
    hi: float
    beyond: bool = False
    below: bool = False  # the edge lies below the map's smallest |ΔRI|: on the line from ΔRI = 0
    traced_min: float = float("nan")  # the map's smallest traced |ΔRI| on this side


def _crossing(x: np.ndarray, y: np.ndarray, level: float) -> tuple[float, bool]:
    """The first x at which the piecewise-linear y (x ascending, from (0, 0)) reaches ``level``;
    (the last x, True) if it never does."""
    for k in range(1, len(x)):
        if y[k] > level:
            if y[k - 1] >= level:
                return float(x[k - 1]), False
            return float(x[k - 1] + (x[k] - x[k - 1]) * (level - y[k - 1]) / (y[k] - y[k - 1])), False
    return float(x[-1]), True


def haze_at(ds, thickness_mm: float):
    """Haze and its interval bounds at ``thickness_mm``, interpolated along the map's thickness."""
    t = ds["thickness"].values.astype(float)
    if not t.min() <= thickness_mm <= t.max():
        raise ParameterError(f"`thickness_mm` must lie within the design map's {t.min():g}-{t.max():g} mm, got "
                             f"thickness_mm={thickness_mm:g} (add thicknesses to the map's `vary.thickness_mm` "
                             "and run `make design`)")
    sel = ds[["haze", "haze_ci_lower", "haze_ci_upper"]]
    return sel.interp(thickness=thickness_mm) if thickness_mm not in t else sel.sel(thickness=thickness_mm)


def window(ds, thickness_mm: float, haze_max: float) -> dict[str, Edge]:
    """The ΔRI window keeping haze <= ``haze_max`` at ``thickness_mm``: per side ("negative",
    "positive") the largest |ΔRI| with its interval."""
    if not 0.0 < haze_max < 1.0:
        raise ParameterError(f"`haze_max` must be a fraction in (0, 1), got haze_max={haze_max:g}")
    at = haze_at(ds, thickness_mm)
    dri = at["delta_ri"].values.astype(float)
    out = {}
    for side, sign in (("negative", -1.0), ("positive", 1.0)):
        pick = np.flatnonzero(sign * dri > 0)
        pick = pick[np.argsort(np.abs(dri[pick]))]
        if pick.size == 0:
            raise ParameterError(f"the design map has no {side} ΔRI: add some to its `vary.delta_ri`")
        x = np.concatenate([[0.0], np.abs(dri[pick])])
        edge = {}
        for name in ("haze", "haze_ci_upper", "haze_ci_lower"):
            y = np.concatenate([[0.0], at[name].values[pick]])
            edge[name] = _crossing(x, y, haze_max)
        e = edge["haze"][0]
        below = e < x[1]
        lo, hi = (np.nan, np.nan) if below else (edge["haze_ci_upper"][0], edge["haze_ci_lower"][0])
        out[side] = Edge(e, lo, hi, edge["haze"][1], below, float(x[1]))
    return out


FORWARD = ("haze", "FWHM_R")  # what a map answers forwards, each with its _ci_lower and _ci_upper


@dataclass(frozen=True)
class Reading:
    """Haze and FWHM_R of a map at one thickness and ΔRI: each (value, lower, upper), and how the
    map knows it: "traced" (a cell), "interpolated" (between traced cells), "extrapolated" (between
    ΔRI = 0 and the smallest traced |ΔRI|: no interval) or "matched" (ΔRI = 0: 0 exactly)."""

    haze: tuple
    fwhm_r: tuple
    how: str


def reading(ds, thickness_mm: float, delta_ri: float) -> Reading:
    """What the map ``ds`` says of ``thickness_mm`` and ``delta_ri``: linear between its
    thicknesses, then along ΔRI on the same side of 0 (value and bounds alike)."""
    dri = ds["delta_ri"].values.astype(float)
    if not dri.min() <= delta_ri <= dri.max():
        raise ParameterError(f"`delta_ri` must lie within the design map's {dri.min():g} to {dri.max():g}, got "
                             f"delta_ri={delta_ri:g} (add values to the map's `vary.delta_ri` and run `make design`)")
    names = [n + s for n in FORWARD for s in ("", "_ci_lower", "_ci_upper")]
    haze_at(ds, thickness_mm)  # the thickness's own check
    t = ds["thickness"].values.astype(float)
    at = ds[names].interp(thickness=thickness_mm) if thickness_mm not in t else ds[names].sel(thickness=thickness_mm)
    if delta_ri == 0.0:
        return Reading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), "matched")
    side = np.flatnonzero(np.sign(dri) == np.sign(delta_ri))
    side = side[np.argsort(np.abs(dri[side]))]
    x = np.abs(dri[side])
    d = abs(delta_ri)
    vals = {n: at[n].values[side].astype(float) for n in names}
    if d < x[0]:  # on the line from ΔRI = 0: a value, no interval
        f = d / x[0]
        return Reading((f * vals["haze"][0], np.nan, np.nan), (f * vals["FWHM_R"][0], np.nan, np.nan), "extrapolated")
    get = {n: float(np.interp(d, x, v)) for n, v in vals.items()}
    how = "traced" if d in x and thickness_mm in t else "interpolated"
    return Reading(*(tuple(get[n + s] for s in ("", "_ci_lower", "_ci_upper")) for n in FORWARD), how)


def reading_line(ds, thickness_mm: float, delta_ri: float) -> str:
    """:func:`reading` as one line: haze [%] and FWHM_R [°] with their 95 % intervals."""
    r = reading(ds, thickness_mm, delta_ri)
    est = ds.attrs.get("fwhm_estimator", "lorentz-mle")

    def text(v, unit, scale):
        if np.isnan(v[1]):
            return f"{scale * v[0]:.3g}{unit}"
        return f"{scale * v[0]:.3g}{unit} [{scale * v[1]:.3g}, {scale * v[2]:.3g}]"

    how = {"traced": "a traced cell", "interpolated": "interpolated between traced cells",
           "matched": "index-matched: nothing deviates",
           "extrapolated": "extrapolated below the smallest traced |ΔRI| on the line from ΔRI = 0; no interval"}
    return (f"haze {text(r.haze, ' %', 100.0)}, FWHM_R ({est}) {text(r.fwhm_r, '°', 1.0)} at {thickness_mm:g} mm, "
            f"ΔRI {delta_ri:+g} ({how[r.how]})")


def open_map(results: Path, preset: str, exit: str, path: str | None = None):
    """The design map Dataset: ``path``, or results/design/<preset>[-air].zarr; one line if absent."""
    import xarray as xr

    where = Path(path) if path else Path(results) / "design" / f"{map_name(preset, exit)}.zarr"
    if not where.exists():
        field, value = ("map", path) if path else ("results", str(results))
        raise ParameterError(f"`{field}` must hold the design map {where} (run `make design`, or "
                             f"`twray study studies/design/{map_name(preset, exit)}.yaml --results "
                             f"{Path(results) / 'design'}`), got {field}={value!r}")
    ds = xr.open_zarr(where, consolidated=False)
    if set(ds["haze"].dims) != {"thickness", "delta_ri"}:
        raise ParameterError(f"`map` must be a study over thickness_mm × delta_ri, got {where} with dimensions "
                             f"{', '.join(ds['haze'].dims)}")
    return ds


def window_line(ds, thickness_mm: float, haze_max: float) -> str:
    """The window as one sentence, with its intervals and what the map was traced with."""
    w = window(ds, thickness_mm, haze_max)
    n, p = w["negative"], w["positive"]

    return (f"haze <= {100 * haze_max:g} % at {thickness_mm:g} mm for ΔRI from {edge_text(n, '-')} to "
            f"{edge_text(p, '+')} (95 % intervals, wood-to-wood variation included)")


def regime_line(results: Path, preset: str, thickness_mm: float, haze_max: float, ds, exit: str) -> str:
    """Whether rays hold at the window's two edges, from results/wave/regime.zarr (`make wave`)."""
    from .publish import open_dataset
    from .wave.run import verdict_at, verdict_text

    path = Path(results) / "wave" / "regime.zarr"
    if not path.exists():
        return f"not measured (no {path}: run `make wave`)"
    regime = open_dataset(path)
    w = window(ds, thickness_mm, haze_max)
    return "; ".join(f"{sign}{w[side].value:.2g}: {verdict_text(verdict_at(regime, preset, thickness_mm, s * w[side].value, exit))}"
                     for side, sign, s in (("negative", "-", -1.0), ("positive", "+", 1.0)))


def edge_text(e: Edge, sign: str, short: bool = False) -> str:
    """One side of a window as text: the edge and its interval, ordered along ΔRI; an edge below
    the smallest traced |ΔRI| as extrapolated, with no interval (``short``: marked † only)."""
    if e.beyond:
        return f"beyond {sign}{e.value:.3g} (the map's edge)"
    if e.below:
        return (f"{sign}{e.value:.2g} †" if short else
                f"{sign}{e.value:.2g} (extrapolated: below the smallest traced |ΔRI|, {e.traced_min:g}, on the "
                "line from ΔRI = 0; no interval)")
    lo, hi = (e.lo, e.hi) if sign == "+" else (e.hi, e.lo)
    return f"{sign}{e.value:.2g} [{sign}{lo:.2g}, {sign}{hi:.2g}]"


def _with_zero(ds, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(thickness, ΔRI with 0 inserted, values with 0 at ΔRI = 0): the maps' exact centre line."""
    dri = ds["delta_ri"].values.astype(float)
    order = np.argsort(dri)
    dri = dri[order]
    v = ds[name].transpose("thickness", "delta_ri").values[:, order]
    k = int(np.searchsorted(dri, 0.0))
    return (ds["thickness"].values.astype(float), np.insert(dri, k, 0.0), np.insert(v, k, 0.0, axis=1))


def regime_marks(ds, regime) -> tuple[list, list]:
    """(ΔRI, thickness) points of the map ``ds`` where the regime map ``regime`` (rays against waves)
    measured that rays do not hold (first list) and where they do (second); cells it did not
    measure are in neither."""
    from .wave.run import verdict_at

    preset = json.loads(ds.attrs["scenes"])[0]["wood"]["species"]
    exit = str(ds.attrs.get("exit_angles", "internal"))
    out, ok = [], []
    for t in ds["thickness"].values:
        for d in ds["delta_ri"].values:
            measured = float(d) in [float(v) for v in regime["delta_ri"].values]
            v = verdict_at(regime, preset, float(t), float(d), exit) if measured else None
            if v is not None:
                (ok if v["holds"] else out).append((float(d), float(t)))
    return out, ok


def plot_maps(maps: dict, path: Path, regime=None) -> Path:
    """Haze and FWHM_R over thickness × ΔRI for each map (columns), the haze = 10, 20, 50 %
    contours on both; with ``regime`` (the rays-against-waves map), × on the cells where rays were
    measured not to hold and ○ where they hold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(maps), figsize=(4.2 * len(maps), 7.0), squeeze=False)
    for j, (name, ds) in enumerate(maps.items()):
        t, dri, haze = _with_zero(ds, "haze")
        _, _, fw = _with_zero(ds, "FWHM_R")
        est = ds.attrs.get("fwhm_estimator", "lorentz-mle")
        for i, (vals, label, scale) in enumerate(((haze, "haze [%]", 100.0), (fw, f"FWHM_R, {est} [°]", 1.0))):
            ax = axes[i, j]
            cf = ax.contourf(dri, t, vals * scale, levels=12, cmap="magma")
            fig.colorbar(cf, ax=ax, label=label)
            cs = ax.contour(dri, t, haze * 100.0, levels=[100 * h for h in HAZE_LEVELS], colors="w",
                            linewidths=1.0)
            ax.clabel(cs, fmt="%g %%", fontsize=7)
            if regime is not None:
                out, ok = regime_marks(ds, regime)
                for pts, marker in ((out, "x"), (ok, "o")):
                    if pts:
                        colour = {"edgecolors": "c", "facecolors": "none"} if marker == "o" else {"c": "c"}
                        ax.scatter(*zip(*pts), marker=marker, s=28, linewidths=1.2, **colour,
                                   label="rays do not hold (waves)" if marker == "x" else "rays hold")
                if i == 0 and j == 0 and (out or ok):
                    ax.legend(fontsize=6, loc="upper left")
            ax.set_xscale("symlog", linthresh=1e-3)
            ax.set_yscale("log")
            ax.set_xlabel("ΔRI (wall − polymer)")
            ax.set_ylabel("thickness [mm]")
            if i == 0:
                ax.set_title(f"{name.removesuffix('-air')}, angles {'in air' if name.endswith('-air') else 'internal'}",
                             fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def plot_windows(maps: dict, path: Path, levels=HAZE_LEVELS) -> Path:
    """The largest |ΔRI| keeping haze below each level, against thickness, per map and side, with
    its 95 % interval as a band; edges extrapolated below the smallest traced |ΔRI| as open
    circles, without a band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(levels), figsize=(4.6 * len(levels), 4.0), squeeze=False)
    for j, h in enumerate(levels):
        ax = axes[0, j]
        for (name, ds), colour in zip(maps.items(), ("tab:blue", "tab:cyan", "tab:red", "tab:orange")):
            t = ds["thickness"].values.astype(float)
            for side, style in (("positive", "-"), ("negative", "--")):
                edges = [window(ds, d, h)[side] for d in t]
                # Where haze stays below the limit to the map's edge the line stops (no bound to draw).
                ax.plot(t, [np.nan if e.beyond else e.value for e in edges], style, color=colour,
                        label=f"{name}, ΔRI {'>' if side == 'positive' else '<'} 0")
                ax.fill_between(t, [e.lo for e in edges], [e.hi for e in edges], color=colour, alpha=0.12)
                far = [(d, e.value) for d, e in zip(t, edges) if e.below]  # extrapolated: open, no band
                if far:
                    ax.scatter(*zip(*far), s=22, facecolors="white", edgecolors=colour, zorder=3)
        ax.scatter([], [], s=22, facecolors="white", edgecolors="k",
                   label="extrapolated below the smallest traced |ΔRI| (no interval)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("thickness [mm]")
        ax.set_ylabel("largest |ΔRI| with haze below the limit")
        ax.set_title(f"haze <= {100 * h:g} %")
        if j == 0:
            ax.legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def window_table(maps: dict, thicknesses=(0.25, 1.0, 2.0), limit: float = 0.1) -> list[str]:
    """Markdown: per map and thickness, the ΔRI window keeping haze <= ``limit``, with intervals."""
    lines = [f"| map | thickness [mm] | largest ΔRI < 0 for haze ≤ {100 * limit:g} % [95 % CI] | "
             f"largest ΔRI > 0 [95 % CI] |", "|---|---|---|---|"]
    for name, ds in maps.items():
        for d in thicknesses:
            w = window(ds, d, limit)
            lines.append(f"| {name} | {d:g} | {edge_text(w['negative'], '-', True)} | "
                         f"{edge_text(w['positive'], '+', True)} |")
    return lines


def two_digits(x: float) -> str:
    """``x`` to two significant digits as a table prints it: never in powers of ten (110, not 1.1e+02)."""
    text = f"{x:.2g}"
    return f"{x:.0f}" if "e+" in text else text


def glance_tables(maps: dict) -> list[str]:
    """Markdown for a designer, per species: haze, then FWHM_R, in air / inside the sample, over the
    traced thickness × ΔRI cells of its two maps (``maps``: by name of MAPS)."""
    lines = []
    for preset in ("birch", "balsa"):
        inside, air = maps.get(preset), maps.get(map_name(preset, "air"))
        if inside is None or air is None:
            continue
        dri = np.sort(inside["delta_ri"].values.astype(float))
        est = inside.attrs.get("fwhm_estimator", "lorentz-mle")
        for name, what, scale, fmt in (("haze", "haze [%]", 100.0, "{:.0f}".format),
                                       ("FWHM_R", f"FWHM_R ({est}) [°]", 1.0, two_digits)):
            lines += [f"**{preset}, {what}**, in air / inside", "",
                      "| thickness [mm] \\ ΔRI | " + " | ".join(f"{d:+g}" for d in dri) + " |",
                      "|---|" + "---|" * len(dri)]
            for t in inside["thickness"].values.astype(float):
                cells = [fmt(scale * float(air[name].sel(thickness=t, delta_ri=d))) + "/"
                         + fmt(scale * float(inside[name].sel(thickness=t, delta_ri=d))) for d in dri]
                lines.append(f"| {t:g} | " + " | ".join(cells) + " |")
            lines.append("")
    return lines
