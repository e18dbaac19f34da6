"""``twray generate``, ``slices``, ``export-tiff`` and ``info``: wood volumes and what is read from them."""

from __future__ import annotations

import math
import shutil
import sys
import time
from pathlib import Path

from .. import limits
from ..progress import mode as progress_mode
from ..cluster import generate_client
from ..params import ParameterError, build_params, make_grid, parse_set, parse_triple, preset_names
from .args import YES_HELP, integer, number, out_path, subparser


def add_generate(sub):
    p = subparser(sub, "generate", help="generate a wood microstructure volume (OME-Zarr)")
    p.add_argument("--preset", default="birch", help=f"species preset ({', '.join(preset_names())})")
    p.add_argument("--config", help="YAML file of parameters (may name a preset)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter, e.g. --set wall_thickness_um=4")
    p.add_argument("--size-um", default=None, help="sample size R,T,L [µm] (required unless --materialise)")
    p.add_argument("--origin-um", default="0,0,0", help="position of the sample corner R,T,L [µm]")
    p.add_argument("--voxel-um", default="0.5", help="voxel size [µm] (default 0.5)")
    p.add_argument("--chunks", default="128,128,128", help="chunk shape R,T,L [voxels]")
    p.add_argument("--seed", default="1", help="non-negative integer seed")
    p.add_argument("--out", required=True, help="output store, e.g. sample.zarr")
    p.add_argument("--materialise", action="store_true",
                   help="generate every chunk a --lazy store at OUT does not hold yet (other tools read "
                        "those as 255), in place")
    p.add_argument("--lazy", action="store_true",
                   help="write only the metadata; chunks are generated when first read")
    p.add_argument("--workers", default=None,
                   help="generate on a local dask.distributed cluster of N worker processes")
    p.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_generate)


def _generate_estimate(voxels: float, voxel_um: float, params, *, workers) -> limits.Estimate:
    """Generating ``voxels`` into a store: the command (and its workers) started, the voxels
    generated, their chunks and pyramid written."""
    return limits.startup(1 + (workers or 0)) + limits.Estimate(
        limits.generate_cpu_s(voxels, params), 0.0, limits.stored_bytes(voxels, voxel_um, params))


def _materialise(args) -> int:
    """Generate in place the chunks a lazy twray volume does not hold yet."""
    from ..microstructure.volume import WoodVolume

    if args.size_um is not None or args.lazy or args.overwrite:
        raise ParameterError("`--materialise` works on the existing store at --out: give no --size-um, "
                             "--lazy or --overwrite")
    out = out_path(args.out)
    vol = WoodVolume.open(out)
    todo = len(vol.all_chunks()) - len(vol.generated_chunks())
    nvox = todo / max(1, len(vol.all_chunks())) * math.prod(vol.shape)
    workers = integer(args.workers, "workers", 1) if args.workers is not None else None
    est = _generate_estimate(nvox, vol.grid.voxel_um, vol.params, workers=workers)
    limits.check(est, what=f"`generate --materialise` of {todo} chunks", yes=args.yes, disk_path=out,
                 fit="keep the store lazy: twray generates chunks as they are read")
    t0 = time.perf_counter()
    with generate_client(workers, args.scheduler) as client:
        n = vol.generate(scheduler=client, progress=progress_mode(args.quiet))
        vol.build_pyramid()
    print(f"{out}: {n} chunks generated in {time.perf_counter() - t0:.1f} s; all "
          f"{len(vol.all_chunks())} chunks are stored")
    return 0


