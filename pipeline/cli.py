"""The ``twray`` command line.

Every bad input ends with one line on stderr naming the field, the value and
the rule, exit code 2, and nothing written.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import shutil
import signal
import sys
import threading
import time
import dataclasses
from dataclasses import replace
from pathlib import Path

from . import __version__, limits
from .cache import log_to_stderr
from .progress import mode as progress_mode
from .params import ParameterError, build_params, make_grid, parse_set, parse_triple, preset_names

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # as a shell reports a process ended by Ctrl-C


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # Values such as `--delta-ri -1e-3` or `--incidence-deg -10,5` are values,
        # not options (argparse's own test knows only plain decimals); no option
        # of twray starts with a digit or a dot.
        self._negative_number_matcher = re.compile(r"^-[\d.]")

    def error(self, message):  # one line, not the usage block
        raise ParameterError(f"{self.prog}: {message}")


YES_HELP = ("run even if the estimate is above TWRAY_CONFIRM_CPU_HOURS (default 2 CPU-hours); what cannot "
            "fit memory or disk is refused anyway")


EXAMPLES = {
    "generate": ("Generate a wood microstructure (axes R, T, L; 1 = cell wall, 0 = polymer) from a species "
                 "preset and physical parameters into an OME-Zarr store, chunk by chunk on a Dask cluster, "
                 "or lazily (--lazy: chunks are made when first read). The same seed gives the same voxels "
                 "whatever the chunks or workers.",
                 ["twray generate --preset birch --size-um 150,150,100 --out birch.zarr",
                  "twray generate --preset balsa --set wall_thickness_um=1.2 --size-um 1500,1500,1500 --lazy "
                  "--out balsa.zarr",
                  "twray generate --config my-wood.yaml --size-um 300,300,300 --workers 2 --out w.zarr"]),
    "trace": ("Trace a square beam of rays through generated wood (--preset, made lazily as rays reach it) "
              "or a user volume (--volume) with Snell refraction and total internal reflection, and report "
              "FWHM_R and FWHM_L (Lorentz fits with bootstrap 95 % intervals) and haze.",
              ["twray trace --preset birch --thickness-mm 0.5 --delta-ri 0.01",
               "twray trace --volume sample.zarr --delta-ri -0.02 --rays 4000 --method fast --json",
               "twray trace --preset balsa --thickness-mm 1 --delta-ri 0.02 --exit air --out rays.nc"]),
    "study": ("Run parameter studies (the paper's Table 1) as a cached, incremental Dask graph: wood "
              "chunks, ray shards and summaries are cache entries, verified when read, and each study "
              "becomes results/<study>.zarr (an xarray Dataset). An unchanged rerun computes nothing.",
              ["twray study studies/table1/study-2.yaml --scale small",
               "twray study studies/table1/*.yaml --results results/paper --report results/paper/table1.md",
               "twray study my-study.yaml --scheduler-file scheduler.json --dry-run"]),
    "camera": ("Render what a thin-lens camera sees of an object through a TW sheet (the paper's Figure "
               "5): every pixel's aperture samples are traced through the sheet's wood, cached per image.",
               ["twray camera studies/camera/figure5.yaml --scale small",
                "twray camera studies/camera/figure5.yaml --workers 2 --results results/paper/camera"]),
    "figures": ("Draw the paper's figures from the result datasets: every Table 1 microstructure (sections "
                "and a 3D view), rays through 1.5 mm of birch, bar charts with intervals for every study, "
                "angle histograms with their Lorentz fits, and the camera images beside their ideal images.",
                ["twray figures", "twray figures --results results/small --out results/small/figures",
                 "twray figures --only studies,histograms"]),
    "report": ("Write the reproduction report (Markdown) from the result datasets: Table 1 with every "
               "interval, the trends as paired differences, the camera, the speed/accuracy trade and "
               "the commands that reproduce each item. Every number is read from a dataset.",
               ["twray report", "twray report --out /tmp/REPORT.md"]),
    "cache": ("List, verify or clean the cache of studies and the camera.",
              ["twray cache ls", "twray cache verify --remove",
               "twray cache gc studies/table1/*.yaml --scale paper --dry-run"]),
    "slices": ("Write PNG cross-sections of a volume in the R-T, L-T and L-R planes (one pixel per voxel, "
               "wall black) and an overview figure with axes in µm.",
               ["twray slices birch.zarr --out slices/"]),
    "export-tiff": ("Write one 8-bit TIFF per L slice (rows R, columns T, ImageJ metadata in µm), for ImageJ, "
                    "Fiji or Avizo.",
                    ["twray export-tiff birch.zarr --out tiff/"]),
    "info": ("Print a volume's shape, voxel size, origin, parameters and how many chunks are generated, "
             "as JSON.",
             ["twray info birch.zarr"]),
}


def _subparser(sub, name: str, help: str, **kwargs):
    """A subcommand whose --help has a description and examples."""
    import textwrap

    text, examples = EXAMPLES[name]
    epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    description = textwrap.fill(kwargs.pop("description", text), 88)
    return sub.add_parser(name, help=help, description=description, epilog=epilog,
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)


def _add_generate(sub):
    p = _subparser(sub, "generate", help="generate a wood microstructure volume (OME-Zarr)")
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
        value = float(text)
    except (TypeError, ValueError):
        raise ParameterError(f"`{name}` must be a number, got {name}={text!r}") from None
    if not math.isfinite(value):
        raise ParameterError(f"`{name}` must be a finite number, got {name}={text!r}")
    return value


CONNECT_TIMEOUT = "5s"  # a scheduler that does not answer by then is unreachable


def _connect(address=None, scheduler_file=None):
    """A client of a running Dask scheduler, or one line (ParameterError) if it cannot be reached."""
    from distributed import Client

    name, value = ("scheduler_file", scheduler_file) if scheduler_file is not None else ("scheduler", address)
    if scheduler_file is not None and not Path(scheduler_file).is_file():
        raise ParameterError(f"`scheduler_file` must be an existing scheduler file, got {scheduler_file!r}")
    try:
        if scheduler_file is not None:
            return Client(scheduler_file=scheduler_file, timeout=CONNECT_TIMEOUT)
        return Client(address, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as exc:
        reason = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise ParameterError(f"`{name}` must be a Dask scheduler that answers within {CONNECT_TIMEOUT}, "
                             f"got {name}={value!r} ({reason})") from None


@contextlib.contextmanager
def _generate_client(workers, scheduler):
    """A client of ``scheduler``, of a local cluster of ``workers`` processes, or None (the
    thread pool); the client and its local cluster are closed on leaving, workers stopped."""
    client = cluster = None
    if scheduler:
        client = _connect(scheduler)
    elif workers is not None:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def _materialise(args) -> int:
    """Generate in place the chunks a lazy twray volume does not hold yet."""
    from .microstructure.volume import WoodVolume

    if args.size_um is not None or args.lazy or args.overwrite:
        raise ParameterError("`--materialise` works on the existing store at --out: give no --size-um, "
                             "--lazy or --overwrite")
    out = _out_path(args.out)
    vol = WoodVolume.open(out)
    todo = len(vol.all_chunks()) - len(vol.generated_chunks())
    nvox = todo / max(1, len(vol.all_chunks())) * math.prod(vol.shape)
    est = limits.Estimate(nvox / limits.GENERATE_VOXELS_PER_CPU_S, limits.BASE_MEMORY,
                          nvox * limits.DISK_BYTES_PER_VOXEL)
    limits.check(est, what=f"`generate --materialise` of {todo} chunks", yes=args.yes, disk_path=out,
                 fit="keep the store lazy: twray generates chunks as they are read")
    workers = _int(args.workers, "workers", 1) if args.workers is not None else None
    t0 = time.perf_counter()
    with _generate_client(workers, args.scheduler) as client:
        n = vol.generate(scheduler=client, progress=progress_mode(args.quiet))
        vol.build_pyramid()
    print(f"{out}: {n} chunks generated in {time.perf_counter() - t0:.1f} s; all "
          f"{len(vol.all_chunks())} chunks are stored")
    return 0


def cmd_generate(args) -> int:
    from .microstructure.volume import WoodVolume, check_replaceable, publish, staged_path

    if args.materialise:
        return _materialise(args)
    if args.size_um is None:
        raise ParameterError("`size_um` is required (R,T,L in µm), unless --materialise")
    params = build_params(args.preset, args.config, parse_set(args.overrides))
    size = parse_triple(args.size_um, "size_um", positive=True)
    origin = parse_triple(args.origin_um, "origin_um", positive=False)
    chunks = parse_triple(args.chunks, "chunks", positive=True, integer=True)
    seed = _int(args.seed, "seed", 0)
    workers = _int(args.workers, "workers", 1) if args.workers is not None else None
    grid = make_grid(size, _float(args.voxel_um, "voxel_um"), origin, params)
    out = _out_path(args.out)
    check_replaceable(out, args.overwrite)
    from .cache import sweep_leftovers

    sweep_leftovers(out.parent)  # what generate runs interrupted before this one left
    nvox = math.prod(grid.shape)
    est = limits.Estimate(0.0, limits.BASE_MEMORY, 4096.0)
    if not args.lazy:
        est = limits.Estimate(nvox / limits.GENERATE_VOXELS_PER_CPU_S, limits.BASE_MEMORY,
                              nvox * limits.DISK_BYTES_PER_VOXEL)
    limits.check(est, what=f"`generate` of {nvox:.3g} voxels", yes=args.yes, disk_path=out.parent,
                 fit="use --lazy to generate chunks only when they are read, or a smaller --size-um")
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray generate: estimate {est.text()}", file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    t0 = time.perf_counter()
    try:
        vol = WoodVolume.create(staged, params, grid, seed=seed, chunks=chunks)
        n = 0
        if not args.lazy:
            # The workers stop on leaving, before the staged store is removed (they would
            # write into it again).
            with _generate_client(workers, args.scheduler) as client:
                n = vol.generate(scheduler=client, progress=progress_mode(args.quiet))
                vol.build_pyramid()
        publish(staged, out, args.overwrite)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    dt = time.perf_counter() - t0
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


def _add_trace(sub):
    p = _subparser(sub, "trace", help="trace a beam through a volume and report FWHM_R, FWHM_L, haze")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--volume", help="user volume: .npy, .zarr or a folder of TIFF slices "
                                      "(axes R, T, L; 1 = wall)")
    src.add_argument("--preset", help="generate wood lazily from this species preset")
    p.add_argument("--config", help="YAML file of wood parameters (with --preset)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one wood parameter (with --preset), e.g. --set wall_thickness_um=4 [µm]")
    p.add_argument("--thickness-mm", help="sample thickness along T [mm] (with --preset)")
    p.add_argument("--voxel-um", default="0.5", help="voxel size [µm]")
    p.add_argument("--delta-ri", required=True, help="RI of the wall minus RI of the polymer")
    p.add_argument("--ri-polymer", default="1.49", help="RI of the polymer (default 1.49)")
    p.add_argument("--rays", default="1000", help="number of rays in the beam (default 1000)")
    p.add_argument("--beam-um", default="150", help="side of the square beam footprint [µm]")
    p.add_argument("--beam-origin-um", default=None, help="beam centre R,L on the entrance face [µm]")
    p.add_argument("--incidence-deg", default=None,
                   help="beam direction in air as angles R,L [degree] of its projections on the R-T and "
                        "L-T planes from +T (default 0,0: perpendicular to the L-R face); the beam "
                        "refracts into the sample, and haze is measured from this direction")
    p.add_argument("--method", default="accurate", help="paper, fast or accurate")
    p.add_argument("--exit", default="internal", help="angles inside the sample (internal) or in air")
    p.add_argument("--fresnel", action="store_true", help="partial Fresnel reflection")
    p.add_argument("--step-vox", default=None, help="paper marching step [voxels] (default 2)")
    p.add_argument("--refine", default=None,
                   help="trace generated wood on voxels this many times smaller than --voxel-um "
                        "(default: the method's, 2 for accurate, 1 otherwise; a --volume is traced "
                        "on its own voxels)")
    p.add_argument("--seed", default="1", help="non-negative integer seed of the wood and the beam (default 1)")
    p.add_argument("--target-ci", default=None, metavar="HAZE",
                   help="trace until the 95 %% CI half-width of haze is at most HAZE (a fraction, e.g. 0.01): "
                        "--rays is the first batch, doubled up to --max-rays")
    p.add_argument("--target-ci-fwhm", default=None, metavar="DEG",
                   help="with or without --target-ci: also until the CI half-widths of FWHM_R and FWHM_L are at most DEG")
    p.add_argument("--max-rays", default="64000", help="most rays a --target-ci trace uses (default 64000)")
    p.add_argument("--out", default=None, help="per-ray dataset (.nc or .zarr)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.set_defaults(func=cmd_trace)


def cmd_trace(args) -> int:
    import json

    from .analysis import summarize
    from .optics.sources import ArraySource, WoodSource, load_volume
    from .optics.tracer import Beam, settings_for, square_beam, traced_voxel_um

    voxel = _float(args.voxel_um, "voxel_um")
    if not voxel > 0:
        raise ParameterError(f"`voxel_um` must be > 0 µm, got voxel_um={voxel:g}")
    if args.out is not None:
        args.out = str(_out_path(args.out))
        _check_rays_out(Path(args.out))
    dri = _float(args.delta_ri, "delta_ri")
    n_poly = _float(args.ri_polymer, "ri_polymer")
    n_wall = n_poly + dri
    if not (1.0 <= n_poly <= 3.0 and 1.0 <= n_wall <= 3.0):
        raise ParameterError(f"`delta_ri` and `ri_polymer` must give indices in [1, 3], got "
                             f"polymer {n_poly:g} and wall {n_wall:g}")
    rays = _int(args.rays, "rays", 1)
    target = _trace_target(args, rays)
    beam_um = _float(args.beam_um, "beam_um")
    if not beam_um > 0:
        raise ParameterError(f"`beam_um` must be > 0 µm, got beam_um={beam_um:g}")
    seed = _int(args.seed, "seed", 0)
    changes = {"exit": args.exit}
    if args.step_vox is not None:
        changes["step_vox"] = _float(args.step_vox, "step_vox")
    if args.fresnel:
        changes["fresnel"] = True
    if args.refine is not None:
        changes["refine"] = _int(args.refine, "refine", 1)
    settings = settings_for(args.method, **changes)
    if args.volume:
        if args.thickness_mm or args.overrides or args.config:
            raise ParameterError("`--thickness-mm`, `--set` and `--config` apply to --preset, not --volume")
        if settings.refine > 1 and args.refine is not None:
            raise ParameterError(f"`refine` applies to generated wood (--preset); a --volume has only its "
                                 f"own voxels, got refine={settings.refine}")
        settings = replace(settings, refine=1)
        source = ArraySource(load_volume(args.volume))
        centre = (source.shape[0] / 2.0, source.shape[2] / 2.0)
        wall_um = None
    else:
        if args.thickness_mm is None:
            raise ParameterError("`--thickness-mm` is required with --preset")
        thickness = _float(args.thickness_mm, "thickness_mm")
        if not thickness > 0:
            raise ParameterError(f"`thickness_mm` must be > 0, got thickness_mm={thickness:g}")
        params = build_params(args.preset, args.config, parse_set(args.overrides))
        make_grid((1.0, thickness * 1000.0, 1.0), voxel, (0.0, 0.0, 0.0), params)
        voxel = traced_voxel_um(voxel, settings)  # from here on, the voxels traced
        source = WoodSource(params, thickness_um=thickness * 1000.0, voxel_um=voxel, seed=seed,
                            threads=os.cpu_count() or 1)
        centre = (0.0, 0.0)
        wall_um = params.wall_thickness_um
    if args.beam_origin_um is not None:
        parts = args.beam_origin_um.split(",")
        if len(parts) != 2:
            raise ParameterError(f"`beam_origin_um` must be R,L [µm], got {args.beam_origin_um!r}")
        centre = (_float(parts[0], "beam_origin_um") / voxel, _float(parts[1], "beam_origin_um") / voxel)
    if settings.method == "paper" and wall_um is not None and settings.step_vox * voxel >= wall_um:
        raise ParameterError(f"`step_vox` must be smaller than the wall ({wall_um:g} µm = "
                             f"{wall_um / voxel:g} voxels), got step_vox={settings.step_vox:g}")
    _check_trace_limits(args, rays if target is None else target.max_rays, beam_um, voxel, settings, source, centre)
    incidence = _incidence(args.incidence_deg)
    direction = (math.tan(math.radians(incidence[0])), 1.0, math.tan(math.radians(incidence[1])))
    t0 = time.perf_counter()
    kwargs = dict(n_wall=n_wall, n_poly=n_poly, settings=settings, seed=seed,
                  n_outside=1.0 if args.incidence_deg is not None else None)
    beam = square_beam(rays, beam_um / voxel, centre, seed=seed, direction=direction)
    result = _trace_in_batches(source, beam, progress_mode(args.quiet), **kwargs)
    summary = summarize(result, seed=seed)
    while target is not None and not target.met(summary) and len(result.status) < target.max_rays:
        # The next rays of the same beam (each ray's position is a hash of the seed and its
        # index): the result equals one trace of that many rays.
        n = min(2 * len(result.status), target.max_rays)
        more = square_beam(n, beam_um / voxel, centre, seed=seed, direction=direction)
        lo = len(result.status)
        part = _trace_in_batches(source, Beam(more.origins[lo:], more.direction, more.ray_ids[lo:]),
                                 progress_mode(args.quiet), **kwargs)
        result = _concatenate([result, part])
        summary = summarize(result, seed=seed)
    elapsed = time.perf_counter() - t0
    if target is not None:
        summary["target_ci"] = target.to_dict()
        summary["target_ci_met"] = target.met(summary)
    summary.update({"refine": result.settings.refine, "traced_voxel_um": voxel,
                    "delta_ri": dri, "ri_polymer": n_poly, "incidence_deg": list(incidence),
                    "seconds": elapsed, "chunks_loaded": result.chunks_loaded})
    if not args.volume:  # the wood the trace needed, against what it read
        summary["voxels_generated"] = len(source.distinct) * math.prod(source.chunks)
    if args.out:
        inputs = {"volume": args.volume, "preset": args.preset, "config": args.config,
                  "params": None if args.volume else params.to_dict(),
                  "thickness_mm": None if args.volume else thickness, "voxel_um": _float(args.voxel_um, "voxel_um"),
                  "traced_voxel_um": voxel, "delta_ri": dri, "ri_polymer": n_poly, "rays": rays,
                  "beam_um": beam_um, "beam_centre_vox": list(centre), "incidence_deg": list(incidence),
                  "seed": seed, "settings": dataclasses.asdict(result.settings)}
        _write_rays(result, summary, voxel, args.out, inputs)
    if args.json:
        print(strict_json(summary))
    else:
        lo, hi = summary["haze_ci"]
        met = "" if target is None else (
            "; target_ci met" if summary["target_ci_met"] else f"; target_ci NOT met at max_rays {target.max_rays}")
        print(f"{summary['n_transmitted']}/{summary['n_rays']} transmitted "
              f"(method {summary['method']}, exit {summary['exit']}): "
              f"FWHM_R {summary['fwhm_r_deg']:.3f}°, FWHM_L {summary['fwhm_l_deg']:.3f}°, "
              f"haze {100 * summary['haze']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}], {elapsed:.1f} s{met}")
    return 0


def _trace_target(args, rays: int):
    """The precision ``--target-ci``/``--target-ci-fwhm`` ask for (None: trace ``--rays``)."""
    from .analysis import Target

    if args.target_ci is None and args.target_ci_fwhm is None:
        return None
    haze = fwhm = None
    if args.target_ci is not None:
        haze = _float(args.target_ci, "target_ci")
        if not 0 < haze <= 0.5:
            raise ParameterError(f"`target_ci` must be a haze half-width in (0, 0.5], got target_ci={haze:g}")
    if args.target_ci_fwhm is not None:
        fwhm = _float(args.target_ci_fwhm, "target_ci_fwhm")
        if not fwhm > 0:
            raise ParameterError(f"`target_ci_fwhm` must be > 0 degree, got target_ci_fwhm={fwhm:g}")
    cap = _int(args.max_rays, "max_rays", rays)
    return Target(haze=haze, fwhm_deg=fwhm, max_rays=cap)


TRACE_BATCHES = 40  # a long trace reports its progress batch by batch


def _trace_in_batches(source, beam, how: str, **kwargs):
    """``trace_beam`` over consecutive batches of the beam, as Dask tasks on the synchronous
    scheduler so that its progress shows (every ray is independent of the others: the result
    equals one call's, tested)."""
    import dataclasses

    import dask
    import numpy as np

    from .optics.tracer import Beam, trace_beam
    from .progress import LocalLines

    n = len(beam.ray_ids)
    size = max(500, math.ceil(n / TRACE_BATCHES))
    if how == "off" or n < 2 * size:
        return trace_beam(source, beam, **kwargs)
    parts = [dask.delayed(trace_beam, pure=False)(
        source, Beam(beam.origins[lo:lo + size], beam.direction, beam.ray_ids[lo:lo + size]), **kwargs)
        for lo in range(0, n, size)]
    with LocalLines("twray trace", how):
        parts = dask.compute(*parts, scheduler="sync")
    return _concatenate(parts)


def _concatenate(parts):
    """RayResults of consecutive parts of one beam as one."""
    import dataclasses

    import numpy as np

    merged = {f.name: np.concatenate([getattr(p, f.name) for p in parts])
              for f in dataclasses.fields(parts[0]) if isinstance(getattr(parts[0], f.name), np.ndarray)}
    return dataclasses.replace(parts[0], **merged, chunks_loaded=sum(p.chunks_loaded for p in parts))


def _check_trace_limits(args, rays, beam_um, voxel, settings, source, centre) -> None:
    """Refuse a beam that misses the volume or a trace that cannot fit (before any work)."""
    width = beam_um / voxel
    if args.volume:
        nr, nt, nl = source.shape
        if not (centre[0] - width / 2 >= 0 and centre[0] + width / 2 <= nr
                and centre[1] - width / 2 >= 0 and centre[1] + width / 2 <= nl):
            raise ParameterError(f"`beam_um` must fit the volume's R-L face ({nr * voxel:g} x {nl * voxel:g} µm) "
                                 f"around the beam's centre, got beam_um={beam_um:g}")
        thickness_um, pitch = nt * voxel, 14.5
    else:
        thickness_um, pitch = source.shape[1] * voxel, source.params.fibre_diameter_um
    est = limits.trace_estimate(rays=rays, beam_um=beam_um, thickness_um=thickness_um, voxel_um=voxel,
                                pitch_um=pitch, method=settings.method, wood=not args.volume)
    limits.check(est, what=f"`trace` of {rays} rays", yes=args.yes,
                 fit="trace fewer rays (--rays; a study traces them by shards), a narrower beam (--beam-um) "
                     "or a thinner sample")


def _incidence(text: str | None) -> tuple[float, float]:
    """The beam's angles (R, L) in air from --incidence-deg [degree]."""
    if text is None:
        return (0.0, 0.0)
    parts = text.split(",")
    if len(parts) != 2:
        raise ParameterError(f"`incidence_deg` must be two angles R,L [degree], got {text!r}")
    angles = tuple(_float(a, "incidence_deg") for a in parts)
    if not all(abs(a) < 90.0 for a in angles):
        raise ParameterError(f"`incidence_deg` angles must lie in (-90, 90) degrees, got {text!r}")
    return angles


def _write_rays(result, summary, voxel, out, inputs: dict):
    import numpy as np
    import xarray as xr

    from .optics.tracer import STATUS_NAMES

    codes = sorted(STATUS_NAMES)
    ds = xr.Dataset(
        {
            "theta_r": ("ray", result.theta_r, {"long_name": "exit angle in the R-T plane", "units": "degree"}),
            "theta_l": ("ray", result.theta_l, {"long_name": "exit angle in the L-T plane", "units": "degree"}),
            "exit_r": ("ray", result.position[:, 0] * voxel, {"long_name": "exit position R", "units": "um"}),
            "exit_l": ("ray", result.position[:, 2] * voxel, {"long_name": "exit position L", "units": "um"}),
            "direction": (("ray", "axis"), result.exit_direction, {"long_name": "exit direction (R, T, L)",
                                                                  "units": "1"}),
            "incident_direction": (("ray", "axis"), result.incident, {
                "long_name": "direction of the ray had nothing deflected it (haze is measured from it)",
                "units": "1"}),
            "path_length": ("ray", result.path * voxel, {"long_name": "geometric path length", "units": "um"}),
            "n_interfaces": ("ray", result.events.astype("int32"), {"long_name": "interfaces met"}),
            "status": ("ray", result.status.astype("int32"), {
                "long_name": "ray status", "flag_values": codes,
                "flag_meanings": " ".join(STATUS_NAMES[c] for c in codes)}),
        },
        coords={"ray": range(result.status.size), "axis": np.array(["R", "T", "L"], dtype=object)},
        attrs={"Conventions": "CF-1.10", "title": "twray per-ray trace result",
               "source": f"twray {__version__}", "summary": strict_json(summary)},
    )
    from .provenance import provenance_attrs

    ds.attrs.update(provenance_attrs(inputs))
    from .microstructure.volume import publish, staged_path

    out = Path(out)
    _check_rays_out(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    try:
        if out.suffix == ".zarr":
            from .study.run import write_zarr

            write_zarr(ds, staged)
            publish(staged, out, overwrite=True)
        else:
            ds.to_netcdf(staged, engine="scipy")
            os.replace(staged, out)
    finally:
        if staged.is_dir():
            shutil.rmtree(staged, ignore_errors=True)
        elif staged.exists():
            staged.unlink()


def _finite_or_none(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def strict_json(value) -> str:
    """JSON that strict parsers accept: NaN and infinities (an undefined fit) become null."""
    import json

    return json.dumps(_finite_or_none(value), allow_nan=False)


def _out_path(text: str, name: str = "out") -> Path:
    """An output path, absolute (the workers of a remote scheduler have their own working
    folder), whose folder exists or can be made and can be written (checked before any work)."""
    if not text or not text.strip():
        raise ParameterError(f"`{name}` must be a path, got {name}={text!r}")
    out = Path(text).absolute()
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ParameterError(f"`{name}` must be under a folder, got {name}={text!r} ({parent} is a file)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ParameterError(f"`{name}` must be in a folder you can write, got {name}={text!r} "
                             f"({parent} is read-only)")
    return out


def _check_rays_out(out: Path) -> None:
    """A per-ray result replaces only an earlier twray result: never another folder or file."""
    from .microstructure.volume import check_replaceable

    if out.suffix == ".zarr":
        check_replaceable(out, True)
        return
    if out.exists() or out.is_symlink():
        try:
            import xarray as xr

            with xr.open_dataset(out, engine="scipy") as old:
                ours = str(old.attrs.get("source", "")).startswith("twray ")
        except Exception:
            ours = False
        if not ours or not out.is_file():
            raise ParameterError(f"`out` exists and is not a result twray wrote: it is replaced only then, "
                                 f"got {str(out)!r}")


def _add_cluster_options(p) -> None:
    """Where study and camera graphs run, and their cache."""
    p.add_argument("--workers", default=None, help="local worker processes (study: dask's split of the cores, "
                                                   "2 on 2 cores; camera: 1, using every core)")
    p.add_argument("--threads", default=None, help="threads per local worker (default: cores / workers)")
    p.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    p.add_argument("--scheduler-file", default=None, help="scheduler file of a running Dask cluster")
    p.add_argument("--cache", default="results/cache", help="cache directory (default results/cache)")


def _add_study(sub):
    p = _subparser(sub, "study", help="run parameter studies (Table 1) into results/<study>.zarr")
    p.add_argument("files", nargs="+", metavar="FILE.yaml", help="study files, e.g. studies/table1/*.yaml")
    p.add_argument("--scale", default="paper", help="paper (the study's numbers) or small (quick)")
    _add_cluster_options(p)
    p.add_argument("--results", default="results", help="where <study>.zarr goes (default results)")
    p.add_argument("--shard-rays", default="250", help="rays per tracing task (default 250)")
    p.add_argument("--realisations", default=None,
                   help="wood realisations per value (default: the file's `realisations`, 5; at most 2 at "
                        "scale small)")
    p.add_argument("--method", default=None, help="trace with this method instead of the file's trace.method "
                                                  "(paper, fast, accurate)")
    p.add_argument("--rays", default=None, help="rays per value and realisation instead of the file's (not scaled)")
    p.add_argument("--dry-run", action="store_true", help="list each stage as cached or to compute")
    p.add_argument("--report", default=None, help="also write a Markdown table of every study here")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_study)


# glibc settings of the local cluster's worker processes, over Dask's own.
# Dask sets the trim threshold to 64 KiB, which also freezes the mmap
# threshold at 128 KiB: every chunk-sized array is then a fresh mmap whose
# pages fault in on first touch (Table 1 at paper scale: 43 million page
# faults, 15 % of its CPU time in the kernel).  Keep freed memory for reuse
# instead, up to 256 MiB.
WORKER_MALLOC = {"MALLOC_TRIM_THRESHOLD_": 256 << 20, "MALLOC_MMAP_THRESHOLD_": 64 << 20}


def _study_client(args, command: str = "study"):
    import os

    import dask
    from distributed import Client, LocalCluster
    from distributed.deploy.utils import nprocesses_nthreads

    if args.scheduler and args.scheduler_file:
        raise ParameterError("give either `--scheduler` or `--scheduler-file`, not both")
    if args.scheduler:
        return _connect(args.scheduler), None
    if args.scheduler_file:
        return _connect(scheduler_file=args.scheduler_file), None
    cores = os.cpu_count() or 1
    # A study's shards hold the GIL between kernel calls (chunk reads, the tracer's loop):
    # Table 1 small ran 1.6x faster on 2 processes than on 1 process of 2 threads
    # (results/BENCH.md), so a study starts dask's split of the cores into processes.
    # The camera's row tasks share wood chunks in one process's memory and keep one worker.
    default = nprocesses_nthreads(cores)[0] if command == "study" else 1
    workers = _int(args.workers, "workers", 1) if args.workers is not None else default
    threads = (_int(args.threads, "threads", 1) if args.threads is not None
               else max(1, cores // workers))
    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **WORKER_MALLOC}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True)
    return Client(cluster), cluster


def _absolute_paths(args) -> None:
    """The cache and results folders as absolute paths, resolved here on the client: the
    workers of a scheduler elsewhere have their own working folder."""
    for name in ("cache", "results"):
        value = str(_out_path(getattr(args, name), name))
        if Path(value).exists() and not Path(value).is_dir():
            raise ParameterError(f"`{name}` must be a folder, got {name}={value!r} (a file)")
        setattr(args, name, value)
    from .cache import sweep_leftovers

    # What runs interrupted before this one left half-written (removed unless still running).
    sweep_leftovers(args.results, *(Path(args.cache) / d for d in ("rays", "summary", "pool", "camera")))
    sweep_leftovers(Path(args.cache) / "micro", deep=True)  # chunk files too


@contextlib.contextmanager
def _cluster(args, command: str):
    """A Dask client for ``args`` (printing its dashboard), closed with its local cluster."""
    client, cluster = _study_client(args, command)
    try:
        print(f"twray {command}: dashboard {client.dashboard_link}", file=sys.stderr)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def cmd_study(args) -> int:
    from .study.run import (compute, describe_plan, plan_study, ray_sampling, report_table, summary_rows, widen,
                            write_dataset)
    from .study.spec import load_study

    shard_rays = _int(args.shard_rays, "shard_rays", 1)
    if args.workers is not None:
        _int(args.workers, "workers", 1)
    _absolute_paths(args)
    report = _out_path(args.report, "report") if args.report is not None else None
    if report is not None and report.is_dir():
        raise ParameterError(f"`report` must be a file path, got report={args.report!r} (a folder)")
    realisations = None if args.realisations is None else _int(args.realisations, "realisations", 1)
    rays = None if args.rays is None else _int(args.rays, "rays", 1)
    studies = [load_study(f, scale=args.scale, realisations=realisations, method=args.method, rays=rays)
               for f in args.files]
    names = [s.name for s in studies]
    if len(set(names)) != len(names):
        raise ParameterError(f"study files must have distinct names, got {names}")
    # What could never fit is refused before planning (which lists the wood's chunks).
    scenes = [sc for st in studies for sc in st.all_scenes()]
    fit = "use fewer rays, a narrower beam, larger voxels or a thinner sample"
    est = limits.study_estimate(scenes, shard_rays=shard_rays)
    limits.check(est, what="`study`", yes=True, disk_path=args.cache, fit=fit)
    t0 = time.perf_counter()
    plans = [plan_study(s, args.cache, shard_rays=shard_rays) for s in studies]
    todo = [plan.study.realisation(summ.scene_index, summ.realisation)
            for plan in plans for summ in plan.summaries if not summ.cached]
    est = limits.study_estimate(todo, shard_rays=shard_rays)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray study: estimate for the {len(todo)} value{'' if len(todo) == 1 else 's'} to compute: "
              f"{est.text()}", file=sys.stderr)
    if args.dry_run:
        for plan in plans:
            print("\n".join(describe_plan(plan)))
        return 0
    limits.check(est, what="`study`", yes=args.yes, disk_path=args.cache, fit=fit)
    with contextlib.ExitStack() as stack:
        client = None
        while True:
            if not all(p.up_to_date for p in plans):
                if client is None:
                    client = stack.enter_context(_cluster(args, "study"))
                compute(plans, client, progress=progress_mode(args.quiet))
                plans = [plan_study(p.study, args.cache, shard_rays=shard_rays) for p in plans]
            # A study with a `target_ci` is traced again with twice the rays until it is met.
            wider = [widen(p) for p in plans]
            if not any(wider):
                break
            for st in wider:
                if st is not None:
                    print(f"twray study: {st.name}: an interval is wider than target_ci; "
                          f"tracing {st.scenes[0].rays} rays", file=sys.stderr)
            plans = [plan_study(w, args.cache, shard_rays=shard_rays) if w is not None else p
                     for w, p in zip(wider, plans)]
    for plan in plans:
        out = write_dataset(plan, args.results)
        st = plan.study
        target = st.scenes[0].target
        met = "" if target is None else (
            ", target_ci met" if all(target.met(ray_sampling(r)) for r in summary_rows(plan)) else
            f", target_ci NOT met at max_rays {target.max_rays}")
        print(f"{out}: {st.title} (scale {st.scale}, {st.scenes[0].rays} rays x {st.realisations} "
              f"realisation{'' if st.realisations == 1 else 's'}, {st.scenes[0].settings.method}{met})")
        for row in summary_rows(plan):
            print(f"  {st.dimension}={row['value']}: FWHM_R {row['fwhm_r_deg']:.2f}°, "
                  f"FWHM_L {row['fwhm_l_deg']:.2f}°, haze {100 * row['haze']:.1f} % "
                  f"[{100 * row['haze_ci'][0]:.1f}, {100 * row['haze_ci'][1]:.1f}], "
                  f"{row['n_transmitted']}/{row['n_rays']} transmitted")
    if report is not None:
        from .cache import atomic_write

        atomic_write(report, lambda tmp: tmp.write_text(report_table(plans)))
        print(f"wrote {report}")
    print(f"{len(plans)} studies in {time.perf_counter() - t0:.1f} s")
    return 0


def _add_camera(sub):
    p = _subparser(sub, "camera", help="render images through a TW sheet with a thin-lens camera")
    p.add_argument("file", metavar="FILE.yaml", help="camera file, e.g. studies/camera/figure5.yaml")
    p.add_argument("--scale", default="paper", help="paper (the file's numbers) or small (quick)")
    _add_cluster_options(p)
    p.add_argument("--results", default="results/camera",
                   help="where the Dataset and PNGs go (default results/camera)")
    p.add_argument("--rows-per-task", default="3", help="sensor rows per rendering task (default 3)")
    p.add_argument("--dry-run", action="store_true", help="list each image as cached or to render")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_camera)


