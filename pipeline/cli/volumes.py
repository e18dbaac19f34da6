"""``twray generate``, ``slices``, ``export-tiff`` and ``info``: wood volumes and what is read from them."""

from __future__ import annotations

import math

from .. import limits
from ..progress import mode as progress_mode
from ..params import ParameterError, build_params, parse_set, parse_triple, preset_names
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
    p.add_argument("--grey", action="store_true",
                   help="write the grey-level scan a µCT would record (.npy, float32: the wall fraction of "
                        "each voxel) instead of voxels, for --method iso")
    p.add_argument("--supersample", default=None, help="--grey: fine voxels per voxel edge (default 4)")
    p.add_argument("--blur-um", default=None, help="--grey: σ of a Gaussian point-spread function [µm] (default 0)")
    p.add_argument("--noise", default=None, help="--grey: standard deviation of Gaussian noise (default 0)")
    p.set_defaults(func=cmd_generate)


def cmd_generate(args) -> int:
    from .. import generate_job

    workers = integer(args.workers, "workers", 1) if args.workers is not None else None
    if args.materialise:
        if args.size_um is not None or args.lazy or args.overwrite:
            raise ParameterError("`--materialise` works on the existing store at --out: give no --size-um, "
                                 "--lazy or --overwrite")
        done = generate_job.materialise(out_path(args.out), workers=workers, scheduler=args.scheduler,
                                        progress=progress_mode(args.quiet), yes=args.yes)
        print(generate_job.describe(done, materialised=True))
        return 0
    if args.size_um is None:
        raise ParameterError("`size_um` is required (R,T,L in µm), unless --materialise")
    request = generate_job.GenerateRequest(
        params=build_params(args.preset, args.config, parse_set(args.overrides)),
        size_um=parse_triple(args.size_um, "size_um", positive=True),
        origin_um=parse_triple(args.origin_um, "origin_um", positive=False),
        voxel_um=number(args.voxel_um, "voxel_um"),
        chunks=parse_triple(args.chunks, "chunks", positive=True, integer=True),
        seed=integer(args.seed, "seed", 0), out=out_path(args.out), lazy=args.lazy, overwrite=args.overwrite,
        workers=workers, scheduler=args.scheduler, progress=progress_mode(args.quiet), yes=args.yes,
        grey=_grey_scan(args))
    print(generate_job.describe(generate_job.generate(request)))
    return 0


def _grey_scan(args):
    """``--grey`` and its options as a GreyScan (None without it; its options alone are refused)."""
    from ..generate_job import GreyScan

    given = [f"--{k.replace('_', '-')}" for k in ("supersample", "blur_um", "noise") if getattr(args, k) is not None]
    if not args.grey:
        if given:
            raise ParameterError(f"`{given[0]}` applies to --grey (a grey-level scan)")
        return None
    return GreyScan(integer(args.supersample or "4", "supersample", 1), number(args.blur_um or "0", "blur_um"),
                    number(args.noise or "0", "noise"))


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
