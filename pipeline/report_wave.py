"""REPORT.md's "Where geometrical optics holds": `exact` rays against scalar waves on the same sections
(``results/<scale>/wave/regime.zarr``, ``make wave``), its tables and its two figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .analysis import SLUG
from .design import two_digits
from .wave.run import FWHM_TOL, HAZE_TOL, WINDOW_LOST

REGIME = Path("wave") / "regime.zarr"  # under a scale's results folder
HM = f"FWHM_R_{SLUG['half-max']}"


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def _ci(ds, name: str, scale: float = 1.0, fmt: str = "+.1f") -> str:
    lo, hi = f"{name}_ci_lower", f"{name}_ci_upper"
    if lo not in ds:
        return ""
    return f" [{scale * float(ds[lo]):{fmt}}, {scale * float(ds[hi]):{fmt}}]"


def _deg(x: float) -> str:
    """A width in degrees, as the tables print it (below 0.01°: a width rays give when nearly none is deviated)."""
    return "<0.01°" if x < 0.01 else f"{two_digits(x)}°"


def cell_text(ds) -> str:
    """One cell of the tables: haze and FWHM_R, rays / waves, and whether rays hold."""
    hr, hw = float(ds["haze_ray"].mean()), float(ds["haze_wave"].mean())
    fr, fw = float(ds[f"{HM}_ray"].mean()), float(ds[f"{HM}_wave"].mean())
    mark = "✓" if int(ds["rays_hold"]) else ("haze ✓" if int(ds["haze_holds"]) else "✗")
    cut = "≥" if int(ds["window_limited"]) else ""
    return f"{_pct(hr)} / {_pct(hw)} %, {_deg(fr)} / {cut}{_deg(fw)} {mark}"


def regime_table(ds, exit: str = "internal") -> list[str]:
    """Rows of geometries, columns of ΔRI: rays / waves haze and FWHM_R (half-max), ✓ where rays hold."""
    d = ds.sel(exit=exit)
    dris = [float(v) for v in ds["delta_ri"].values]
    out = ["| section | " + " | ".join(f"ΔRI {v:+g}" for v in dris) + " |",
           "|---|" + "---|" * len(dris)]
    for g in ds["geometry"].values:
        row = d.sel(geometry=g)
        out.append(f"| {g} | " + " | ".join(cell_text(row.sel(delta_ri=v)) for v in dris) + " |")
    return out


def holds_lines(ds, exit: str = "internal") -> list[str]:
    """Per section: the ΔRI values where rays hold, and where only haze does."""
    d = ds.sel(exit=exit)
    out = []
    for g in ds["geometry"].values:
        row = d.sel(geometry=g)
        both = [f"{float(v):+g}" for v in ds["delta_ri"].values if int(row["rays_hold"].sel(delta_ri=v))]
        haze = [f"{float(v):+g}" for v in ds["delta_ri"].values
                if int(row["haze_holds"].sel(delta_ri=v)) and not int(row["rays_hold"].sel(delta_ri=v))]
        out.append(f"- **{g}** ({float(row['thickness_mm']):g} mm): rays hold "
                   f"{'at ΔRI ' + ', '.join(both) if both else 'at no ΔRI of the map'}"
                   + (f"; haze alone at {', '.join(haze)}" if haze else "") + ".")
    return out


def summary_line(ds, exit: str = "internal") -> str:
    """How many cells rays hold in, and how that follows the unscattered power."""
    d = ds.sel(exit=exit)
    coh = ds["wave_coherent"].mean("realisation")
    hold, haze = d["rays_hold"].values.astype(bool), d["haze_holds"].values.astype(bool)
    n = hold.size
    gone, kept = (coh < 0.05).values, (coh > 0.9).values
    both_haze = haze & (np.abs(d["haze_ray"].mean("realisation")) > 0.05).values  # haze agrees where there is some
    resolved = ""
    if "haze_difference_ci_lower" in d:
        out_h = (d["haze_difference_ci_lower"] > HAZE_TOL) | (d["haze_difference_ci_upper"] < -HAZE_TOL)
        out_w = (d["fwhm_r_ratio_ci_lower"] > 1 + FWHM_TOL) | (d["fwhm_r_ratio_ci_upper"] < 1 - FWHM_TOL)
        resolved = (f" Of the {int((~hold).sum())} cells where they do not, {int((out_h | out_w).values[~hold].sum())} "
                    f"are resolved (the 95 % interval of the haze difference or of the FWHM_R ratio, over "
                    f"{ds.sizes['realisation']} realisations, lies wholly outside the tolerance).")
    return (f"Over the {n} cells (sections × ΔRI, angles {exit}): rays hold in {int(hold.sum())}, haze alone in "
            f"{int((haze & ~hold).sum())} more, of which {int((both_haze & ~hold).sum())} with a haze above 5 %. Where "
            f"the waves kept less than 5 % of their power unscattered ({int(gone.sum())} cells), haze agrees in "
            f"{int((haze & gone).sum())}; where they kept more than 90 % ({int(kept.sum())} cells, all haze below "
            f"{_pct(float(d['haze_wave'].mean('realisation').values[kept].max())) if kept.any() else '–'} %), haze agrees "
            f"in {int((haze & kept).sum())} but FWHM_R in {int((hold & kept).sum())}: there the waves' width is the "
            f"unscattered beam's own.{resolved}")


def compare_line(ds, geometry: str, delta_ri: float, exit: str = "internal") -> str:
    """Rays against waves for one cell, with the interval of the haze difference over realisations."""
    c = ds.sel(geometry=geometry, delta_ri=delta_ri, exit=exit)
    r = int(ds.sizes["realisation"])
    return (f"{geometry} at ΔRI {delta_ri:+g}: haze {_pct(float(c['haze_ray'].mean()))} % (rays) against "
            f"{_pct(float(c['haze_wave'].mean()))} % (waves), difference {100 * float(c['haze_difference']):+.1f} "
            f"points{_ci(c, 'haze_difference', 100.0)} over {r} realisations; FWHM_R {float(c[f'{HM}_ray'].mean()):.2f}° "
            f"against {float(c[f'{HM}_wave'].mean()):.2f}° (ratio {float(c['fwhm_r_ratio']):.2f}"
            f"{_ci(c, 'fwhm_r_ratio', fmt='.2f')}); unscattered power {_pct(float(c['wave_coherent'].mean()))} %")


def asymmetry_line(ds, geometry: str, magnitude: float) -> str | None:
    """FWHM_R at −|ΔRI| over +|ΔRI|, for rays and for waves (the ray-only explanation's test)."""
    vals = [float(v) for v in ds["delta_ri"].values]
    if magnitude not in vals or -magnitude not in vals or geometry not in ds["geometry"].values:
        return None
    c = ds.sel(geometry=geometry, exit="internal")
    ratio = {side: float(c[f"{HM}_{side}"].sel(delta_ri=-magnitude).mean()) /
             float(c[f"{HM}_{side}"].sel(delta_ri=magnitude).mean()) for side in ("ray", "wave")}
    haze = {side: (float(c[f"haze_{side}"].sel(delta_ri=-magnitude).mean()),
                   float(c[f"haze_{side}"].sel(delta_ri=magnitude).mean())) for side in ("ray", "wave")}
    return (f"{geometry}, ±{magnitude:g}: FWHM_R(−)/FWHM_R(+) {ratio['ray']:.2f} for rays, {ratio['wave']:.2f} for "
            f"waves; haze (−/+) {_pct(haze['ray'][0])} / {_pct(haze['ray'][1])} % for rays, "
            f"{_pct(haze['wave'][0])} / {_pct(haze['wave'][1])} % for waves")


def plot_regime(ds, path: Path, exit: str = "internal") -> Path:
    """Rays − waves in haze (colour, points) per section × ΔRI, each cell labelled with the FWHM_R
    ratio; a box where rays hold (haze within 2 points and FWHM_R within 10 %)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    d = ds.sel(exit=exit)
    geos = [str(g) for g in ds["geometry"].values]
    dris = [float(v) for v in ds["delta_ri"].values]
    order = np.argsort(dris)
    diff = 100 * d["haze_difference"].transpose("geometry", "delta_ri").values[:, order]
    ratio = d["fwhm_r_ratio"].transpose("geometry", "delta_ri").values[:, order]
    holds = d["rays_hold"].transpose("geometry", "delta_ri").values[:, order]
    lim = max(5.0, float(np.nanmax(np.abs(diff))))
    fig, ax = plt.subplots(figsize=(1.1 * len(dris) + 2.5, 0.55 * len(geos) + 1.6))
    im = ax.imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    fig.colorbar(im, ax=ax, label="haze, rays − waves [points]")
    for i in range(len(geos)):
        for j in range(len(dris)):
            ax.text(j, i, f"{ratio[i, j]:.2g}×" if ratio[i, j] >= 0.01 else "0×", ha="center", va="center", fontsize=7)
            if holds[i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=2.0, ec="k"))
    ax.set_xticks(range(len(dris)), [f"{dris[k]:+g}" for k in order], rotation=45, fontsize=8)
    ax.set_yticks(range(len(geos)), [f"{g} ({float(t):g} mm)" for g, t in zip(geos, ds['thickness_mm'].values)],
                  fontsize=8)
    ax.set_xlabel("ΔRI (wall − polymer)")
    ax.set_title(f"Rays against waves, angles {exit}: cell text FWHM_R rays / waves (half-max); "
                 f"boxed: within {100 * HAZE_TOL:g} points and {100 * FWHM_TOL:g} %", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_spectra(ds, geometry: str, path: Path, values=(0.002, 0.01, 0.03)) -> Path:
    """The angular distributions inside the sample, waves (power) against rays (counts), at a few ΔRI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = [v for v in values if v in [float(x) for x in ds["delta_ri"].values]]
    fig, axes = plt.subplots(1, len(values), figsize=(4.0 * len(values), 3.2), squeeze=False)
    ang = ds["angle"].values
    step = float(ang[1] - ang[0])
    for ax, v in zip(axes[0], values):
        c = ds.sel(geometry=geometry, delta_ri=v)
        for side, style in (("wave", "-"), ("ray", "--")):
            dens = c[f"distribution_{side}"].mean("realisation").values / step
            ax.semilogy(ang, np.maximum(dens, 1e-6), style, label=f"{side}s")
        ax.axvspan(-2.5, 2.5, color="0.9")
        ax.set_xlim(-30, 30)
        ax.set_ylim(1e-5, None)
        ax.set_xlabel("θ_R inside [°]")
        ax.set_title(f"{geometry}, ΔRI {v:+g} (grey: within the 2.5° haze cut)", fontsize=8)
    axes[0, 0].set_ylabel("share per degree [1/°]\n(waves: power, rays: counts)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def wave_section(results: Path, scale_dir: str = "paper", fig: str = "figures") -> list[str]:
    """The section's Markdown, or a line saying how to make its dataset."""
    from .publish import open_dataset

    path = Path(results) / scale_dir / REGIME
    L = ["## Where geometrical optics holds", ""]
    if not path.exists():
        return L + [f"No `{scale_dir}/{REGIME}`: run `make wave SCALE={scale_dir}`.", ""]
    ds = open_dataset(path)
    lam = json.loads(ds.attrs["wavelengths_nm"])
    samp = json.loads(ds.attrs["sampling"])
    bench = {}
    bench_path = Path(results) / "bench.json"
    if bench_path.exists():
        bench = json.loads(bench_path.read_text()).get("wave", {})
    L += [
        "Every number above is a ray result. Here the same sections are also solved as scalar waves "
        "(`make wave`, `studies/wave/regime.yaml`, docs/methods.md#wave-optics): the field propagates along T "
        "through the section's index map, sampled from the model's own phase, by multi-slice angular-spectrum "
        f"steps (dx {ds.attrs['dx_um']:g} µm, dz {ds.attrs['dz_um']:g} µm, each cell's wall fraction from "
        f"{samp['per_dx'] * samp['per_dz']} points); light is white ({ds.attrs['light']}: "
        f"{', '.join(f'{v:.0f}' for v in lam)} nm), in a Gaussian beam of {ds.attrs['beam_um']:g} µm at "
        f"{ds.attrs['beam_positions']} positions on each of {ds.sizes['realisation']} realisations; `exact` (version "
        f"{ds.attrs.get('tracer_version', '?')}) traces "
        f"{ds.attrs['rays_per_realisation']} rays a realisation drawn from the same beams through the same sections "
        "(uniform along L: lattices, and woods without ray cells or fibre ends, fibres straight along L). "
        "The solver is checked against analytic optics in `tests/test_wave.py`: Raman–Nath orders J_m²(φ) to "
        "2e-4, a thick grating at the Bragg angle to Kogelnik's efficiency within 1.5 %, Snell's law at a "
        "tilted interface (30°: 0.5 %, 60°: 3 %), a cylinder's exact series within 3.5 % plus the screen's "
        "1 − cos φ at angle φ; reflections are left out and estimated per case (`wave_reflected`: at most "
        f"{_pct(float(ds['wave_reflected'].max()))} % of the power, normal incidence, incoherent sum); "
        f"power lost sideways or evanescent at most {_pct(float(ds['wave_lost'].max()))} % (beyond "
        f"{100 * WINDOW_LOST:g} % only in the cells marked ≥ below). Halving dx and dz moves the map's haze and "
        "widths by less than 0.2 points and 1 % (`make bench-wave`).",
        "",
        f"Each cell: haze rays / waves, FWHM_R (half-max, the rays' estimator applied to the waves' power with "
        f"the kernel of {ds.attrs['rays_per_realisation']} rays) rays / waves, angles inside the sample; "
        f"✓ where rays hold (haze within {100 * HAZE_TOL:g} points and FWHM_R within {100 * FWHM_TOL:g} %, means "
        "over realisations), \"haze ✓\" where only haze does; ≥ marks a wave width cut by the window (more "
        f"than {100 * WINDOW_LOST:g} % of the power spread beyond {ds.attrs['keep_deg']:g}° and was absorbed at its "
        "sides, counted as haze). The finest width a wave result can show is "
        f"the beam's own: {float(ds['diffraction_limit_deg']):.2f}° (half-max, at the shortest wavelength).",
        "",
    ]
    L += regime_table(ds)
    L += ["", f"![rays against waves]({fig}/wave-regime.png)", ""]
    L += [summary_line(ds), ""]
    L += holds_lines(ds)
    L.append("")
    geos = [str(g) for g in ds["geometry"].values]
    base = "birch-1mm" if "birch-1mm" in geos else geos[-1]
    for v in (0.01, 0.002):
        if v in [float(x) for x in ds["delta_ri"].values]:
            table1 = "Table 1's base scene, " if (base, v) == ("birch-1mm", 0.01) else ""
            L.append(f"- {table1}{compare_line(ds, base, v)}.")
    for g in (base, "tubes-14.5-w2"):
        for m in (0.03, 0.01):
            line = asymmetry_line(ds, g, m)
            if line:
                L.append(f"- {line}.")
    L += ["", f"![angular distributions]({fig}/wave-spectra.png)", ""]
    if bench:
        L += [f"Cost (`make bench`, results/bench.json): {bench.get('summary', '')}", ""]
    return L


def wave_figures(results: Path, out: Path, log=print) -> list[Path]:
    """The section's figures from ``results/<scale>/wave/regime.zarr`` (``results``: a scale's folder)."""
    from .publish import open_dataset

    path = Path(results) / REGIME
    if not path.exists():
        log(f"wave figures not drawn: no {path} (run `make wave`)")
        return []
    ds = open_dataset(path)
    geos = [str(g) for g in ds["geometry"].values]
    made = [plot_regime(ds, Path(out) / "wave-regime.png"),
            plot_spectra(ds, "birch-1mm" if "birch-1mm" in geos else geos[-1], Path(out) / "wave-spectra.png")]
    for p in made:
        log(f"wrote {p}")
    return made

