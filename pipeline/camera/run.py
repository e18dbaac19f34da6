"""Render the images of a camera file as a cached Dask graph (docs/methods.md#virtual-camera).

Each image is split into blocks of sensor rows, one task each; the tasks of
all images run on one ``distributed.Client``.  The sheet's wood comes from
the same content-addressed chunk store as the studies'
(``cache/micro/<key>.zarr``, see :func:`pipeline.microstructure.store.wood_store`), so
only the chunks that camera rays visit are generated, once, and a sheet of
the Table 1 base wood reuses the chunks the studies made.  A finished image
is a cache entry ``cache/camera/<key>.npz`` whose key hashes the camera, the
sheet, the object raster and the trace settings, verified when read
(:mod:`pipeline.cache`); a rerun renders nothing.  Until its image is
whole, each finished block of rows is an entry ``cache/camera-rows/<key>.npz``
(the image's record and the rows): a run that stops part-way keeps them, the
next renders only the rest, and the image, once written, replaces them.

Outputs under ``results/camera/``: ``<file>.zarr`` (an xarray Dataset of the
images, their ideal thin-lens images and lost-sample counts),
``<file>-<image>.png`` (each image, 8-bit grey, one pixel per sensor
pixel), ``<file>-<image>-object.png`` (the object) and ``<file>.png`` (a
figure of the objects and the images side by side).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..runlog import task
from ..cache import DamagedEntry, atomic_write, cache_key, check_npz, read_npz, sound, write_npz
from .. import versions
from ..microstructure.store import wood_record, wood_store
from ..optics.settings import traced_voxel_um
from ..publish import publish_dataset
from .lens import RowsImage, ideal_image, render_rows
from .scene import CameraStudy, ImageConfig

ROWS_PER_TASK = 3
ROWS_STAGE = "camera-rows"  # the cache folder of an unfinished image's row blocks


@dataclass
class Entry:
    config: ImageConfig
    key: str
    path: Path
    cached: bool


def image_record(cfg: ImageConfig) -> dict:
    """What an image depends on (its cache key)."""
    sheet = None
    if cfg.sheet is not None:
        sheet = dataclasses.asdict(cfg.sheet)
        sheet["wood"] = cfg.sheet.wood.key_dict()
        if cfg.settings.medium_kind == "voxels":  # the chunks it reads
            sheet["micro"] = wood_record(cfg.sheet.wood, cfg.sheet.seed,
                                         traced_voxel_um(cfg.sheet.voxel_um, cfg.settings))
    return {"stage": "camera", "version": versions.CAMERA, "tracer": versions.tracer(cfg.settings.method),
            "camera": dataclasses.asdict(cfg.camera),
            "sheet": sheet, "object": cfg.target.digest(), "settings": cfg.settings.to_dict()}


@dataclass
class Block:
    """Sensor rows [lo, hi) of one image, and their cache entry."""
    lo: int
    hi: int
    key: str
    path: Path
    cached: bool


def block_record(cfg: ImageConfig, lo: int, hi: int) -> dict:
    """What a block of rows depends on: its image and its rows."""
    return {"image": image_record(cfg), "rows": [int(lo), int(hi)]}


def plan_blocks(entry: Entry, cache_dir, rows_per_task: int = ROWS_PER_TASK) -> list[Block]:
    """The row blocks of ``entry``'s image, each cached or to render."""
    ny = entry.config.camera.pixels[0]
    out = []
    for lo in range(0, ny, rows_per_task):
        hi = min(lo + rows_per_task, ny)
        key = cache_key(block_record(entry.config, lo, hi))
        path = Path(cache_dir) / ROWS_STAGE / f"{key}.npz"
        out.append(Block(lo, hi, key, path, sound(check_npz, path, key)))
    return out


def plan_camera(study: CameraStudy, cache_dir) -> list[Entry]:
    out = []
    for cfg in study.images:
        key = cache_key(image_record(cfg))
        path = Path(cache_dir) / "camera" / f"{key}.npz"
        out.append(Entry(cfg, key, path, sound(check_npz, path, key)))
    return out