def cmd_camera(args) -> int:
    from .camera.run import compute, load_entry, plan_camera, write_outputs
    from .camera.scene import load_camera

    rows = _int(args.rows_per_task, "rows_per_task", 1)
    if args.workers is not None:
        _int(args.workers, "workers", 1)
    _absolute_paths(args)
    study = load_camera(args.file, scale=args.scale)
    fit = "use fewer pixels or samples, a smaller or thinner sheet, or larger voxels"
    limits.check(limits.camera_estimate(study.images), what="`camera`", yes=True, disk_path=args.cache, fit=fit)
    t0 = time.perf_counter()
    entries = plan_camera(study, args.cache)
    todo = [e.config for e in entries if not e.cached]
    est = limits.camera_estimate(todo)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray camera: estimate for the {len(todo)} image{'' if len(todo) == 1 else 's'} to render "
              f"(the sheet's wood counted whole): {est.text()}", file=sys.stderr)
    if args.dry_run:
        for e in entries:
            print(f"{study.name} {e.config.name}: {'cached' if e.cached else 'to render'} ({e.key[:12]})")
        return 0
    limits.check(est, what="`camera`", yes=args.yes, disk_path=args.cache, fit=fit)
    if not all(e.cached for e in entries):
        with _cluster(args, "camera") as client:
            compute(entries, client, args.cache, rows_per_task=rows, progress=progress_mode(args.quiet))
        entries = plan_camera(study, args.cache)
    paths = write_outputs(study, entries, args.results)
    print(f"{paths[0]}: {study.title} (scale {study.scale}, {study.images[0].camera.samples} "
          f"samples per pixel, {study.images[0].settings.method})")
    for e in entries:
        d = load_entry(e)
        c = e.config
        n = d["image"].size * c.camera.samples
        print(f"  {c.name}: f {c.camera.focal_mm:g} mm, m {c.camera.magnification:.4g}, "
              + ("no sheet" if c.sheet is None else
                 f"ΔRI {c.sheet.ri_wall - c.sheet.ri_polymer:.3g}, gap {c.sheet.gap_um:g} µm, "
                 f"{float(d['interfaces_per_ray']):.1f} interfaces/ray")
              + f", {int(d['lost'].sum())}/{n} samples lost")
    print(f"wrote {len(paths)} files under {Path(args.results)} in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_slices(args) -> int:
    from .microstructure.export import write_slices
    from .microstructure.volume import WoodVolume

    args.out = str(_out_path(args.out))
    for path in write_slices(WoodVolume.open(args.volume), args.out):
        print(path)
    return 0


def cmd_export_tiff(args) -> int:
    from .microstructure.export import write_tiff_stack
    from .microstructure.volume import WoodVolume

    args.out = str(_out_path(args.out))
    vol = WoodVolume.open(args.volume)
    nvox = math.prod(vol.shape)
    todo = 1.0 - len(vol.generated_chunks()) / max(1, math.prod(vol.chunk_grid))
    # Uncompressed 8-bit slices, and the chunks a lazy volume has not generated yet.
    est = limits.Estimate(todo * nvox / limits.GENERATE_VOXELS_PER_CPU_S, limits.BASE_MEMORY,
                          nvox + todo * nvox * limits.DISK_BYTES_PER_VOXEL)
    limits.check(est, what=f"`export-tiff` of {nvox:.3g} voxels", yes=args.yes, disk_path=args.out,
                 fit="export a smaller volume (generate one with a smaller --size-um)")
    paths = write_tiff_stack(vol, args.out)
    print(f"wrote {len(paths)} TIFF slices (one per L) to {args.out}")
    return 0


def cmd_info(args) -> int:
    from .microstructure.volume import describe

    print(describe(args.volume))
    return 0


def _add_cache(sub):
    p = _subparser(
        sub, "cache", help="list, verify or clean the cache of studies and the camera",
        description="Every cache entry (wood chunk store, ray shard, summary, camera image) is named by "
                    "the key of what produced it and carries a digest of its content. `ls` lists them with "
                    "their size and provenance, `verify` checks every one (exit 1 if any is damaged; a "
                    "study recomputes damaged entries by itself), `gc` removes what the given study and "
                    "camera files do not use, and what interrupted runs left.")
    p.add_argument("action", choices=("ls", "verify", "gc"), help="ls, verify or gc")
    p.add_argument("files", nargs="*", metavar="FILE.yaml",
                   help="gc: the study and camera files whose entries are kept (default: every .yaml under "
                        "studies/)")
    p.add_argument("--cache", default="results/cache", help="cache directory (default results/cache)")
    p.add_argument("--scale", action="append", default=None,
                   help="gc: scale whose entries are kept, repeatable (default: paper and small)")
    p.add_argument("--dry-run", action="store_true", help="gc: list what would be removed, remove nothing")
    p.add_argument("--remove", action="store_true", help="verify: also remove the damaged entries")
    p.add_argument("--json", action="store_true", help="ls: one JSON object per line")
    p.set_defaults(func=cmd_cache)


def cmd_cache(args) -> int:
    import json

    from . import inventory

    cache = Path(args.cache)
    if args.action != "gc" and (args.files or args.scale or args.dry_run):
        raise ParameterError(f"`{args.action}` takes no study files, --scale or --dry-run (those are gc's)")
    if not cache.is_dir():
        raise ParameterError(f"`cache` must be an existing folder, got cache={str(cache)!r}")
    entries = inventory.scan(cache)
    if args.action == "ls":
        for e in entries:
            if args.json:
                print(json.dumps({"stage": e.stage, "key": e.key, "bytes": e.size, "path": str(e.path),
                                  "about": e.about}))
            else:
                print(f"{e.stage:8s} {e.key or '-':24s} {limits.size(e.size):>9s}  {e.about or e.path.name}")
        total = sum(e.size for e in entries)
        print(f"{len(entries)} entries, {limits.size(total)} in {cache}", file=sys.stderr)
        return 0
    if args.action == "verify":
        damaged = 0
        for e in entries:
            for path, why in inventory.verify(e):
                print(f"{path}: {why}")
                damaged += 1
                if args.remove:
                    inventory.remove(path)
        print(f"{len(entries)} entries verified, {damaged} damaged"
              f"{' (removed)' if args.remove and damaged else ''}", file=sys.stderr)
        return 1 if damaged else 0
    files = args.files or sorted(str(f) for f in Path("studies").rglob("*.yaml"))
    if not files:
        raise ParameterError("`files` must name the study and camera files whose entries to keep "
                             "(no studies/ folder here)")
    scales = args.scale or ["paper", "small"]
    keep = inventory.keys_in_use(files, scales, cache)
    # Only twray's own entries are removed: anything else found there is named and left.
    for e in entries:
        if e.stage == "unknown":
            print(f"left alone {e.path} (not a twray cache entry)")
    drop = [e for e in entries if e.stage == "leftover" or (e.stage in inventory.STAGES and e.key not in keep)]
    for e in drop:
        print(f"{'would remove' if args.dry_run else 'removed'} {e.path} ({limits.size(e.size)})")
        if not args.dry_run:
            inventory.remove(e.path)
    kept = len(entries) - len(drop)
    print(f"{len(drop)} entries ({limits.size(sum(e.size for e in drop))}) "
          f"{'to remove' if args.dry_run else 'removed'}, {kept} kept", file=sys.stderr)
    return 0


FIGURE_KINDS = ("microstructure", "trajectories", "studies", "histograms", "camera")


def _add_figures(sub):
    p = _subparser(sub, "figures", help="draw the paper's figures from the result datasets")
    p.add_argument("--results", default="results/paper",
                   help="the scale's results folder holding study-*.zarr and camera/ (default results/paper)")
    p.add_argument("--out", default="results/figures", help="where the PNGs go (default results/figures)")
    p.add_argument("--only", default=None, help=f"comma-separated subset of {','.join(FIGURE_KINDS)}")
    p.set_defaults(func=cmd_figures)
    p = _subparser(sub, "report", help="write the reproduction report from the result datasets")
    p.add_argument("--results", default="results", help="the results folder (default results)")
    p.add_argument("--scale", default="paper", help="whose datasets: results/<scale>/ (default paper)")
    p.add_argument("--out", default="results/REPORT.md", help="the report (default results/REPORT.md)")
    p.set_defaults(func=cmd_report)


def _need(path: Path, field: str, value: str, command: str) -> None:
    if not path.exists():
        raise ParameterError(f"`{field}` must hold {path.name} (run `{command}` first), got {field}={value!r}")


def cmd_figures(args) -> int:
    from .figures import TABLE1, make_figures

    which = None
    if args.only is not None:
        which = {w.strip() for w in args.only.split(",") if w.strip()}
        bad = sorted(which - set(FIGURE_KINDS))
        if bad or not which:
            raise ParameterError(f"`only` must name some of {', '.join(FIGURE_KINDS)}, got only={args.only!r}")
    results = Path(args.results)
    kinds = which or set(FIGURE_KINDS)
    if kinds & {"studies", "histograms"}:
        for name in (TABLE1 if "studies" in kinds else ("study-1",)):
            _need(results / f"{name}.zarr", "results", args.results, "make table1")
    if "camera" in kinds:
        _need(results / "camera" / "figure5.zarr", "results", args.results, "make camera")
    out = _out_path(args.out, "out")
    t0 = time.perf_counter()
    made = make_figures(results, out, which=which)
    print(f"{len(made)} figures in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_report(args) -> int:
    from .cache import atomic_write
    from .report import TABLE1, build_report, figure_links

    results = Path(args.results)
    base = results / args.scale
    for name in TABLE1:
        _need(base / f"{name}.zarr", "results", args.results, f"make table1 SCALE={args.scale}")
    _need(base / "camera" / "figure5.zarr", "results", args.results, f"make camera SCALE={args.scale}")
    for name in ("birch-0.7mm", "birch-0.7mm-air", "balsa-1mm", "balsa-1mm-air"):
        _need(base / "experiment" / f"{name}.zarr", "results", args.results, f"make experiment SCALE={args.scale}")
    for name in TABLE1:
        _need(base / "paper-method" / f"{name}.zarr", "results", args.results,
              f"make table1-paper-method SCALE={args.scale}")
    _need(results / "tradeoff.zarr", "results", args.results, "make tradeoff")
    _need(results / "bench.json", "results", args.results, "make bench")
    out = _out_path(args.out, "out")
    text = build_report(results, scale_dir=args.scale)
    atomic_write(out, lambda tmp: tmp.write_text(text))
    missing = [f for f in figure_links(text) if not (out.parent / f).exists()]
    print(f"wrote {out}")
    if missing:
        print(f"twray report: {len(missing)} linked figures do not exist yet (run `make figures`): "
              f"{', '.join(missing)}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="twray", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"twray {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_generate(sub)
    _add_trace(sub)
    _add_study(sub)
    _add_camera(sub)
    _add_cache(sub)
    _add_figures(sub)
    p = _subparser(sub, "slices", help="PNG cross-sections in the R-T, L-T and L-R planes")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_slices)
    p = _subparser(sub, "export-tiff", help="one TIFF per L slice, for ImageJ/Avizo")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_export_tiff)
    p = _subparser(sub, "info", help="print a volume's shape, parameters and generated chunks")
    p.add_argument("volume", help="a twray volume (.zarr)")
    p.set_defaults(func=cmd_info)
    return parser


def _terminated(signum, frame):
    raise KeyboardInterrupt  # a kill (SIGTERM) cleans up like Ctrl-C: staged outputs are removed


def main(argv: list[str] | None = None) -> int:
    log_to_stderr()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except ParameterError as exc:
        print(f"twray: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("twray: interrupted; nothing half-written is left (studies and the camera resume from their "
              "cache)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # the filesystem refused (disk full, permissions): one line, not a traceback
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        print(f"twray: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
