"""One ``twray generate``: a wood volume written as an OME-Zarr store, every chunk or lazily,
or the chunks a lazy store does not hold yet generated in place (docs/guide.md#volumes)."""

from __future__ import annotations

import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from . import limits
from .cluster import generate_client
from .params import WoodParams, make_grid


@dataclass(frozen=True, kw_only=True)
class GenerateRequest:
    """A volume of ``params`` and ``seed``: ``size_um`` (R, T, L) from ``origin_um`` at ``voxel_um``
    in ``chunks`` [voxels], written at ``out``; ``lazy``: metadata only (chunks generated when read).
    ``workers``/``scheduler``: where chunks are generated (None: in this process)."""

    params: WoodParams
    size_um: tuple
    out: Path
    origin_um: tuple = (0.0, 0.0, 0.0)
    voxel_um: float = 0.5
    chunks: tuple = (128, 128, 128)
    seed: int = 1
    lazy: bool = False
    overwrite: bool = False
    workers: int | None = None
    scheduler: str | None = None
    progress: str = "auto"
    yes: bool = False
    grey: GreyScan | None = None  # write the grey-level scan a µCT would record (.npy) instead of voxels


@dataclass(frozen=True)
class GreyScan:
    """A grey-level scan of the wood (:func:`pipeline.microstructure.grey.grey_volume`): the wall
    fraction of each voxel from ``supersample``³ fine voxels, a Gaussian blur of σ ``blur_um`` and
    noise of standard deviation ``noise``."""

    supersample: int = 4
    blur_um: float = 0.0
    noise: float = 0.0


@dataclass(frozen=True)
class Generated:
    """What was written: the store and its volume (a WoodVolume; with ``grey``, the scan's array), how
    many chunks were generated and in how long."""

    out: Path
    volume: object
    chunks_generated: int
    seconds: float
    lazy: bool
    grey: bool = False


def estimate(voxels: float, voxel_um: float, params, *, workers) -> limits.Estimate:
    """Generating ``voxels`` into a store: the command (and its workers) started, the voxels
    generated, their chunks and pyramid written."""
    return limits.startup(1 + (workers or 0)) + limits.Estimate(
        limits.generate_cpu_s(voxels, params), 0.0, limits.stored_bytes(voxels, voxel_um, params))


def generate(request: GenerateRequest) -> Generated:
    """Check what the volume would cost, generate it staged (every chunk, unless lazy) and publish it
    at ``request.out``; nothing is left at ``out`` if it fails."""
    from .cache import sweep_leftovers
    from .microstructure.volume import WoodVolume
    from .publish import check_replaceable, publish, staged_path

    r = request
    grid = make_grid(r.size_um, r.voxel_um, r.origin_um, r.params)
    out = Path(r.out)
    check_replaceable(out, r.overwrite)
    if r.grey is not None:
        return _grey(r, grid, out)
    sweep_leftovers(out.parent)  # what generate runs interrupted before this one left
    nvox = math.prod(grid.shape)
    est = limits.startup(1, kernels=False) + limits.Estimate(0.0, 0.0, 4096.0)
    if not r.lazy:
        est = estimate(nvox, grid.voxel_um, r.params, workers=r.workers)
    limits.check(est, what=f"`generate` of {nvox:.3g} voxels", yes=r.yes, disk_path=out.parent,
                 fit="use --lazy to generate chunks only when they are read, or a smaller --size-um")
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray generate: estimate {est.text()}", file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    t0 = time.perf_counter()
    try:
        vol = WoodVolume.create(staged, r.params, grid, seed=r.seed, chunks=r.chunks)
        n = 0
        if not r.lazy:
            # The workers stop on leaving, before the staged store is removed (they would
            # write into it again).
            with generate_client(r.workers, r.scheduler) as client:
                n = vol.generate(scheduler=client, progress=r.progress)
                vol.build_pyramid()
        publish(staged, out, r.overwrite)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    return Generated(out, vol, n, time.perf_counter() - t0, r.lazy)