def cmd_generate(args) -> int:
    if args.materialise:
        return _materialise(args)
    if args.size_um is None:
        raise ParameterError("`size_um` is required (R,T,L in µm), unless --materialise")
    params = build_params(args.preset, args.config, parse_set(args.overrides))
    size = parse_triple(args.size_um, "size_um", positive=True)
    origin = parse_triple(args.origin_um, "origin_um", positive=False)
    chunks = parse_triple(args.chunks, "chunks", positive=True, integer=True)
    seed = integer(args.seed, "seed", 0)
    workers = integer(args.workers, "workers", 1) if args.workers is not None else None
    grid = make_grid(size, number(args.voxel_um, "voxel_um"), origin, params)
    out = out_path(args.out)
    t0 = time.perf_counter()
    vol, n = _generate(args, params, grid, seed, chunks, workers, out)
    dt = time.perf_counter() - t0
    nvox = math.prod(grid.shape)
    msg = (f"{out}: {params.species}, shape {grid.shape} (R, T, L) at {grid.voxel_um:g} µm, "
           f"chunks {tuple(vol.chunks)}")
    if args.lazy:
        msg += ", lazy (chunks generated on first read)"
    else:
        from ..microstructure.volume import WoodVolume

        msg += f", {n} chunks in {dt:.1f} s ({nvox / max(dt, 1e-9):.3g} voxels/s)"
        if nvox <= 2 * 10**8:
            msg += f", wall fraction {WoodVolume.open(out).wall_fraction():.3f}"
    print(msg)
    return 0


def _generate(args, params, grid, seed: int, chunks, workers, out: Path):
    """Check what the volume would cost, generate it staged (every chunk, unless --lazy) and publish
    it at ``out``; the volume and the chunks generated."""
    from ..cache import sweep_leftovers
    from ..microstructure.volume import WoodVolume
    from ..publish import check_replaceable, publish, staged_path

    check_replaceable(out, args.overwrite)
    sweep_leftovers(out.parent)  # what generate runs interrupted before this one left
    nvox = math.prod(grid.shape)
    est = limits.startup(1, kernels=False) + limits.Estimate(0.0, 0.0, 4096.0)
    if not args.lazy:
        est = _generate_estimate(nvox, grid.voxel_um, params, workers=workers)
    limits.check(est, what=f"`generate` of {nvox:.3g} voxels", yes=args.yes, disk_path=out.parent,
                 fit="use --lazy to generate chunks only when they are read, or a smaller --size-um")
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray generate: estimate {est.text()}", file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    try:
        vol = WoodVolume.create(staged, params, grid, seed=seed, chunks=chunks)
        n = 0
        if not args.lazy:
            # The workers stop on leaving, before the staged store is removed (they would
            # write into it again).
            with generate_client(workers, args.scheduler) as client:
                n = vol.generate(scheduler=client, progress=progress_mode(args.quiet))
                vol.build_pyramid()
        publish(staged, out, args.overwrite)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    return vol, n


def cmd_slices(args) -> int:
    from ..microstructure.export import write_slices
    from ..microstructure.volume import WoodVolume

    args.out = str(out_path(args.out))
    for path in write_slices(WoodVolume.open(args.volume), args.out):
        print(path)
    return 0


def cmd_export_tiff(args) -> int:
    from ..microstructure.export import write_tiff_stack
    from ..microstructure.volume import WoodVolume

    args.out = str(out_path(args.out))
    vol = WoodVolume.open(args.volume)
    nvox = math.prod(vol.shape)
    todo = 1.0 - len(vol.generated_chunks()) / max(1, math.prod(vol.chunk_grid))
    # Uncompressed 8-bit slices (one slab of a chunk's depth in memory at a time), and the chunks
    # a lazy volume has not generated yet.
    est = limits.startup(1, kernels=False) + limits.Estimate(
        limits.generate_cpu_s(todo * nvox, vol.params) + nvox * limits.TIFF_CPU_S_PER_BYTE,
        limits.BASE_MEMORY + vol.shape[0] * vol.shape[1] * vol.chunks[2],
        nvox + limits.stored_bytes(todo * nvox, vol.grid.voxel_um, vol.params))
    limits.check(est, what=f"`export-tiff` of {nvox:.3g} voxels", yes=args.yes, disk_path=args.out,
                 fit="export a smaller volume (generate one with a smaller --size-um)")
    paths = write_tiff_stack(vol, args.out)
    print(f"wrote {len(paths)} TIFF slices (one per L) to {args.out}")
    return 0


def cmd_info(args) -> int:
    from ..microstructure.volume import describe

    print(describe(args.volume))
    return 0
