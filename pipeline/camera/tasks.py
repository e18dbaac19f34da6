"""The camera's graph tasks: a block of sensor rows rendered (or read back from an earlier run),
and an image assembled from its blocks.  The sheet's wood comes from the same content-addressed
chunk store as the studies' (``cache/micro/<key>.zarr``, see
:func:`pipeline.microstructure.store.wood_store`), so only the chunks that camera rays visit are
generated, once."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cache import DamagedEntry, read_npz, write_npz
from ..microstructure.store import wood_store
from ..optics.settings import traced_voxel_um
from ..runlog import task
from .lens import RowsImage, render_rows
from .plan import Entry, block_record, image_record
from .scene import ImageConfig


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


# ---------------------------------------------------------------------- outputs
def load_entry(e: Entry) -> dict:
    arrays = read_npz(e.path, e.key)
    if arrays is None:
        raise DamagedEntry(f"cache entry {e.path} was damaged during the run; run again to recompute it")
    return arrays
