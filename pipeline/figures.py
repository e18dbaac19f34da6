"""Figures of the paper's kind from the result datasets (``twray figures``, ``make figures``).

Every plotted number is read from a Dataset that ``twray study`` or ``twray
camera`` wrote (``results/paper/study-*.zarr``, ``results/paper/camera/figure5.zarr``);
the microstructure sections and the ray trajectories are computed from the
study files themselves (the wood is a function of position, so the sections
are the very wood that was traced).

Outputs (PNG, under ``results/figures/``):

* ``microstructure-<name>.png`` — every distinct Table 1 structure: R-T, L-T
  and L-R sections and a 3D view of the block they bound (the paper's Figure 3);
* ``trajectories.png`` — rays through the 1.5 mm birch sample of study 1, in
  3D and projected on the R-T and L-T planes (Figure 4a);
* ``study-<n>.png`` — FWHM_R, FWHM_L and haze with their 95 % intervals over
  the study's values (Figure 4b-g);
* ``histograms.png`` — θ_R and θ_L at 0.5 and 1.5 mm with their Lorentz fits
  (Figure S1);
* ``camera.png`` — each image beside its ideal thin-lens image, with the
  image-quality numbers (Figure 5).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from .analysis import HAZE_ANGLE_DEG, cauchy_fit, image_quality
from .cache import atomic_write
from .optics.interface import TRANSMITTED, TRAPPED
from .params import Grid, WoodParams, build_params, validate
from .publish import open_dataset
from .result_sets import TABLE1, traced_voxel_um_of, value_label

SECTION_UM = (300.0, 500.0, 600.0)  # the block the sections bound, along R, T, L [µm]
SECTION_VOXEL_UM = 0.5
DPI = 110


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=DPI, format="png"))
    _pyplot().close(fig)
    return path


# ------------------------------------------------------------------ microstructure
def structure_label(params: WoodParams, base: WoodParams) -> tuple[str, str]:
    """(file-name slug, caption) of ``params`` by how it differs from ``base``."""
    diff = {k: v for k, v in params.to_dict().items() if base.to_dict()[k] != v}
    if not diff:
        return base.species, f"{base.species} (Table 1 default)"
    words, slug = [], []
    for k, v in sorted(diff.items()):
        if isinstance(v, bool):
            words.append(f"{'with' if v else 'no'} {k.replace('_', ' ')}")
            slug.append(f"{'' if v else 'no-'}{k.replace('_', '-')}")
        elif k == "laminate":
            plies = "/".join(f"{a:g}" for a in v)
            words.append(f"laminate [{plies}]")
            slug.append("laminate")
        else:
            name = k.removesuffix("_um").replace("_", " ")
            words.append(f"{name} {v:g}{' µm' if k.endswith('_um') else ''}")
            slug.append(f"{name.replace(' ', '-')}-{v:g}")
    return "-".join(slug), f"{base.species}, " + ", ".join(words)


def wood_of(record: dict) -> WoodParams:
    """The validated wood parameters of a scene record (a Dataset's ``scenes`` attribute)."""
    w = dict(record["wood"])
    if w.get("laminate") is not None:
        w["laminate"] = tuple(w["laminate"])
    return validate(WoodParams(**w))


def scene_records(ds) -> list[dict]:
    """The scenes a study Dataset was traced from (its ``scenes`` attribute)."""
    return json.loads(ds.attrs["scenes"])


def table1_structures(datasets) -> list[tuple[str, str, WoodParams, int]]:
    """The distinct wood structures of the study ``datasets``, in order of first use:
    (slug, caption, params, seed)."""
    records = [r for ds in datasets for r in scene_records(ds)]
    base = build_params(records[0]["wood"]["species"])
    seen, out = set(), []
    for rec in records:
        wood = wood_of(rec)
        key = (repr(wood), rec["seed"])
        if key not in seen:
            seen.add(key)
            slug, caption = structure_label(wood, base)
            out.append((slug, caption, wood, int(rec["seed"])))
    return out


def sections(params: WoodParams, seed: int, *, size_um=SECTION_UM, voxel_um: float = SECTION_VOXEL_UM) -> dict:
    """The three faces of a block of the wood at the origin, as 2D arrays (1 = wall).

    ``rt``: the R-T face at L = 0 (rows R, columns T); ``lt``: the L-T face at
    the block's far R (rows T, columns L); ``lr``: the L-R face at T = 0, the
    beam's entrance face (rows R, columns L).
    """
    from .microstructure.model import generate_block

    n = [int(round(s / voxel_um)) for s in size_um]
    grid = Grid(tuple(n), voxel_um, (0.0, 0.0, 0.0))
    return {
        "rt": generate_block(params, grid, (0, 0, 0), (n[0], n[1], 1), seed=seed)[:, :, 0],
        "lt": generate_block(params, grid, (n[0] - 1, 0, 0), (1, n[1], n[2]), seed=seed)[0],
        "lr": generate_block(params, grid, (0, 0, 0), (n[0], 1, n[2]), seed=seed)[:, 0, :],
        "size_um": tuple(size_um),
    }


def _coarse(a: np.ndarray, every: int) -> np.ndarray:
    """Block means of ``a`` over every × every pixels (a wall thinner than a block stays grey)."""
    m, n = (a.shape[0] // every) * every, (a.shape[1] // every) * every
    return a[:m, :n].reshape(m // every, every, n // every, every).mean(axis=(1, 3))


def _cube(ax, sec: dict, *, every: int = 5) -> None:
    """The block's three visible faces, each textured with its section (walls dark)."""
    R, T, L = sec["size_um"]
    rt, lt, lr = (_coarse(sec[k].astype(float), every) for k in ("rt", "lt", "lr"))
    grey = lambda a: np.repeat((0.95 - 0.8 * a)[..., None], 3, axis=2)
    r = np.linspace(0, R, rt.shape[0])
    t = np.linspace(0, T, rt.shape[1])
    l_ = np.linspace(0, L, lr.shape[1])
    kw = dict(rstride=1, cstride=1, shade=False, linewidth=0, antialiased=False)
    # Axes of the plot: x = L, y = R, z = T (the beam travels down through the block).
    gr, gt = np.meshgrid(r, t, indexing="ij")
    ax.plot_surface(np.zeros_like(gr), gr, -gt, facecolors=grey(rt), **kw)
    gt2, gl = np.meshgrid(t, l_, indexing="ij")
    ax.plot_surface(gl, np.full_like(gl, R), -gt2, facecolors=grey(lt), **kw)
    gr3, gl3 = np.meshgrid(r, l_, indexing="ij")
    ax.plot_surface(gl3, gr3, np.zeros_like(gl3), facecolors=grey(lr), **kw)
    ax.set_xlabel("L (µm)", fontsize=7, labelpad=-2)
    ax.set_ylabel("R (µm)", fontsize=7, labelpad=-2)
    ax.set_zlabel("−T (µm)", fontsize=7, labelpad=-2)
    ax.tick_params(labelsize=5, pad=0)
    ax.set_box_aspect((L, R, T))
    ax.set_yticks([0, R / 2, R])  # the short axis: three ticks, not crowded
    ax.view_init(elev=24, azim=-58)


def plot_microstructure(sec: dict, caption: str, path: Path) -> Path:
    plt = _pyplot()
    R, T, L = sec["size_um"]
    fig = plt.figure(figsize=(12, 3.3))
    widths = [T, L, L, 1.25 * L]
    gs = fig.add_gridspec(1, 4, width_ratios=widths, wspace=0.25)
    panels = [("R-T section (L = 0)", sec["rt"], [0, T, R, 0], "T (µm)", "R (µm)"),
              (f"L-T section (R = {R:g} µm)", sec["lt"], [0, L, T, 0], "L (µm)", "T (µm)"),
              ("L-R section (T = 0, entrance face)", sec["lr"], [0, L, R, 0], "L (µm)", "R (µm)")]
    for k, (title, img, extent, xl, yl) in enumerate(panels):
        ax = fig.add_subplot(gs[0, k])
        ax.imshow(img, cmap="gray_r", vmin=0, vmax=1.4, extent=extent, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(xl, fontsize=7)
        ax.set_ylabel(yl, fontsize=7)
        ax.tick_params(labelsize=6)
    ax = fig.add_subplot(gs[0, 3], projection="3d")
    _cube(ax, sec)
    ax.set_title("3D view", fontsize=8)
    fig.suptitle(f"{caption} — walls dark, polymer light, {SECTION_VOXEL_UM:g} µm voxels", fontsize=9)
    fig.subplots_adjust(left=0.04, right=0.99, top=0.86, bottom=0.13)
    return _save(fig, path)


# ------------------------------------------------------------------ trajectories
def trajectories(record: dict, *, n_rays: int = 16, every: int = 3, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Paths of ``n_rays`` rays of a scene's beam through its sample [µm].

    ``record`` is a scene record (a study Dataset's ``scenes`` attribute).  The
    tracer keeps no path; a ray stopped by the event cap ``max_events = k``
    stands at its k-th interface, so tracing with k = every, 2·every, … gives
    corners of the path (between interfaces a ray is straight).

    Returns (points, status): points of shape (n_rays, K, 3) along [R, T, L],
    the last row of each ray repeated once it has left; status the final one.
    """
    from .optics.media import wood_medium
    from .optics.rays import square_beam
    from .optics.settings import Optics, TraceSettings
    from .optics.trace import trace

    settings = TraceSettings.from_dict(record["settings"]).validate()
    medium = wood_medium(wood_of(record), seed=record["seed"], thickness_um=record["thickness_um"],
                         voxel_um=record["voxel_um"], settings=settings, threads=os.cpu_count() or 1)
    beam = square_beam(n_rays, record["beam_um"], seed=seed)
    optics = Optics.of_delta(record["ri_polymer"], record["delta_ri"], seed=record["seed"])
    full = trace(medium, beam, optics, settings)
    points = [beam.origins.copy()]
    for k in range(every, int(full.events.max()) + every, every):
        part = trace(medium, beam, optics, dataclasses.replace(settings, max_events=k))
        points.append(np.where((part.status == TRAPPED)[:, None], part.position, full.position))
    points.append(full.position)
    return np.stack(points, axis=1), full.status


def plot_trajectories(points: np.ndarray, status: np.ndarray, caption: str, path: Path) -> Path:
    plt = _pyplot()
    fig = plt.figure(figsize=(11, 4.2))
    gs = fig.add_gridspec(1, 3, width_ratios=[1.5, 1, 1], wspace=0.3)
    ax3 = fig.add_subplot(gs[0, 0], projection="3d")
    axr = fig.add_subplot(gs[0, 1])
    axl = fig.add_subplot(gs[0, 2])
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(points)))
    for p, c, st in zip(points, colours, status):
        r, t, l_ = p[:, 0], p[:, 1] / 1000.0, p[:, 2]
        ls = "-" if st == TRANSMITTED else ":"
        ax3.plot(l_, r, t, color=c, lw=0.8, ls=ls)
        axr.plot(r, t, color=c, lw=0.8, ls=ls)
        axl.plot(l_, t, color=c, lw=0.8, ls=ls)
    ax3.set_xlabel("L (µm)", fontsize=7)
    ax3.set_ylabel("R (µm)", fontsize=7)
    ax3.set_zlabel("T (mm)", fontsize=7)
    ax3.invert_zaxis()
    ax3.tick_params(labelsize=6)
    ax3.set_title("3D (lateral axes stretched)", fontsize=8)
    for ax, xl, title in ((axr, "R (µm)", "projection on the R-T plane"),
                          (axl, "L (µm)", "projection on the L-T plane")):
        ax.set_xlabel(xl, fontsize=7)
        ax.set_ylabel("T (mm), depth in the sample", fontsize=7)
        ax.invert_yaxis()
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=6)
    fig.suptitle(caption, fontsize=9)
    fig.subplots_adjust(left=0.02, right=0.98, top=0.86, bottom=0.12)
    return _save(fig, path)


# ------------------------------------------------------------------ studies
def _value_labels(ds, dim: str) -> list[str]:
    return [value_label(v) for v in ds[dim].values]


def plot_study(ds, path: Path) -> Path:
    """FWHM_R, FWHM_L and haze with their 95 % intervals over the study's values."""
    plt = _pyplot()
    dim = next(iter(ds["FWHM_R"].dims))
    labels = _value_labels(ds, dim)
    x = np.arange(len(labels))
    units = {"um": "µm"}.get(ds[dim].attrs.get("units", ""), ds[dim].attrs.get("units", ""))
    # A wood parameter's long_name is its key in words ("wall thickness um"): the unit goes in brackets.
    name = ds[dim].attrs.get("long_name", dim).removesuffix(" um")
    xlabel = name + (f" ({units})" if units and units != "1" else "")
    fig, axes = plt.subplots(1, 3, figsize=(10, 3.2))
    est = ds.attrs.get("fwhm_estimator", "lorentz-mle")  # Datasets before summary version 5: the Lorentz ML fit
    for ax, (var, scale, ylabel, colour) in zip(axes, (
            ("FWHM_R", 1.0, f"FWHM_R, {est} (°)", "#3b6ea8"),
            ("FWHM_L", 1.0, f"FWHM_L, {est} (°)", "#c0703a"),
            ("haze", 100.0, f"haze (%, > {HAZE_ANGLE_DEG:g}°)", "#5a9a5a"))):
        y = ds[var].values * scale
        lo = ds[f"{var}_ci_lower"].values * scale
        hi = ds[f"{var}_ci_upper"].values * scale
        ax.bar(x, y, color=colour, width=0.65)
        ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="none", ecolor="black", capsize=3, lw=0.9)
        each = f"{var}_per_realisation"
        if each in ds and ds.sizes.get("realisation", 1) > 1:  # each wood's own value
            v = ds[each].transpose(dim, "realisation").values * scale
            offsets = np.linspace(-0.2, 0.2, v.shape[1])
            ax.scatter((x[:, None] + offsets[None, :]).ravel(), v.ravel(), s=7, color="white",
                       edgecolors="black", linewidths=0.5, zorder=3)
        ax.set_xticks(x, labels, fontsize=7, rotation=30 if max(len(s) for s in labels) > 6 else 0)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.tick_params(labelsize=7)
    fig.supxlabel(xlabel, fontsize=8)
    n_real = ds.sizes.get("realisation", 1)
    fig.suptitle(f"{ds.attrs['title']} — {ds.attrs['rays']} rays × {n_real} wood realisation"
                 f"{'' if n_real == 1 else 's'}, method {_settings(ds)['method']}\npooled, 95 % intervals "
                 f"{'with' if n_real > 1 else 'without'} the wood-to-wood variation"
                 f"{'; dots: each wood' if n_real > 1 else ''}", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _settings(ds) -> dict:
    return json.loads(ds.attrs["trace_settings"])


def plot_histograms(ds, thicknesses, path: Path) -> Path:
    """θ_R and θ_L of the transmitted rays with the fitted Lorentz density (study 1's Dataset)."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(thicknesses), 2, figsize=(9, 3.0 * len(thicknesses)), squeeze=False)
    for i, th in enumerate(thicknesses):
        one = ds.sel(thickness=th)
        ok = one["status"].values == TRANSMITTED
        for j, (var, fw) in enumerate((("theta_r", "FWHM_R"), ("theta_l", "FWHM_L"))):
            ax = axes[i, j]
            theta = one[var].values[ok]
            loc, gamma = cauchy_fit(theta)
            span = max(4.0 * float(one[fw]), 1.0)
            bins = np.linspace(loc - span, loc + span, 61)
            # Density over all transmitted rays, so that it compares with the fitted density
            # (rays beyond the plotted range count in the total).
            width = bins[1] - bins[0]
            outside = int(np.sum((theta < bins[0]) | (theta > bins[-1])))
            ax.hist(theta, bins=bins, weights=np.full(theta.size, 1.0 / (theta.size * width)),
                    color="#9bb7d4", edgecolor="none", label=f"{theta.size} rays ({outside} beyond the axis)")
            grid = np.linspace(bins[0], bins[-1], 400)
            ax.plot(grid, gamma / (math.pi * ((grid - loc) ** 2 + gamma ** 2)), color="#b03030", lw=1.2,
                    label=f"Lorentz maximum-likelihood fit, 2γ {2 * gamma:.2f}°")
            if f"{fw}_half_max" in one:  # the distribution's own width at half its maximum (Table 1's FWHM)
                counts, _ = np.histogram(theta, bins=bins)
                peak = counts.max() / (theta.size * width)
                half = float(one[f"{fw}_half_max"])
                ax.hlines(peak / 2, loc - half / 2, loc + half / 2, color="#202020", lw=1.2,
                          label=f"width at half maximum {half:.2f}°")
            name = "θ_R" if var == "theta_r" else "θ_L"
            ax.set_xlabel(f"{name} (°)", fontsize=8)
            ax.set_ylabel("density (1/°)", fontsize=8)
            ax.set_title(f"{th:g} mm: {name}", fontsize=8)
            ax.legend(fontsize=6, frameon=False, loc="upper left")
            ax.tick_params(labelsize=7)
    fig.suptitle(f"Exit angles, their width at half maximum and Lorentz fits ({ds.attrs['title']})", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


# ------------------------------------------------------------------ camera
def plot_camera(ds, path: Path) -> Path:
    """Each rendered image beside its ideal thin-lens image, with its quality numbers."""
    plt = _pyplot()
    configs = [str(c) for c in ds["config"].values]
    fig, axes = plt.subplots(2, len(configs), figsize=(2.7 * len(configs), 6.4), squeeze=False)
    r_axis = json.loads(ds.attrs.get("r_axis", "{}"))
    for k, name in enumerate(configs):
        one = ds.sel(config=name)
        q = image_quality(one["image"].values, one["ideal"].values)
        # Object-plane coordinates of the pixels [µm]: the images are shown upright at object scale.
        x, y = one["x_object_um"].values, one["y_object_um"].values
        half_x, half_y = (x[1] - x[0]) / 2, (y[0] - y[1]) / 2
        extent = [x[0] - half_x, x[-1] + half_x, y[-1] - half_y, y[0] + half_y]
        axes[0, k].imshow(one["ideal"].values, cmap="gray", vmin=0, vmax=1, extent=extent)
        axes[0, k].set_title(f"{name}: ideal thin-lens image\nf {float(one['focal_mm']):g} mm, "
                             f"magnification {float(one['magnification']):.3g}", fontsize=7)
        axes[1, k].imshow(one["image"].values, cmap="gray", vmin=0, vmax=1, extent=extent)
        dri = float(one["delta_ri"])
        axes[1, k].set_title(f"through {float(one['thickness_um']) / 1000:g} mm, ΔRI {dri:.3g}, "
                             f"gap {float(one['gap_um']):g} µm\ncontrast {q['contrast']:.2f}, "
                             f"RMS error {q['rmse']:.3f}", fontsize=7)
        along = {"x": "x", "y": "y"}.get(r_axis.get(name) or "", None)
        axes[1, k].set_xlabel("x (µm, object plane)" + (f"; wood R along {along}" if along else ""), fontsize=6)
        for ax in axes[:, k]:
            ax.tick_params(labelsize=6)
        axes[0, k].set_ylabel("y (µm)", fontsize=6)
        axes[1, k].set_ylabel("y (µm)", fontsize=6)
    fig.suptitle(f"{ds.attrs['title']} ({ds.attrs['samples_per_pixel']} aperture samples per pixel, "
                 f"traced with {ds.attrs.get('tracing_method', 'fast')})",
                 fontsize=9)
    fig.tight_layout(h_pad=2.0)
    return _save(fig, path)


# ------------------------------------------------------------------ all of them
def make_figures(results: Path, out: Path, *, which: set[str] | None = None, log=print) -> list[Path]:
    """Every figure from the datasets under ``results`` (a scale's folder) into ``out``.

    ``which`` limits the work to some of ``{"microstructure", "trajectories",
    "studies", "histograms", "camera", "design", "wave"}`` (the design maps are drawn when all of
    results/design/ is there, the wave figures when results/wave/regime.zarr is).
    """
    results, out = Path(results), Path(out)
    which = which or {"microstructure", "trajectories", "studies", "histograms", "camera", "design", "wave"}
    need = TABLE1 if which & {"microstructure", "studies"} else (
        ("study-1",) if which & {"histograms", "trajectories"} else ())
    datasets = {name: open_dataset(results / f"{name}.zarr") for name in need}
    made = []
    if "microstructure" in which:
        for slug, caption, params, seed in table1_structures(list(datasets.values())):
            made.append(plot_microstructure(sections(params, seed), caption, out / f"microstructure-{slug}.png"))
            log(f"wrote {made[-1]}")
    if "studies" in which:
        for name, ds in datasets.items():
            made.append(plot_study(ds, out / f"{name}.png"))
            log(f"wrote {made[-1]}")
    if "histograms" in which:
        ds = datasets["study-1"]
        pick = [th for th in (0.5, 1.5) if th in ds["thickness"].values] or list(ds["thickness"].values[[0, -1]])
        made.append(plot_histograms(ds, pick, out / "histograms.png"))
        log(f"wrote {made[-1]}")
    if "trajectories" in which:
        ds = datasets["study-1"]
        rec = max(scene_records(ds), key=lambda r: r["thickness_um"])
        points, status = trajectories(rec)
        grid = "" if rec["settings"].get("voxel", {}) is None else f", {traced_voxel_um_of(rec):g} µm voxels"
        caption = (f"{len(points)} rays through {rec['thickness_um'] / 1000:g} mm of birch TW "
                   f"(ΔRI {rec['delta_ri']:g}, method {rec['settings']['method']}{grid}), "
                   f"the thickest sample of {ds.attrs['title']}")
        made.append(plot_trajectories(points, status, caption, out / "trajectories.png"))
        log(f"wrote {made[-1]}")
    if "camera" in which:
        made.append(plot_camera(open_dataset(results / "camera" / "figure5.zarr"), out / "camera.png"))
        log(f"wrote {made[-1]}")
    if "design" in which:
        from .design import MAPS, plot_maps, plot_windows

        paths = {name: results / "design" / f"{name}.zarr" for name in MAPS}
        if all(p.exists() for p in paths.values()):
            maps = {name: open_dataset(p) for name, p in paths.items()}
            regime_path = results / "wave" / "regime.zarr"  # rays against waves: marks where rays were measured
            regime = open_dataset(regime_path) if regime_path.exists() else None
            made.append(plot_maps(maps, out / "design-maps.png", regime))
            log(f"wrote {made[-1]}")
            made.append(plot_windows(maps, out / "design-windows.png"))
            log(f"wrote {made[-1]}")
        else:
            log(f"design maps not drawn: {results / 'design'} lacks some of {', '.join(MAPS)} (run `make design`)")
    if "wave" in which:
        from .report_wave import wave_figures

        made += wave_figures(results, out, log=log)
    return made


