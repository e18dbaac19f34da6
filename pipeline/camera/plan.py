"""A camera file's images planned against the cache (docs/methods.md#virtual-camera).

Each image is split into blocks of sensor rows.  A finished image is a cache
entry ``cache/camera/<key>.npz`` whose key hashes the camera, the sheet, the
object raster and the trace settings, verified when read
(:mod:`pipeline.cache`); a rerun renders nothing.  Until its image is whole,
each finished block of rows is an entry ``cache/camera-rows/<key>.npz`` (the
image's record and the rows): a run that stops part-way keeps them, the next
renders only the rest, and the image, once written, replaces them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from .. import versions
from ..cache import cache_key, check_npz, sound
from ..microstructure.store import wood_record
from ..optics.settings import traced_voxel_um
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
        # The key holds the two indices the trace uses, not the file's spelling of them.
        optics = cfg.sheet.optics
        del sheet["delta_ri"]
        sheet["ri_wall"], sheet["ri_polymer"] = optics.n_wall, optics.n_poly
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
