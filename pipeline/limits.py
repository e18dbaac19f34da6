"""Estimates of what a command costs, checked before any work starts.

Every command that generates or traces estimates from its inputs the CPU
time, the memory and the disk it needs (rates measured by ``make bench`` on
2-core machines, rounded towards the slow side).  What cannot fit this
machine's memory or the free disk is refused with the estimate in the
message; what would take longer than ``TWRAY_CONFIRM_CPU_HOURS`` (default 2
CPU-hours) runs only with ``--yes``.  The estimates are meant to be right
within a factor of a few, which is what telling "seconds" from "a month"
needs.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from .optics.settings import METHODS
from .params import ParameterError

CONFIRM_ENV = "TWRAY_CONFIRM_CPU_HOURS"
CONFIRM_DEFAULT_H = 2.0
GENERATE_VOXELS_PER_CPU_S = 15e6  # birch 40-140 M/s, balsa 16 M/s (results/bench.json)
DISK_BYTES_PER_VOXEL = 0.01  # zstd chunks of birch: 0.0055 B a voxel
MEMORY_BYTES_PER_WOOD_VOXEL = 0.2  # chunks the tracer keeps bit-packed, and the chunk cache
RAY_BYTES = 512  # a ray's state, result and beam entry in one trace
DATASET_RAY_BYTES = 24  # theta_r, theta_l, interfaces and status of a ray in a result Dataset
BASE_MEMORY = 1 << 30  # the interpreter, compiled kernels and the chunk cache
INTERFACE_CPU_S = {"paper": 1.2e-3, "fast": 3e-6, "accurate": 5e-6,
                   # exact: no wood generated; ~130 µs an interface, plus REGION_CPU_S a trace (measured
                   # by tests/test_limits.py, within 1.5x; 2 mm at ΔRI < 0 takes up to 2x: regions widen)
                   "exact": 1.3e-4}
REGION_CPU_S = 0.9  # exact: building the region of generated wood around a beam, once a trace (a shard)
INTERFACES_PER_PITCH = 2.0  # interfaces met per cell pitch crossed (birch 1.6-1.8, balsa 2.3: two walls and more)
# What a study writes besides its wood (measured by tests/test_limits.py): per shard of rays an .npz
# (headers and its record, then 120 B a ray), per wood and value a summary and per value a pool
# (JSON, under 1 kB each), per study a Dataset (75 kB of metadata and numbers, then per ray
# DATASET_RAY_BYTES; Table 1's compress to 17 B a ray).
SHARD_BYTES, SHARD_RAY_BYTES, ENTRY_BYTES, DATASET_BYTES = 7e3, 120.0, 800.0, 75e3
SPREAD = 2.0  # chunks generated around the beam's column by spreading rays, as a factor
CHUNK = 64  # voxels along a chunk edge in the study cache
SHOW_ESTIMATE_S = 60.0  # commands estimated above this many CPU-seconds print their estimate first


@dataclass
class Estimate:
    cpu_s: float = 0.0
    memory: float = 0.0  # peak bytes in one process
    disk: float = 0.0

    def __add__(self, other: "Estimate") -> "Estimate":
        return Estimate(self.cpu_s + other.cpu_s, max(self.memory, other.memory), self.disk + other.disk)

    def text(self) -> str:
        return f"~{hours(self.cpu_s)} of CPU, {size(self.memory)} of memory, {size(self.disk)} of disk"


def hours(cpu_s: float) -> str:
    if cpu_s < 120:
        return f"{cpu_s:.0f} CPU-s"
    if cpu_s < 7200:
        return f"{cpu_s / 60:.0f} CPU-min"
    return f"{cpu_s / 3600:.3g} CPU-h"


def size(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} PB"


def machine_memory() -> int:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 40


def free_disk(path) -> int:
    path = Path(path).absolute()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free


def confirm_hours() -> float:
    text = os.environ.get(CONFIRM_ENV, str(CONFIRM_DEFAULT_H))
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise ParameterError(f"`{CONFIRM_ENV}` must be a number of CPU-hours >= 0, got {text!r}")
    return value


def check(est: Estimate, *, what: str, yes: bool, disk_path=None, fit: str = "") -> None:
    """Refuse ``what`` if ``est`` cannot fit this machine, or needs ``--yes`` and has not got it."""
    hint = f"; {fit}" if fit else ""
    memory = machine_memory()
    if not est.memory <= 0.8 * memory:
        raise ParameterError(f"{what} needs {est.text()}: more memory than this machine's "
                             f"{size(memory)}{hint}")
    if disk_path is not None and not est.disk <= free_disk(disk_path):
        raise ParameterError(f"{what} needs {est.text()}: more disk than the {size(free_disk(disk_path))} free "
                             f"under {disk_path}{hint}")
    if not yes and not est.cpu_s <= confirm_hours() * 3600:
        raise ParameterError(f"{what} needs {est.text()}, above {CONFIRM_ENV}={confirm_hours():g} CPU-hours: "
                             f"add --yes (with make: YES=1) to run it{hint}")


def wood_voxels(beam_um: float, thickness_um: float, voxel_um: float) -> float:
    """Voxels of wood a beam of ``beam_um`` traced through ``thickness_um`` generates."""
    side = math.ceil((beam_um / voxel_um + 16) / CHUNK) * CHUNK
    depth = math.ceil(thickness_um / voxel_um / CHUNK) * CHUNK
    return SPREAD * side * side * depth


def surface_region_bytes(beam_um: float, thickness_um: float, pitch_um: float) -> float:
    """Memory of what ``exact`` builds for generated wood around a beam: the distortion grid (2
    doubles every pitch/16 in R and T, held as tiles, as the region's patch and its padded copy)
    over the beam, its margins and a rotated ply's diagonal (docs/methods.md#the-exact-method)."""
    from .optics.wood_surface import FIRST_MARGIN_UM

    grid = pitch_um / 16.0
    side = math.sqrt(2.0) * (beam_um + 2.0 * (FIRST_MARGIN_UM + 0.05 * thickness_um)) + 2.0
    return 3.0 * 16.0 * (side / grid + 2) * ((thickness_um + 2.0) / grid + 2)


def trace_estimate(*, rays: int, beam_um: float, thickness_um: float, voxel_um: float, pitch_um: float,
                   method: str, wood: bool = True, store: bool = False, generated: bool = True) -> Estimate:
    """One beam traced in one process (``wood``: generated as rays reach it; ``store``: kept on disk;
    ``generated``: the model's wood, not a reference lattice)."""
    interfaces = rays * INTERFACES_PER_PITCH * thickness_um / pitch_um
    voxels = wood_voxels(beam_um, thickness_um, voxel_um) if wood and METHODS[method] == "voxels" else 0.0
    cpu = interfaces * INTERFACE_CPU_S.get(method, INTERFACE_CPU_S["accurate"]) + voxels / GENERATE_VOXELS_PER_CPU_S
    memory = BASE_MEMORY + rays * RAY_BYTES + (0 if store else voxels * MEMORY_BYTES_PER_WOOD_VOXEL)
    if generated and METHODS.get(method) == "surfaces":
        memory += surface_region_bytes(beam_um, thickness_um, pitch_um)
        cpu += REGION_CPU_S
    return Estimate(cpu, memory, voxels * DISK_BYTES_PER_VOXEL if store else 0.0)


def study_estimate(scenes, *, shard_rays: int) -> Estimate:
    """A study's scenes: each wood generated once (on disk), each scene's rays traced by shards and
    written with their summaries, pools and one Dataset."""
    est = Estimate()
    woods = {}
    for s in scenes:
        if s.target is not None:  # traced to a precision: at most its cap of rays
            s = dataclasses.replace(s, rays=s.target.max_rays)
        voxel = s.trace_voxel_um
        if s.settings.medium_kind == "voxels" and s.wood is not None:  # surfaces and lattices store no wood
            key = (repr(s.wood), s.seed, voxel)
            woods[key] = max(woods.get(key, 0.0), wood_voxels(s.beam_um, s.thickness_um, voxel))
        shard = trace_estimate(rays=min(s.rays, shard_rays), beam_um=s.beam_um, thickness_um=s.thickness_um,
                               voxel_um=voxel, pitch_um=s.pitch_um, method=s.settings.method,
                               wood=False, store=True, generated=s.wood is not None)
        n_shards = math.ceil(s.rays / shard_rays)
        # The scene's rays read back at once for its summary and Dataset.
        reduce = BASE_MEMORY + s.rays * (RAY_BYTES + DATASET_RAY_BYTES * len(scenes))
        written = n_shards * SHARD_BYTES + s.rays * (SHARD_RAY_BYTES + DATASET_RAY_BYTES) + 2 * ENTRY_BYTES
        est = est + Estimate(shard.cpu_s * n_shards, max(shard.memory, reduce), written)
    voxels = sum(woods.values())
    return est + Estimate(voxels / GENERATE_VOXELS_PER_CPU_S, 0.0,
                          voxels * DISK_BYTES_PER_VOXEL + (DATASET_BYTES if scenes else 0.0))


def camera_estimate(images) -> Estimate:
    """Images through a sheet: every pixel's aperture samples traced, the sheet's wood (at
    most all of it) generated once and kept on disk."""
    from .optics.settings import traced_voxel_um

    est = Estimate()
    woods = {}
    for cfg in images:
        cam, sh = cfg.camera, cfg.sheet
        rays = cam.pixels[0] * cam.pixels[1] * cam.samples
        if sh is None:
            est = est + Estimate(rays * 1e-6, BASE_MEMORY, 0.0)
            continue
        voxel = traced_voxel_um(sh.voxel_um, cfg.settings)
        if cfg.settings.medium_kind == "voxels":  # a surface method generates no wood
            key = (repr(sh.wood), sh.seed, voxel)
            woods[key] = max(woods.get(key, 0.0), sh.width_um * sh.length_um * sh.thickness_um / voxel ** 3)
        cost = INTERFACE_CPU_S.get(cfg.settings.method, INTERFACE_CPU_S["accurate"])
        est = est + Estimate(rays * INTERFACES_PER_PITCH * sh.thickness_um / sh.wood.fibre_diameter_um * cost,
                             BASE_MEMORY, 0.0)
    voxels = sum(woods.values())
    return est + Estimate(voxels / GENERATE_VOXELS_PER_CPU_S, 0.0, voxels * DISK_BYTES_PER_VOXEL)
