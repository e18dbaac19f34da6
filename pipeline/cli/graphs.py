"""``twray study`` and ``twray camera``: Dask graphs on a local or running cluster."""

from __future__ import annotations

import sys
from pathlib import Path

from .. import limits
from ..cluster import memory_limit
from ..progress import mode as progress_mode
from ..params import ParameterError
from .args import YES_HELP, integer, out_path, subparser


def add_cluster_options(p) -> None:
    """Where study and camera graphs run, and their cache."""
    p.add_argument("--workers", default=None, help="local worker processes (study: dask's split of the cores, "
                                                   "2 on 2 cores; camera: 1, using every core)")
    p.add_argument("--threads", default=None, help="threads per local worker (default: cores / workers)")
    p.add_argument("--memory-limit", default=None,
                   help="memory per local worker, e.g. 2GB (default: the machine's memory / workers); a worker "
                        "past it is restarted and its task retried")
    p.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    p.add_argument("--scheduler-file", default=None, help="scheduler file of a running Dask cluster")
    p.add_argument("--cache", default="results/cache", help="cache directory (default results/cache)")


def add_study(sub):
    p = subparser(sub, "study", help="run parameter studies (Table 1) into results/<study>.zarr")
    p.add_argument("files", nargs="+", metavar="FILE.yaml", help="study files, e.g. studies/table1/*.yaml")
    p.add_argument("--scale", default="paper", help="paper (the study's numbers), quick (the same samples and "
                                                     "woods, a twentieth of the rays) or small (a tenth of the "
                                                     "thickness; tests)")
    add_cluster_options(p)
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


def _absolute_paths(args) -> None:
    """The cache and results folders as absolute paths, resolved here on the client: the
    workers of a scheduler elsewhere have their own working folder."""
    for name in ("cache", "results"):
        value = str(out_path(getattr(args, name), name))
        if Path(value).exists() and not Path(value).is_dir():
            raise ParameterError(f"`{name}` must be a folder, got {name}={value!r} (a file)")
        setattr(args, name, value)
    from .. import runlog
    from ..cache import sweep_leftovers

    runlog.start(args.cache)

    # What runs interrupted before this one left half-written (removed unless still running).
    sweep_leftovers(args.results, *(Path(args.cache) / d for d in ("rays", "summary", "pool", "camera")))
    sweep_leftovers(Path(args.cache) / "micro", deep=True)  # chunk files too


def _cluster(args, command: str):
    """The cluster ``args`` ask for (``--workers``, ``--threads``, ``--memory-limit``, ``--scheduler``,
    ``--scheduler-file``); its logs go to the run's log file under ``--cache``."""
    from ..cluster import cluster

    return cluster(command, quiet=args.quiet,
                   workers=None if args.workers is None else integer(args.workers, "workers", 1),
                   threads=None if args.threads is None else integer(args.threads, "threads", 1),
                   memory=memory_limit(args.memory_limit), scheduler=args.scheduler,
                   scheduler_file=args.scheduler_file)


def _workers(args, command: str) -> int:
    """The local workers the command starts (none with a running scheduler)."""
    from ..cluster import local_workers

    if args.scheduler or args.scheduler_file:
        return 0
    return local_workers(command, None if args.workers is None else integer(args.workers, "workers", 1))


def _started(args, command: str) -> "limits.Estimate":
    """The command and the local workers it starts."""
    return limits.startup(1 + _workers(args, command))


def cmd_study(args) -> int:
    from ..study.run import StudyRequest, describe, run

    shard_rays = integer(args.shard_rays, "shard_rays", 1)
    if args.workers is not None:
        integer(args.workers, "workers", 1)
    _absolute_paths(args)
    memory_limit(args.memory_limit)
    report = out_path(args.report, "report") if args.report is not None else None
    if report is not None and report.is_dir():
        raise ParameterError(f"`report` must be a file path, got report={args.report!r} (a folder)")
    request = StudyRequest(
        files=tuple(args.files), cache=args.cache, results=args.results, scale=args.scale, shard_rays=shard_rays,
        realisations=None if args.realisations is None else integer(args.realisations, "realisations", 1),
        method=args.method, rays=None if args.rays is None else integer(args.rays, "rays", 1),
        dry_run=args.dry_run, yes=args.yes, report=report, progress=progress_mode(args.quiet),
        started=_started(args, "study"), workers=_workers(args, "study"))
    outcome = run(request, open_client=lambda: _cluster(args, "study"))
    print("\n".join(describe(outcome)))
    return 0


def add_camera(sub):
    p = subparser(sub, "camera", help="render images through a TW sheet with a thin-lens camera")
    p.add_argument("file", metavar="FILE.yaml", help="camera file, e.g. studies/camera/figure5.yaml")
    p.add_argument("--scale", default="paper", help="paper (the file's numbers), quick (a tenth of the aperture "
                                                     "samples) or small (also a fifth of the sheet)")
    add_cluster_options(p)
    p.add_argument("--results", default="results/camera",
                   help="where the Dataset and PNGs go (default results/camera)")
    p.add_argument("--method", default=None, help="trace the sheet with this method instead of the file's "
                                                   "trace.method (exact, fast, accurate, paper)")
    p.add_argument("--rows-per-task", default="3", help="sensor rows per rendering task (default 3)")
    p.add_argument("--dry-run", action="store_true", help="list each image as cached or to render")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.set_defaults(func=cmd_camera)


def cmd_camera(args) -> int:
    from ..camera.run import CameraRequest, describe, render

    rows = integer(args.rows_per_task, "rows_per_task", 1)
    if args.workers is not None:
        integer(args.workers, "workers", 1)
    _absolute_paths(args)
    memory_limit(args.memory_limit)
    request = CameraRequest(file=args.file, cache=args.cache, results=args.results, scale=args.scale,
                            method=args.method, rows_per_task=rows, dry_run=args.dry_run, yes=args.yes,
                            progress=progress_mode(args.quiet), started=_started(args, "camera"),
                            workers=_workers(args, "camera"))
    outcome = render(request, open_client=lambda: _cluster(args, "camera"),
                     log=lambda line: print(line, file=sys.stderr))
    print("\n".join(describe(outcome, args.results)))
    return 0