# ---------------------------------------------------------------------- tasks (run on workers)
@task
def render_block(cfg: ImageConfig, lo: int, hi: int, cache_dir: str, path: str) -> RowsImage:
    """Sensor rows [lo, hi) of one image, kept at ``path`` until the image is whole."""
    from ..optics.media import wood_medium

    medium = None
    sh = cfg.sheet
    if sh is not None:
        store = None
        if cfg.settings.medium_kind == "voxels":
            store = wood_store(cache_dir, sh.wood, sh.seed, traced_voxel_um(sh.voxel_um, cfg.settings))
        medium = wood_medium(sh.wood, seed=sh.seed, thickness_um=sh.thickness_um, voxel_um=sh.voxel_um,
                             settings=cfg.settings, store=store)
    rows = render_rows(cfg.camera, sh, cfg.target, np.arange(lo, hi), settings=cfg.settings, medium=medium)
    write_npz(Path(path), block_record(cfg, lo, hi),
              {"image": rows.image, "lost": rows.lost, "interfaces": np.float64(rows.interfaces),
               "chunks_loaded": np.int64(rows.chunks_loaded)})
    return rows


@task
def load_block(path: str, key: str, lo: int, hi: int) -> RowsImage:
    """A block of rows an earlier run rendered."""
    arrays = read_npz(Path(path), key)
    if arrays is None:
        raise DamagedEntry(f"cache entry {path} was damaged during the run; run again to recompute it")
    return RowsImage(np.arange(lo, hi), arrays["image"], arrays["lost"], float(arrays["interfaces"]),
                     int(arrays["chunks_loaded"]))


@task
def assemble(cfg: ImageConfig, path: str, block_paths: list, *blocks: RowsImage) -> dict:
    """Join the row blocks of an image, store it (atomically) as a cache entry, and remove the
    blocks' own entries (the image holds them)."""
    image = np.concatenate([b.image for b in blocks])
    lost = np.concatenate([b.lost for b in blocks])
    rays = image.size * cfg.camera.samples
    arrays = {"image": image, "lost": lost,
              "interfaces_per_ray": np.float64(sum(b.interfaces for b in blocks) / rays),
              "chunks_loaded": np.int64(sum(b.chunks_loaded for b in blocks))}
    write_npz(Path(path), image_record(cfg), arrays)
    for p in block_paths:
        Path(p).unlink(missing_ok=True)
    return {"rays": rays, "chunks_loaded": int(arrays["chunks_loaded"])}


def compute(entries: list[Entry], client, cache_dir, *, rows_per_task: int = ROWS_PER_TASK,
            progress: str = "off") -> dict:
    """Render every image of ``entries`` that is not cached, on a ``distributed.Client``: the
    row blocks an earlier run finished are read, the others rendered.

    Returns counts: images assembled, row blocks rendered and read, camera rays traced."""
    import dask

    tasks = []
    report = {"images": 0, "row_tasks": 0, "rows_cached": 0, "rays": 0}
    labels = {}
    for e in entries:
        if e.cached:
            continue
        labels[f"camera-image-{e.key[:12]}"] = labels[f"camera-config-{e.key[:12]}"] = f"camera image {e.config.name}"
        cfg = dask.delayed(e.config, name=f"camera-config-{e.key[:12]}", traverse=False)
        blocks = []
        plan = plan_blocks(e, cache_dir, rows_per_task)
        for b in plan:
            name = f"camera-rows-{e.key[:12]}-{b.lo}"
            labels[name] = f"camera image {e.config.name}, rows {b.lo}-{b.hi}"
            if b.cached:
                blocks.append(dask.delayed(load_block, pure=False)(str(b.path), b.key, b.lo, b.hi, dask_key_name=name))
                report["rows_cached"] += 1
            else:
                blocks.append(dask.delayed(render_block, pure=False)(cfg, b.lo, b.hi, str(cache_dir), str(b.path),
                                                                     dask_key_name=name))
                report["row_tasks"] += 1
                report["rays"] += (b.hi - b.lo) * e.config.camera.pixels[1] * e.config.camera.samples
        tasks.append(dask.delayed(assemble, pure=False)(
            cfg, str(e.path), [str(b.path) for b in plan], *blocks, dask_key_name=f"camera-image-{e.key[:12]}"))
    report["images"] = len(tasks)
    if not tasks:
        return report
    from ..progress import graph_keys
    from ..runlog import gather_graph

    futures = client.compute(tasks)
    gather_graph(client, futures, graph_keys(tasks), "twray camera", progress, labels)
    return report


# ---------------------------------------------------------------------- outputs
def load_entry(e: Entry) -> dict:
    arrays = read_npz(e.path, e.key)
    if arrays is None:
        raise DamagedEntry(f"cache entry {e.path} was damaged during the run; run again to recompute it")
    return arrays


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
                 f"{cfg.sheet.thickness_um / 1000:g} mm, ΔRI {cfg.sheet.ri_wall - cfg.sheet.ri_polymer:.3g}, "
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
            "delta_ri": per_image(sheet_value(lambda s: s.ri_wall - s.ri_polymer), "1",
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
