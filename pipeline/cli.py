"""The ``twray`` command line.

Every bad input ends with one line on stderr naming the field, the value and
the rule, exit code 2, and nothing written.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from . import __version__
from .params import ParameterError, build_params, make_grid, parse_set, parse_triple, preset_names

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, not the usage block
        raise ParameterError(f"{self.prog}: {message}")


def _add_generate(sub):
    p = sub.add_parser("generate", help="generate a wood microstructure volume (OME-Zarr)")
    p.add_argument("--preset", default="birch", help=f"species preset ({', '.join(preset_names())})")
    p.add_argument("--config", help="YAML file of parameters (may name a preset)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one parameter, e.g. --set wall_thickness_um=4")
    p.add_argument("--size-um", required=True, help="sample size R,T,L [µm]")
    p.add_argument("--origin-um", default="0,0,0", help="position of the sample corner R,T,L [µm]")
    p.add_argument("--voxel-um", default="0.5", help="voxel size [µm] (default 0.5)")
    p.add_argument("--chunks", default="128,128,128", help="chunk shape R,T,L [voxels]")
    p.add_argument("--seed", default="1", help="non-negative integer seed")
    p.add_argument("--out", required=True, help="output store, e.g. sample.zarr")
    p.add_argument("--lazy", action="store_true",
                   help="write only the metadata; chunks are generated when first read")
    p.add_argument("--workers", default=None,
                   help="generate on a local dask.distributed cluster of N worker processes")
    p.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_generate)


def _int(text: str, name: str, minimum: int) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ParameterError(f"`{name}` must be an integer, got {name}={text!r}") from None
    if value < minimum:
        raise ParameterError(f"`{name}` must be >= {minimum}, got {name}={value}")
    return value


def _float(text: str, name: str) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        raise ParameterError(f"`{name}` must be a number, got {name}={text!r}") from None


def _client(workers, scheduler):
    if scheduler:
        from distributed import Client

        return Client(scheduler), None
    if workers is not None:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        return Client(cluster), cluster
    return None, None


def cmd_generate(args) -> int:
    from .microstructure.volume import WoodVolume, publish, staged_path

    params = build_params(args.preset, args.config, parse_set(args.overrides))
    size = parse_triple(args.size_um, "size_um", positive=True)
    origin = parse_triple(args.origin_um, "origin_um", positive=False)
    chunks = parse_triple(args.chunks, "chunks", positive=True, integer=True)
    seed = _int(args.seed, "seed", 0)
    workers = _int(args.workers, "workers", 1) if args.workers is not None else None
    grid = make_grid(size, _float(args.voxel_um, "voxel_um"), origin, params)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ParameterError(f"`out` must not exist already (use --overwrite), got {str(out)!r}")
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    client = cluster = None
    t0 = time.perf_counter()
    try:
        vol = WoodVolume.create(staged, params, grid, seed=seed, chunks=chunks)
        n = 0
        if not args.lazy:
            client, cluster = _client(workers, args.scheduler)
            n = vol.generate(scheduler=client)
        publish(staged, out, args.overwrite)
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    dt = time.perf_counter() - t0
    nvox = grid.shape[0] * grid.shape[1] * grid.shape[2]
    msg = (f"{out}: {params.species}, shape {grid.shape} (R, T, L) at {grid.voxel_um:g} µm, "
           f"chunks {tuple(vol.chunks)}")
    if args.lazy:
        msg += ", lazy (chunks generated on first read)"
    else:
        msg += f", {n} chunks in {dt:.1f} s ({nvox / max(dt, 1e-9):.3g} voxels/s)"
        if nvox <= 2 * 10**8:
            msg += f", wall fraction {WoodVolume.open(out).wall_fraction():.3f}"
    print(msg)
    return 0


def cmd_slices(args) -> int:
    from .microstructure.export import write_slices
    from .microstructure.volume import WoodVolume

    for path in write_slices(WoodVolume.open(args.volume), args.out):
        print(path)
    return 0


def cmd_export_tiff(args) -> int:
    from .microstructure.export import write_tiff_stack
    from .microstructure.volume import WoodVolume

    paths = write_tiff_stack(WoodVolume.open(args.volume), args.out)
    print(f"wrote {len(paths)} TIFF slices (one per L) to {args.out}")
    return 0


def cmd_info(args) -> int:
    from .microstructure.volume import describe

    print(describe(args.volume))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="twray", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"twray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_generate(sub)
    p = sub.add_parser("slices", help="PNG cross-sections in the R-T, L-T and L-R planes")
    p.add_argument("volume")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_slices)
    p = sub.add_parser("export-tiff", help="one TIFF per L slice, for ImageJ/Avizo")
    p.add_argument("volume")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_export_tiff)
    p = sub.add_parser("info", help="print a volume's shape, parameters and generated chunks")
    p.add_argument("volume")
    p.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except ParameterError as exc:
        print(f"twray: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
