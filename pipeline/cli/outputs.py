"""``twray cache``, ``figures`` and ``report``: what the runs left, checked, drawn and written up."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ..params import ParameterError
from .args import out_path, subparser


def add_cache(sub):
    p = subparser(
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
                   help="gc: scale whose entries are kept, repeatable (default: every scale)")
    p.add_argument("--dry-run", action="store_true", help="gc: list what would be removed, remove nothing")
    p.add_argument("--remove", action="store_true", help="verify: also remove the damaged entries")
    p.add_argument("--json", action="store_true", help="ls: one JSON object per line")
    p.set_defaults(func=cmd_cache)


def cmd_cache(args) -> int:
    from .. import inventory

    request = inventory.CacheRequest(args.action, Path(args.cache), tuple(args.files),
                                     tuple(args.scale) if args.scale else None, args.dry_run, args.remove)
    outcome = inventory.run(request)
    lines, total = inventory.describe(outcome, as_json=args.json)
    for line in lines:
        print(line)
    print(total, file=sys.stderr)
    return outcome.exit_code


FIGURE_KINDS = ("microstructure", "trajectories", "studies", "histograms", "camera", "design", "wave")


def add_figures(sub):
    p = subparser(sub, "figures", help="draw the paper's figures from the result datasets")
    p.add_argument("--results", default="results/paper",
                   help="the scale's results folder holding study-*.zarr and camera/ (default results/paper)")
    p.add_argument("--out", default="results/figures", help="where the PNGs go (default results/figures)")
    p.add_argument("--only", default=None, help=f"comma-separated subset of {','.join(FIGURE_KINDS)}")
    p.set_defaults(func=cmd_figures)
    p = subparser(sub, "report", help="write the reproduction report from the result datasets")
    p.add_argument("--results", default="results", help="the results folder (default results)")
    p.add_argument("--scale", default="paper", help="whose datasets: results/<scale>/ (default paper)")
    p.add_argument("--out", default="results/REPORT.md", help="the report (default results/REPORT.md)")
    p.set_defaults(func=cmd_report)


def add_design(sub):
    p = subparser(sub, "design", help="the ΔRI window that keeps haze below a limit, or haze and FWHM_R at one "
                                      "ΔRI, from the design maps")
    p.add_argument("--preset", default="birch", choices=("birch", "balsa"), help="species (default birch)")
    p.add_argument("--exit", default="internal", choices=("internal", "air"),
                   help="haze of the angles inside the sample (the paper's) or in air (a hazemeter's)")
    p.add_argument("--thickness-mm", required=True, help="sample thickness [mm], within the map's")
    p.add_argument("--haze-max", default=None, help="the haze limit, a fraction (0.2: 20 %%): the ΔRI window")
    p.add_argument("--delta-ri", default=None, help="wall minus polymer index: haze and FWHM_R there, inside the "
                                                    "sample and in air (both maps, unless --map names one)")
    p.add_argument("--results", default="results/paper", help="where design/<map>.zarr is (default results/paper)")
    p.add_argument("--map", default=None, help="a design map Dataset (default: the preset's and exit's under --results)")
    p.set_defaults(func=cmd_design)


def cmd_design(args) -> int:
    import json

    from ..design import map_name, open_map, reading_line, regime_line, window_line
    from .args import number

    thickness = number(args.thickness_mm, "thickness_mm")
    if args.haze_max is None and args.delta_ri is None:
        raise ParameterError("`haze_max` or `delta_ri` must be given: the ΔRI window below a haze limit, or haze "
                             "and FWHM_R at one ΔRI (e.g. --haze-max 0.2, --delta-ri 0.005)")
    results = Path(args.results)
    if args.delta_ri is not None:
        delta_ri = number(args.delta_ri, "delta_ri")
        exits = (args.exit,) if args.map else ("internal", "air")
        for exit in exits:
            if args.map is None and len(exits) > 1 and exit != args.exit and not (
                    results / "design" / f"{map_name(args.preset, exit)}.zarr").exists():
                print(f"{args.preset}, angles {exit}: no map (run `make design`)")
                continue
            ds = open_map(results, args.preset, exit, args.map)
            print(f"{ds.attrs['title']}: {reading_line(ds, thickness, delta_ri)}")
    if args.haze_max is not None:
        haze_max = number(args.haze_max, "haze_max")
        ds = open_map(results, args.preset, args.exit, args.map)
        print(f"{ds.attrs['title']}: {window_line(ds, thickness, haze_max)}")
        print(f"  ray optics at this window's edges: {regime_line(results, args.preset, thickness, haze_max, ds, args.exit)}")
    method = json.loads(ds.attrs["trace_settings"])["method"]
    print(f"  interpolated on {args.map or results / 'design'} ({ds.sizes['thickness']} thicknesses × "
          f"{ds.sizes['delta_ri']} ΔRI, {ds.attrs['realisations']} woods × {ds.attrs['rays']} rays per cell, "
          f"method {method}, scale {ds.attrs['scale']})")
    return 0


def _need(path: Path, field: str, value: str, command: str) -> None:
    if not path.exists():
        raise ParameterError(f"`{field}` must hold {path.name} (run `{command}` first), got {field}={value!r}")


def cmd_figures(args) -> int:
    from ..figures import make_figures
    from ..result_sets import TABLE1

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
    if which is not None and "design" in which:
        from ..design import MAPS

        for name in MAPS:
            _need(results / "design" / f"{name}.zarr", "results", args.results, "make design")
    out = out_path(args.out, "out")
    t0 = time.perf_counter()
    made = make_figures(results, out, which=which)
    print(f"{len(made)} figures in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_report(args) -> int:
    from ..cache import atomic_write
    from ..report import build_report, figure_links
    from ..result_sets import TABLE1

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
    out = out_path(args.out, "out")
    text = build_report(results, scale_dir=args.scale)
    atomic_write(out, lambda tmp: tmp.write_text(text))
    missing = [f for f in figure_links(text) if not (out.parent / f).exists()]
    print(f"wrote {out}")
    if missing:
        print(f"twray report: {len(missing)} linked figures do not exist yet (run `make figures`): "
              f"{', '.join(missing)}", file=sys.stderr)
    return 0


def add_resummarize(sub):
    p = subparser(sub, "resummarize", help="recompute a study Dataset's FWHM, haze and intervals from its own rays")
    p.add_argument("datasets", nargs="+", metavar="STUDY.zarr", help="study Datasets (twray study's outputs)")
    p.add_argument("--fwhm", default=None, metavar="ESTIMATOR",
                   help="half-max, lorentz-hist or lorentz-mle (default: the Dataset's own, else half-max)")
    p.set_defaults(func=cmd_resummarize)


def cmd_resummarize(args) -> int:
    from ..analysis import ESTIMATORS, FwhmSpec
    from ..study.summaries import resummarize_file

    if args.fwhm is not None and args.fwhm not in ESTIMATORS:
        raise ParameterError(f"`fwhm` must be one of {', '.join(ESTIMATORS)}, got fwhm={args.fwhm!r}")
    paths = [Path(d) for d in args.datasets]
    for path in paths:
        if not (path / "zarr.json").is_file():
            raise ParameterError(f"`datasets` must be study Datasets (.zarr), got {str(path)!r}")
    for path in paths:
        try:
            pooled = resummarize_file(path, spec=FwhmSpec(args.fwhm) if args.fwhm else None)
        except ValueError as exc:
            raise ParameterError(f"`{path}`: {exc}") from None
        print(f"{path}: {len(pooled)} values re-summarised ({pooled[0]['fwhm']['estimator']}, "
              f"{pooled[0]['realisations']} woods)")
    return 0
