"""``twray study`` and ``twray camera``: Dask graphs on a local or running cluster."""

from __future__ import annotations

import sys
import time
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


def _started(args, command: str) -> "limits.Estimate":
    """The command and the local workers it starts (none with a running scheduler)."""
    from ..cluster import local_workers

    if args.scheduler or args.scheduler_file:
        return limits.startup(1)
    return limits.startup(1 + local_workers(command, None if args.workers is None else
                                            integer(args.workers, "workers", 1)))


def cmd_study(args) -> int:
    from ..study.dataset import write_dataset
    from ..study.plan import describe_plan, plan_study, report_table, summary_rows, target_met
    from ..study.run import run_studies
    from ..study.spec import at_target_cap, load_study

    shard_rays = integer(args.shard_rays, "shard_rays", 1)
    if args.workers is not None:
        integer(args.workers, "workers", 1)
    _absolute_paths(args)
    memory_limit(args.memory_limit)
    report = out_path(args.report, "report") if args.report is not None else None
    if report is not None and report.is_dir():
        raise ParameterError(f"`report` must be a file path, got report={args.report!r} (a folder)")
    realisations = None if args.realisations is None else integer(args.realisations, "realisations", 1)
    rays = None if args.rays is None else integer(args.rays, "rays", 1)
    studies = [load_study(f, scale=args.scale, realisations=realisations, method=args.method, rays=rays)
               for f in args.files]
    names = [s.name for s in studies]
    if len(set(names)) != len(names):
        raise ParameterError(f"study files must have distinct names, got {names}")
    unused = [s.name for s in studies if "voxel_um" in s.unused]
    if unused:
        print(f"twray study: `voxel_um` is unused in {', '.join(unused)}: method exact traces the model's own "
              "surfaces, no voxels (it applies with --method fast, accurate or paper)", file=sys.stderr)
    # What could never fit is refused before planning (which lists the wood's chunks).
    # A target over woods may trace up to its cap of woods (over rays, study_estimate takes its cap of rays).
    scenes = [sc for st in studies for sc in at_target_cap(st).all_scenes()]
    fit = "use fewer rays, a narrower beam, larger voxels or a thinner sample"
    started = _started(args, "study")
    est = started + limits.study_estimate(scenes, shard_rays=shard_rays)
    limits.check(est, what="`study`", yes=True, disk_path=args.cache, fit=fit)
    t0 = time.perf_counter()
    plans = [plan_study(s, args.cache, shard_rays=shard_rays) for s in studies]
    todo = [plan.study.realisation(summ.scene_index, summ.realisation)
            for plan in plans for summ in plan.summaries if not summ.cached]
    more = [sc for st in studies for sc in at_target_cap(st).all_scenes() if sc.realisation >= st.realisations]
    est = started + limits.study_estimate(todo + more, shard_rays=shard_rays)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        upto = f" (up to {len(more)} more at the targets' caps of woods)" if more else ""
        print(f"twray study: estimate for the {len(todo)} value{'' if len(todo) == 1 else 's'} to compute{upto}: "
              f"{est.text()}", file=sys.stderr)
    if args.dry_run:
        for plan in plans:
            print("\n".join(describe_plan(plan)))
        return 0
    limits.check(est, what="`study`", yes=args.yes, disk_path=args.cache, fit=fit)
    plans = run_studies(plans, args.cache, open_client=lambda: _cluster(args, "study"), shard_rays=shard_rays,
                        progress=progress_mode(args.quiet), log=lambda line: print(line, file=sys.stderr))
    for plan in plans:
        out = write_dataset(plan, args.results)
        st = plan.study
        target = st.scenes[0].target
        cap = f"max_realisations {target.max_realisations}" if target and target.over == "woods" else (
            f"max_rays {target.max_rays}" if target else "")
        unmet = (f", target_ci NOT met at {cap}" if st.scale == "paper"
                 else f", target_ci not met at the {st.scale} scale's {cap}")
        met = "" if target is None else (
            ", target_ci met" if target_met(target, summary_rows(plan)) else unmet)
        print(f"{out}: {st.title} (scale {st.scale}, {st.scenes[0].rays} rays x {st.realisations} "
              f"realisation{'' if st.realisations == 1 else 's'}, {st.scenes[0].settings.method}{met})")
        for row in summary_rows(plan):
            traced = "" if st.scale == "paper" else f" ({row['thickness_traced_mm']:g} mm traced)"
            print(f"  {row['label']}{traced}: FWHM_R {row['fwhm_r_deg']:.2f}°, "
                  f"FWHM_L {row['fwhm_l_deg']:.2f}°, haze {100 * row['haze']:.1f} % "
                  f"[{100 * row['haze_ci'][0]:.1f}, {100 * row['haze_ci'][1]:.1f}], "
                  f"{row['n_transmitted']}/{row['n_rays']} transmitted")
    if report is not None:
        from ..cache import atomic_write

        atomic_write(report, lambda tmp: tmp.write_text(report_table(plans)))
        print(f"wrote {report}")
    print(f"{len(plans)} studies in {time.perf_counter() - t0:.1f} s")
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
    from ..camera.run import compute, load_entry, plan_blocks, plan_camera, write_outputs
    from ..camera.scene import load_camera

    rows = integer(args.rows_per_task, "rows_per_task", 1)
    if args.workers is not None:
        integer(args.workers, "workers", 1)
    _absolute_paths(args)
    memory_limit(args.memory_limit)
    study = load_camera(args.file, scale=args.scale, method=args.method)
    fit = "use fewer pixels or samples, a smaller or thinner sheet, or larger voxels"
    started = _started(args, "camera")
    limits.check(started + limits.camera_estimate(study.images), what="`camera`", yes=True, disk_path=args.cache, fit=fit)
    t0 = time.perf_counter()
    entries = plan_camera(study, args.cache)
    todo = [e for e in entries if not e.cached]
    blocks = {e.key: plan_blocks(e, args.cache, rows) for e in todo}  # an interrupted run's are kept
    left = [sum(b.hi - b.lo for b in blocks[e.key] if not b.cached) for e in todo]
    est = started + limits.camera_estimate([e.config for e in todo], rows=left)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        print(f"twray camera: estimate for the {len(todo)} image{'' if len(todo) == 1 else 's'} to render "
              f"(the part of the sheet its rays reach): {est.text()}", file=sys.stderr)
    if args.dry_run:
        for e in entries:
            done = sum(b.cached for b in blocks.get(e.key, ()))
            state = "cached" if e.cached else "to render" + (f", {done} of {len(blocks[e.key])} row blocks "
                                                             "done" if done else "")
            print(f"{study.name} {e.config.name}: {state} ({e.key[:12]})")
        return 0
    limits.check(est, what="`camera`", yes=args.yes, disk_path=args.cache, fit=fit)
    if not all(e.cached for e in entries):
        resumed = sum(b.cached for bs in blocks.values() for b in bs)
        if resumed:
            print(f"twray camera: {resumed} of {sum(len(bs) for bs in blocks.values())} row blocks were "
                  "rendered by an earlier run and are read, not rendered", file=sys.stderr)
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