def _grey(r: GenerateRequest, grid, out: Path) -> Generated:
    """The grey-level scan of ``r``'s wood on ``grid``, written to ``out`` (.npy, float32) in one
    rename."""
    import numpy as np

    from .cache import atomic_write
    from .microstructure.grey import grey_volume
    from .params import ParameterError

    if out.suffix != ".npy" or r.lazy:
        raise ParameterError(f"`out` of a --grey scan must be a .npy file (not --lazy), got {str(out)!r}")
    nvox = math.prod(grid.shape)
    fine = nvox * r.grey.supersample ** 3
    est = limits.startup(1) + limits.Estimate(limits.generate_cpu_s(fine, r.params), limits.BASE_MEMORY + 12.0 * nvox
                                              + min(fine, 32e6), 4.0 * nvox)
    limits.check(est, what=f"`generate --grey` of {nvox:.3g} voxels from {fine:.3g} fine ones", yes=r.yes,
                 disk_path=out.parent, fit="a smaller --size-um, a larger --voxel-um or a smaller --supersample")
    t0 = time.perf_counter()
    scan = grey_volume(r.params, grid, seed=r.seed, supersample=r.grey.supersample, blur_um=r.grey.blur_um,
                       noise=r.grey.noise, noise_seed=r.seed)

    def write(tmp):
        with open(tmp, "wb") as f:
            np.save(f, scan)

    atomic_write(out, write)
    return Generated(out, scan, 0, time.perf_counter() - t0, lazy=False, grey=True)


def materialise(out, *, workers: int | None = None, scheduler: str | None = None, progress: str = "auto",
                yes: bool = False) -> Generated:
    """Generate in place the chunks the lazy twray volume at ``out`` does not hold yet."""
    from .microstructure.volume import WoodVolume

    vol = WoodVolume.open(out)
    todo = len(vol.all_chunks()) - len(vol.generated_chunks())
    nvox = todo / max(1, len(vol.all_chunks())) * math.prod(vol.shape)
    est = estimate(nvox, vol.grid.voxel_um, vol.params, workers=workers)
    limits.check(est, what=f"`generate --materialise` of {todo} chunks", yes=yes, disk_path=out,
                 fit="keep the store lazy: twray generates chunks as they are read")
    t0 = time.perf_counter()
    with generate_client(workers, scheduler) as client:
        n = vol.generate(scheduler=client, progress=progress)
        vol.build_pyramid()
    return Generated(Path(out), vol, n, time.perf_counter() - t0, lazy=False)


def describe(g: Generated, *, materialised: bool = False) -> str:
    """One line on what was written (the wall fraction too, when it is cheap to read)."""
    from .microstructure.volume import WoodVolume

    vol = g.volume
    if g.grey:
        return (f"{g.out}: grey-level scan, shape {vol.shape} (R, T, L), wall fraction {float(vol.mean()):.3f} "
                f"(grey levels {float(vol.min()):.3g} to {float(vol.max()):.3g}), in {g.seconds:.1f} s")
    if materialised:
        return (f"{g.out}: {g.chunks_generated} chunks generated in {g.seconds:.1f} s; all "
                f"{len(vol.all_chunks())} chunks are stored")
    nvox = math.prod(vol.grid.shape)
    msg = (f"{g.out}: {vol.params.species}, shape {vol.grid.shape} (R, T, L) at {vol.grid.voxel_um:g} µm, "
           f"chunks {tuple(vol.chunks)}")
    if g.lazy:
        return msg + ", lazy (chunks generated on first read)"
    msg += f", {g.chunks_generated} chunks in {g.seconds:.1f} s ({nvox / max(g.seconds, 1e-9):.3g} voxels/s)"
    if nvox <= 2 * 10**8:
        msg += f", wall fraction {WoodVolume.open(g.out).wall_fraction():.3f}"
    return msg

