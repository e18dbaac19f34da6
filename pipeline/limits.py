"""Estimates of what a command costs, checked before any work starts.

Every command that generates or traces estimates from its inputs the CPU
time, the memory and the disk it needs (rates measured by ``make
bench-estimates`` on 2-core machines: results/estimates.md).  The estimates
hold within ACCURACY (1.5x) of what the commands use on the cases measured;
what cannot fit this machine's memory or the free disk even at 1/ACCURACY of
its estimate is refused with the estimate in the message, and what may not
fit is run with a warning.  What would take longer than
``TWRAY_CONFIRM_CPU_HOURS`` (default 2 CPU-hours) runs only with ``--yes``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from ._kernel_cache import PACKAGE
from .optics.settings import METHODS
from .params import ParameterError

log = logging.getLogger("twray.limits")

CONFIRM_ENV = "TWRAY_CONFIRM_CPU_HOURS"
ACCURACY = 1.5  # the estimates hold within this factor (tests/test_limits.py): beyond it a run is refused
RECORD_ENV = "TWRAY_ESTIMATES"  # a file each checked estimate is appended to, as one JSON line (measurements)
CONFIRM_DEFAULT_H = 2.0
# Measured by benchmarks/bench_estimates.py (results/estimates.md) on 2-core machines; tests/test_limits.py
# holds a few cases within 1.5x of what the commands use.
STARTUP_CPU_S = 1.6  # a process importing twray and loading its compiled kernels (the command, each worker)
# A process compiling the kernels of a medium kind on first use, once for each checkout and version of the
# sources (`make bench-exact`, part first_compile: a first `twray trace` of 0.1 mm into an empty kernel
# cache, less the same trace warm: exact 100-140 CPU-s, accurate 72-80); FIRST_KERNEL: the kernel whose
# cached index says they are compiled.
COMPILE_CPU_S = {"surfaces": 120.0, "voxels": 80.0}
FIRST_KERNEL = {"surfaces": ("optics._surface_march", "march"), "voxels": ("optics._voxel_march", "march_voxels")}
IMPORT_CPU_S = 1.0  # a command that reads or writes volumes only (export-tiff, a lazy generate)
BASE_MEMORY = 260e6  # a process with twray's libraries and kernels loaded (220-320 MB measured)
# Voxels generated per CPU-second into a store, its compression and pyramid included: fibre ellipses (birch
# 71-88 M/s), rotated plies (46 M/s), balsa's polygons (17 M/s).
GENERATE_VOXELS_PER_CPU_S = {"ellipse": 80e6, "plies": 45e6, "polygon": 17e6}
# zstd chunks and their pyramid at 0.5 µm voxels (birch 0.011-0.013 B, balsa 0.014 B a voxel); finer voxels
# compress better, about as sqrt(voxel); rotated plies 2.3x worse.
DISK_BYTES_PER_VOXEL = 0.012
PLY_DISK_FACTOR = 2.5
TIFF_CPU_S_PER_BYTE = 5e-9  # export-tiff: writing uncompressed slices
MEMORY_BYTES_PER_WOOD_VOXEL = 0.2  # chunks the tracer keeps bit-packed, and the chunk cache
# The camera's worker: its render's working set, and per voxel of the sheet its rays reach (fitted to
# Figure 5 small and quick: 0.68-0.79 GB and 1.24 GB).
CAMERA_MEMORY, CAMERA_BYTES_PER_WOOD_VOXEL = 330e6, 0.27
RAY_BYTES = 512  # a ray's state, result and beam entry in one trace
DATASET_RAY_BYTES = 24  # theta_r, theta_l, interfaces and status of a ray in a result Dataset
INTERFACE_CPU_S = {"paper": 1.2e-3, "fast": 3e-6, "accurate": 5e-6,
                   # exact: no wood generated; 16 CPU-µs an estimated interface (1000 rays x 1.5 mm on 2
                   # threads: 2.9 CPU-s of march for 207,000 estimated, 184,000 met; then its summary),
                   # plus its regions
                   "exact": 1.6e-5}
REGION_MEMORY_FACTOR = 4.0  # exact: a worker's growth with its regions (their tiles, caches and arenas)
# exact, thick sheets at high |ΔRI|: a few rays in a thousand are guided along R by total reflection at
# the walls, up to the event cap (birch's design maps: 11-46 of 35,000 rays at 1-2 mm), and build the
# distortion tiles along their strips: about GUIDED_TILES_PER_RAY x (|ΔRI| / 0.03)^3.1 x (thickness / 2 mm)^3.4
# tiles a ray beyond its beam's region (benchmarks/guided_tiles.py: birch into air, 500 rays a scene, one
# wood, 1-2 mm, |ΔRI| 0.01-0.03: 0.6-24 tiles a ray, the fit within 1.3x from 0.5 a ray up), and at most
# GUIDED_TILES_MAX a ray beyond what was measured (a ray guided to the event cap builds about 250). Each
# such tile, with the guided rays' extra interfaces, costs GUIDED_TILE_CPU_S at this module's host speed
# (1.9-2.1 ms measured on hosts 1.5-1.9x slower), and a worker keeps them
# (docs/performance.md#rays-guided-along-r).
GUIDED_TILES_PER_RAY, GUIDED_TILES_MAX, GUIDED_TILE_CPU_S = 28.0, 60.0, 1.4e-3
REGION_CPU_S_PER_BYTE = 1.7e-8  # exact: building a trace's regions (1.5 mm of birch: 0.8 CPU-s, nearly all tiles)
INTERFACES_PER_PITCH = 2.0  # interfaces met per cell pitch crossed (birch 1.6-1.8, balsa 2.3: two walls and more)
# What a study writes besides its wood (measured by tests/test_limits.py): per shard of rays an .npz
# (headers and its record, then 120 B a ray), per wood and value a summary and per value a pool
# (JSON, about 2 kB each: every estimator), per study a Dataset (150 kB of metadata and numbers, then per ray
# DATASET_RAY_BYTES; Table 1's compress to 17 B a ray).
SHARD_BYTES, SHARD_RAY_BYTES, ENTRY_BYTES, DATASET_BYTES = 7e3, 120.0, 2.2e3, 150e3
# ... and what its reductions cost: per scene (value and wood) its summary, its share of the value's
# pool and the tasks' overhead; per study its Dataset (xarray, Zarr).  Fitted with the startups to a
# small `exact` study (4 scenes, 5.9 CPU-s in all) and Table 1's study 2 at --scale quick (30, 20.8).
SCENE_CPU_S, DATASET_CPU_S = 0.3, 0.5
# A value's pool: every estimator on 2000 resamples of its woods and of its rays (benchmarks/bench_pool.py,
# measured on a host half as fast as this module's: the old pool's cost in the same hour was twice
# the one its constants were fitted to).  One wood (a trace's summary): every estimator's interval over
# its rays.  Several woods: the fits to resamples of woods, a fraction f of them distinct (a resample
# drawn twice is fitted once: f = 0.06 for 5 woods, 1 for 16 or more), about POOL_CPU_S + f ·
# POOL_FIT_CPU_S + rays · (POOL_CPU_S_PER_RAY + f · POOL_FIT_CPU_S_PER_RAY): 0.08 CPU-s for 3 woods ×
# 200 rays, 0.34 for 5 × 1000, 9.7 for 40 × 1000.
POOL_ONE_CPU_S, POOL_ONE_CPU_S_PER_RAY = 0.55, 3e-4
POOL_CPU_S, POOL_FIT_CPU_S, POOL_CPU_S_PER_RAY, POOL_FIT_CPU_S_PER_RAY = 0.05, 1.1, 3.3e-5, 1.8e-4
SPREAD = 1.25  # chunks generated around the beam's column by spreading rays, as a factor
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


def check(est: Estimate, *, what: str, yes: bool, disk_path=None, fit: str = "", note: str | None = None) -> None:
    """Refuse ``what`` if ``est`` clearly cannot fit this machine (even at 1/ACCURACY of the
    estimate), or needs ``--yes`` and has not got it; warn where it may not fit.  A refusal is one
    line: what it needs, ``fit`` (what would make it fit) and ``note`` (why it needs that much).
    Every estimate checked is appended to the file ``TWRAY_ESTIMATES`` names, if any."""
    _record(est, what)
    hint = (f"; {fit}" if fit else "") + (f"; {note}" if note else "")
    room = [("memory", est.memory, 0.8 * machine_memory(), f"than this machine's {size(machine_memory())}")]
    if disk_path is not None:
        free = free_disk(disk_path)
        room.append(("disk", est.disk, free, f"than the {size(free)} free under {disk_path}"))
    for kind, need, have, where in room:
        if need / ACCURACY > have:
            raise ParameterError(f"{what} needs {est.text()}: more {kind} {where}{hint}")
        if need > have:
            log.warning("%s may need more %s %s (estimated %s, good to %gx); it runs", what, kind, where,
                        size(need), ACCURACY)
    if not yes and not est.cpu_s <= confirm_hours() * 3600:
        raise ParameterError(f"{what} needs {est.text()}, above {CONFIRM_ENV}={confirm_hours():g} CPU-hours: "
                             f"add --yes (with make: YES=1) to run it{hint}")


def _record(est: Estimate, what: str) -> None:
    path = os.environ.get(RECORD_ENV)
    if path:
        line = json.dumps({"what": what, **dataclasses.asdict(est)})
        with open(path, "a", encoding="utf-8") as f:
            f.write(line + "\n")


def _kind(wood) -> str:
    if wood is not None and wood.cell_shape == "polygon":
        return "polygon"
    if wood is not None and wood.laminate and any(a % 180 != 0 for a in wood.laminate):
        return "plies"
    return "ellipse"


def generate_cpu_s(voxels: float, wood=None) -> float:
    """CPU-seconds to generate ``voxels`` of ``wood`` (WoodParams; None: birch-like)."""
    return voxels / GENERATE_VOXELS_PER_CPU_S[_kind(wood)]


def stored_bytes(voxels: float, voxel_um: float, wood=None) -> float:
    """Disk that ``voxels`` of ``wood`` take as compressed chunks with their pyramid."""
    factor = PLY_DISK_FACTOR if _kind(wood) == "plies" else 1.0
    return voxels * DISK_BYTES_PER_VOXEL * factor * math.sqrt(voxel_um / 0.5)


@functools.lru_cache(maxsize=None)
def distinct_resamples(woods: int) -> int:
    """How many of a pool's resamples of ``woods`` woods are distinct (each is fitted once): counted
    on the draws of one seed (:func:`pipeline.summary.woods_weights`; another seed's differ by a few)."""
    import numpy as np

    from .summary import N_BOOT, woods_weights

    if woods < 2:
        return 0
    return len(np.unique(woods_weights(woods, N_BOOT, np.random.default_rng(0)), axis=0))


def pool_cpu_s(woods: int, rays: int) -> float:
    """CPU seconds of reducing ``rays`` traced rays of ``woods`` woods to every estimator's widths
    and haze with their intervals (a value's pool; with one wood, a trace's summary)."""
    from .summary import N_BOOT

    if woods < 2:
        return POOL_ONE_CPU_S + rays * POOL_ONE_CPU_S_PER_RAY
    f = distinct_resamples(woods) / N_BOOT
    return POOL_CPU_S + f * POOL_FIT_CPU_S + rays * (POOL_CPU_S_PER_RAY + f * POOL_FIT_CPU_S_PER_RAY)


def summary_estimate(rays: int) -> Estimate:
    """Reducing ``rays`` traced rays of one wood to every estimator's widths and haze with their
    intervals (a trace's summary)."""
    return Estimate(pool_cpu_s(1, rays), 0.0, 0.0)


def compiling(kinds, processes: int) -> Estimate:
    """Compiling the kernels of the media ``kinds`` ("surfaces", "voxels") that this checkout has not
    compiled yet on this machine, in each of ``processes`` processes (each compiles them at first
    use; docs/performance.md#compiling-the-kernels)."""
    cpu = sum((COMPILE_CPU_S[k] for k in set(kinds) if k in COMPILE_CPU_S and not compiled(*FIRST_KERNEL[k])), 0.0)
    return Estimate(cpu * processes, 0.0, 0.0)


def first_run_note(est: Estimate, workers: int = 0) -> str | None:
    """What a command says where ``est`` (:func:`compiling`) is not nothing: it compiles the tracer's
    kernels first (in ``workers`` workers; 0: in itself)."""
    if not est.cpu_s > 0:
        return None
    who = f"each of the {workers} workers compiles" if workers else "it compiles"
    return f"first run of these sources here: {who} the tracer's kernels before its first trace ({hours(est.cpu_s)} " \
           "in all, once)"


def first_run_line(command: str, est: Estimate, workers: int = 0) -> str | None:
    """:func:`first_run_note` as the line ``twray <command>`` prints."""
    note = first_run_note(est, workers)
    return None if note is None else f"twray {command}: {note}"


def compiled(module: str, kernel: str) -> bool:
    """Whether the kernel cache in use holds ``kernel`` of ``module`` (a module of this package, as
    "optics._surface_march") compiled from this checkout: Numba's index file of it, in the folder
    Numba keeps for that module's folder (``<folder name>_<sha1 of its path>``).  True where Numba
    caches beside the sources (no NUMBA_CACHE_DIR): not looked for."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    if not root:
        return True
    path = os.path.abspath(PACKAGE.joinpath(*module.split(".")).with_suffix(".py"))
    folder = os.path.dirname(path)
    sub = Path(root) / f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"
    version = f"py{sys.version_info[0]}{sys.version_info[1]}"
    return any(sub.glob(f"{Path(path).stem}.{kernel}-*.{version}.nbi"))


def startup(processes: int, *, kernels: bool = True) -> Estimate:
    """What ``processes`` processes running twray cost before any work (the command and its workers;
    ``kernels``: they load the generator's and tracers' compiled kernels)."""
    return Estimate((STARTUP_CPU_S if kernels else IMPORT_CPU_S) * processes, BASE_MEMORY, 0.0)


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


def tiles_kept_bytes(guided_tiles: float) -> float:
    """Memory of the distortion tiles a study's worker keeps beyond one trace's region, for a wood
    whose scenes' guided rays build ``guided_tiles`` (docs/methods.md#distortion): the wood in use
    keeps them up to its ceiling (12,000-15,000 tiles measured in birch at 1-2 mm and |ΔRI| 0.03)."""
    from .microstructure.model import WOOD_TILE_CAP, TILE_BYTES

    return float(min(WOOD_TILE_CAP, guided_tiles) * TILE_BYTES)


def guided_tiles_per_ray(thickness_um: float, delta_ri: float) -> float:
    """Distortion tiles a ray of generated wood builds beyond its beam's region, on average: those
    of the few rays guided along R by total reflection at the walls (GUIDED_TILES_PER_RAY)."""
    x = abs(delta_ri) / 0.03
    return min(GUIDED_TILES_MAX, GUIDED_TILES_PER_RAY * x ** 3.1 * (thickness_um / 2000.0) ** 3.4)


def trace_estimate(*, rays: int, beam_um: float, thickness_um: float, voxel_um: float, pitch_um: float,
                   method: str, wood: bool = True, store: bool = False, generated: bool = True,
                   params=None, delta_ri: float = 0.0) -> Estimate:
    """One beam traced in one process, its start not counted (``wood``: generated as rays reach it;
    ``store``: kept on disk; ``generated``: the model's wood, not a reference lattice; ``params``:
    the wood's WoodParams, for its generation rate and compression; ``delta_ri``: the wall's index
    minus the polymer's, for the tiles of guided rays)."""
    interfaces = rays * INTERFACES_PER_PITCH * thickness_um / pitch_um
    voxels = wood_voxels(beam_um, thickness_um, voxel_um) if wood and METHODS[method] == "voxels" else 0.0
    cpu = interfaces * INTERFACE_CPU_S.get(method, INTERFACE_CPU_S["accurate"]) + generate_cpu_s(voxels, params)
    memory = BASE_MEMORY + rays * RAY_BYTES + (0 if store else voxels * MEMORY_BYTES_PER_WOOD_VOXEL)
    if generated and METHODS.get(method) == "surfaces":
        region = surface_region_bytes(beam_um, thickness_um, pitch_um)
        memory += REGION_MEMORY_FACTOR * region
        cpu += region * REGION_CPU_S_PER_BYTE + rays * guided_tiles_per_ray(thickness_um, delta_ri) * GUIDED_TILE_CPU_S
    return Estimate(cpu, memory, stored_bytes(voxels, voxel_um, params) if store else 0.0)


def shard_estimate(scene, rays: int) -> Estimate:
    """One shard of ``rays`` rays of a study's ``scene`` traced, its rays stored."""
    return trace_estimate(rays=rays, beam_um=scene.beam_um, thickness_um=scene.thickness_um,
                          voxel_um=scene.traced_voxel_um, pitch_um=scene.pitch_um, method=scene.settings.method,
                          wood=False, store=True, generated=scene.wood is not None, params=scene.wood,
                          delta_ri=scene.delta_ri)


def study_estimate(scenes, *, shard_rays: int) -> Estimate:
    """A study's scenes: each wood generated once (on disk), each scene's rays traced by shards and
    written with their summaries, pools and one Dataset."""
    est = Estimate()
    woods = {}
    regions = {}  # exact: per wood, the largest region a scene of it builds
    scenes = [dataclasses.replace(s, rays=s.target.max_rays)  # traced to a precision: at most its cap of rays
              if s.target is not None and s.target.over == "rays" else s for s in scenes]
    guided = {}  # exact: per wood, the tiles its scenes' guided rays build, which a worker keeps
    pools = {}  # per value: its woods and their rays
    for s in scenes:
        if s.wood is not None and METHODS.get(s.settings.method) == "surfaces":
            key = (repr(s.wood), s.seed)
            guided[key] = guided.get(key, 0.0) + s.rays * guided_tiles_per_ray(s.thickness_um, s.delta_ri)
    for s in scenes:
        voxel = s.traced_voxel_um
        if s.settings.medium_kind == "voxels" and s.wood is not None:  # surfaces and lattices store no wood
            key = (repr(s.wood), s.seed, voxel)
            woods[key] = (max(woods.get(key, (0.0,))[0], wood_voxels(s.beam_um, s.thickness_um, voxel)), voxel, s.wood)
        shard = shard_estimate(s, min(s.rays, shard_rays))
        n_shards = math.ceil(s.rays / shard_rays)
        # A surface scene's region is built by each shard, but its distortion tiles (nearly all of
        # its cost) are cached in the worker and shared by every scene of the same wood (Table 1's
        # values of ΔRI, say): counted once a wood.
        again = 0.0
        surface = s.wood is not None and METHODS.get(s.settings.method) == "surfaces"
        if surface:
            region = surface_region_bytes(s.beam_um, s.thickness_um, s.pitch_um) * REGION_CPU_S_PER_BYTE
            again = n_shards * region
            key = (repr(s.wood), s.seed)
            regions[key] = max(regions.get(key, 0.0), region)
        # A worker keeps the distortion tiles of the wood it traces across shards and scenes (up to a ceiling).
        kept = tiles_kept_bytes(guided[(repr(s.wood), s.seed)]) if surface else 0.0
        # The scene's rays read back at once for its summary and Dataset.
        reduce = BASE_MEMORY + s.rays * (RAY_BYTES + DATASET_RAY_BYTES * len(scenes))
        written = n_shards * SHARD_BYTES + s.rays * (SHARD_RAY_BYTES + DATASET_RAY_BYTES) + 2 * ENTRY_BYTES
        est = est + Estimate(shard.cpu_s * n_shards - again + SCENE_CPU_S, max(shard.memory + kept, reduce), written)
        value = repr(dataclasses.replace(s, seed=0, realisation=0, rays=0))  # one pool a value, over its woods
        pools[value] = (pools.get(value, (0, 0))[0] + 1, pools.get(value, (0, 0))[1] + s.rays)
    est = est + Estimate(sum(regions.values()) + sum(pool_cpu_s(w, n) for w, n in pools.values()), 0.0, 0.0)
    return est + _woods(woods) + (Estimate(DATASET_CPU_S, 0.0, DATASET_BYTES) if scenes else Estimate())


def _woods(woods: dict) -> Estimate:
    """Generating and storing each wood of ``woods`` {key: (voxels, voxel_um, WoodParams)} once."""
    return Estimate(sum(generate_cpu_s(n, p) for n, _, p in woods.values()), 0.0,
                    sum(stored_bytes(n, v, p) for n, v, p in woods.values()))


def camera_footprint_um(camera, sheet) -> tuple[float, float]:
    """(along R, along L) [µm] of the sheet the camera's rays can reach: the cone from the aperture to
    the object field at both faces, widened by 1 % of the thickness (scattered rays) and a chunk on
    each side, at most the sheet (Figure 5's sheets: 1.2-1.3x the chunks the rays reached)."""
    p_mm = camera.pitch_um * 1e-3 / camera.magnification
    half = [0.5 * n * p_mm for n in camera.pixels[::-1]]  # (x, y) of the object field [mm]
    u = camera.objective_mm
    reach = []
    for h in half:
        faces = (u - (sheet.gap_um + sheet.thickness_um) * 1e-3, u - sheet.gap_um * 1e-3)
        far = max(0.5 * camera.aperture_mm * (1 - z / u) + h * z / u for z in faces)
        reach.append(2e3 * far + 0.02 * sheet.thickness_um + 2 * CHUNK * sheet.voxel_um)
    along_r, along_l = reach if sheet.r_axis == "x" else reach[::-1]
    return min(along_r, sheet.width_um), min(along_l, sheet.length_um)


def camera_estimate(images, rows=None) -> Estimate:
    """Images through a sheet, their start not counted: every pixel's aperture samples traced, the
    part of the sheet's wood the rays reach generated once and kept on disk.  ``rows``: per image,
    the sensor rows left to render (default all of them)."""
    from .optics.settings import traced_voxel_um

    est = Estimate()
    woods = {}
    for q, cfg in enumerate(images):
        cam, sh = cfg.camera, cfg.sheet
        rays = (cam.pixels[0] if rows is None else rows[q]) * cam.pixels[1] * cam.samples
        if sh is None:
            est = est + Estimate(rays * 1e-6, BASE_MEMORY, 0.0)
            continue
        voxel = traced_voxel_um(sh.voxel_um, cfg.settings)
        held = 0.0
        if cfg.settings.medium_kind == "voxels":  # a surface method generates no wood
            key = (repr(sh.wood), sh.seed, voxel)
            r_um, l_um = camera_footprint_um(cam, sh)
            held = r_um * l_um * sh.thickness_um / voxel ** 3
            woods[key] = (max(woods.get(key, (0.0,))[0], held), voxel, sh.wood)
        cost = INTERFACE_CPU_S.get(cfg.settings.method, INTERFACE_CPU_S["accurate"])
        est = est + Estimate(rays * INTERFACES_PER_PITCH * sh.thickness_um / sh.wood.fibre_diameter_um * cost,
                             BASE_MEMORY + CAMERA_MEMORY + held * CAMERA_BYTES_PER_WOOD_VOXEL, 0.0)
    return est + _woods(woods)
