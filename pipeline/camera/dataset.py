"""A camera file's outputs under ``results/camera/``: ``<file>.zarr`` (an xarray Dataset of the
images, their ideal thin-lens images and lost-sample counts), ``<file>-<image>.png`` (each image,
8-bit grey, one pixel per sensor pixel), ``<file>-<image>-object.png`` (the object) and
``<file>.png`` (a figure of the objects and the images side by side)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import __version__
from ..cache import atomic_write
from ..publish import publish_dataset
from .lens import ideal_image
from .plan import Entry, image_record
from .scene import CameraStudy
from .tasks import load_entry


def edge_widths(image: np.ndarray, pixel_um: float, *, low: float = 0.25, high: float = 0.75) -> dict:
    """Edge-spread widths along both sensor axes, from an image of the ``quadrant`` target.

    The quadrant target is dark for x < 0 and y < 0: rows below the axis cross
    one edge along x, columns left of it one edge along y.  Each edge-spread
    function is the mean of those lines away from the corner, scaled between
    its dark and light ends; its width is the distance between the ``low`` and
    ``high`` levels (25-75 %: for a Lorentzian line spread, its FWHM), in µm
    of the object plane (``pixel_um`` per pixel).
    """
    ny, nx = image.shape
    out = {}
    for name, esf in (("x", image[ny - ny // 3:, :].mean(axis=0)),
                      ("y", image[:, : nx // 3].mean(axis=1)[::-1])):
        ends = max(2, esf.size // 10)
        dark, light = esf[:ends].mean(), esf[-ends:].mean()
        level = (esf - dark) / (light - dark)
        # Robust to noise: how many pixels lie below each level.
        out[name] = float((np.sum(level < high) - np.sum(level < low)) * pixel_um)
    return out


def _png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    def write(tmp):
        Image.fromarray(np.round(np.clip(array, 0, 1) * 255).astype(np.uint8), mode="L").save(tmp, "PNG")

    atomic_write(path, write)


def _figure(study: CameraStudy, images: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(study.images)
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 5.4), squeeze=False)
    for k, (cfg, img) in enumerate(zip(study.images, images)):
        t = cfg.target
        axes[0, k].imshow(t.raster, cmap="gray", vmin=0, vmax=1,
                          extent=[-500 * t.width_mm, 500 * t.width_mm, -500 * t.height_mm, 500 * t.height_mm])
        axes[0, k].set_title(f"{cfg.name}: object", fontsize=8)
        axes[0, k].set_xlabel("µm", fontsize=7)
        axes[1, k].imshow(img, cmap="gray", vmin=0, vmax=1)
        sheet = ("no sheet" if cfg.sheet is None else
                 f"{cfg.sheet.thickness_um / 1000:g} mm, ΔRI {cfg.sheet.delta_ri:.3g}, "
                 f"gap {cfg.sheet.gap_um:g} µm")
        axes[1, k].set_title(f"f {cfg.camera.focal_mm:g} mm, {sheet}", fontsize=7)
        axes[1, k].set_xlabel("sensor pixel", fontsize=7)
        for ax in axes[:, k]:
            ax.tick_params(labelsize=6)
    cfg = study.images[0]
    fig.suptitle(f"{study.title}\nmethod {cfg.settings.method}, {cfg.camera.samples} aperture samples per pixel "
                 f"(scale {study.scale})", fontsize=9)
    fig.tight_layout()

    def write(tmp):
        fig.savefig(tmp, dpi=150, format="png")

    atomic_write(path, write)
    plt.close(fig)


def camera_dataset(study: CameraStudy, entries: list[Entry]):
    import xarray as xr

    data = [load_entry(e) for e in entries]
    cfgs = [e.config for e in entries]
    ny, nx = cfgs[0].camera.pixels  # the sensor is set once per camera file
    names = [c.name for c in cfgs]
    obj_px = np.array([c.camera.pitch_um / c.camera.magnification for c in cfgs])
    rows = np.arange(ny)
    cols = np.arange(nx)

    def per_image(values, units, long_name):
        return ("config", np.asarray(values), {"units": units, "long_name": long_name})

    def sheet_value(get):
        return [np.nan if c.sheet is None else get(c.sheet) for c in cfgs]

    ds = xr.Dataset(
        {
            "image": (("config", "row", "col"), np.stack([d["image"] for d in data]).astype(np.float32),
                      {"units": "1", "long_name": "mean object level seen by each pixel "
                       "(1 = light background, 0 = dark ink or no light)"}),
            "ideal": (("config", "row", "col"), np.stack([ideal_image(c.camera, c.target) for c in cfgs])
                      .astype(np.float32), {"units": "1", "long_name": "ideal thin-lens image of the object"}),
            "lost": (("config", "row", "col"), np.stack([d["lost"] for d in data]).astype(np.int32),
                     {"units": "1", "long_name": "aperture samples that did not reach the object"}),
            "interfaces_per_ray": per_image([float(d["interfaces_per_ray"]) for d in data], "1",
                                            "interfaces met per camera ray in the sheet"),
            "x_object_um": (("config", "col"), (cols[None, :] - 0.5 * (nx - 1)) * obj_px[:, None],
                            {"units": "um", "long_name": "object-plane x of each pixel column"}),
            "y_object_um": (("config", "row"), (0.5 * (ny - 1) - rows[None, :]) * obj_px[:, None],
                            {"units": "um", "long_name": "object-plane y of each pixel row"}),
        },
        coords={
            "config": ("config", np.array(names, dtype=object), {"long_name": "image configuration"}),
            "row": ("row", rows, {"long_name": "sensor row (image shown upright)"}),
            "col": ("col", cols, {"long_name": "sensor column"}),
            "focal_mm": per_image([c.camera.focal_mm for c in cfgs], "mm", "focal length"),
            "objective_mm": per_image([c.camera.objective_mm for c in cfgs], "mm",
                                      "lens to object plane distance"),
            "aperture_mm": per_image([c.camera.aperture_mm for c in cfgs], "mm", "aperture diameter"),
            "magnification": per_image([c.camera.magnification for c in cfgs], "1", "thin-lens magnification"),
            "gap_um": per_image(sheet_value(lambda s: s.gap_um), "um", "sheet exit face to object plane"),
            "delta_ri": per_image(sheet_value(lambda s: s.delta_ri), "1",
                                  "refractive-index difference, cell wall minus polymer (NaN: no sheet)"),
            "thickness_um": per_image(sheet_value(lambda s: s.thickness_um), "um", "sheet thickness"),
            "object": ("config", np.array([c.target.name for c in cfgs], dtype=object), {"long_name": "object"}),
            "object_size_mm": per_image([c.target.width_mm for c in cfgs], "mm", "object card width"),
        },
        attrs={
            "Conventions": "CF-1.10",
            "title": study.title,
            "source": f"twray {__version__}",
            "camera_yaml": study.text,
            "scale": study.scale,
            "samples_per_pixel": cfgs[0].camera.samples,
            "pixel_pitch_um": cfgs[0].camera.pitch_um,
            "r_axis": json.dumps({c.name: (None if c.sheet is None else c.sheet.r_axis) for c in cfgs}),
            "trace_settings": json.dumps(cfgs[0].settings.to_dict()),
            "cache_keys": json.dumps({e.config.name: e.key for e in entries}),
        },
    )
    from ..provenance import provenance_attrs

    ds.attrs.update(provenance_attrs({"camera": study.name, "scale": study.scale,
                                      "images": [image_record(c) for c in cfgs]}, study.images[0].settings.method))
    return ds


def write_outputs(study: CameraStudy, entries: list[Entry], results_dir) -> list[Path]:
    """The Dataset, one PNG per image and per object, and a figure of them all."""
    results = Path(results_dir)
    provenance = {"camera_yaml": study.text, "scale": study.scale, "source": f"twray {__version__}",
                  "cache_keys": json.dumps({e.config.name: e.key for e in entries})}
    out = [publish_dataset(lambda: camera_dataset(study, entries), results / f"{study.name}.zarr",
                           provenance)]
    images = [load_entry(e)["image"] for e in entries]
    for e, img in zip(entries, images):
        p = results / f"{study.name}-{e.config.name}.png"
        _png(p, img)
        q = results / f"{study.name}-{e.config.name}-object.png"
        _png(q, e.config.target.raster)
        out += [p, q]
    fig = results / f"{study.name}.png"
    _figure(study, images, fig)
    out.append(fig)
    return out
