"""``twray trace``: parse, run one :class:`~pipeline.trace_job.TraceJob`, print."""

from __future__ import annotations

import sys
from pathlib import Path

from ..progress import mode as progress_mode
from ..params import ParameterError, build_params, parse_set
from .args import YES_HELP, integer, number, out_path, subparser


def add_trace(sub):
    p = subparser(sub, "trace", help="trace a beam through a volume and report FWHM_R, FWHM_L, haze")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--volume", help="user volume: .npy, .zarr or a folder of TIFF slices "
                                      "(axes R, T, L; 1 = wall; grey levels with --method iso)")
    src.add_argument("--preset", help="generate wood lazily from this species preset")
    src.add_argument("--reference", help="a reference lattice of exact optics: tubes-square, tubes-hex, cells-hex "
                                         "or cells-square (with --pitch-um and --wall-um)")
    p.add_argument("--pitch-um", default=None, help="site spacing of a --reference lattice [µm]")
    p.add_argument("--wall-um", default=None, help="wall thickness of a --reference lattice [µm]")
    p.add_argument("--r-outer-um", default=None,
                   help="outer radius of a tube --reference [µm] (default half the pitch: touching tubes)")
    p.add_argument("--jitter", default="0", help="sites of a --reference moved by up to this fraction of the "
                                                 "pitch, in [0, 0.25] (default 0)")
    p.add_argument("--config", help="YAML file of wood parameters (with --preset)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one wood parameter (with --preset), e.g. --set wall_thickness_um=4 [µm]")
    p.add_argument("--thickness-mm", help="sample thickness along T [mm] (with --preset or --reference)")
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
    p.add_argument("--method", default=None, help="paper, fast, accurate, exact or iso (default: exact for "
                                                  "generated wood and references, accurate for a --volume; iso: "
                                                  "a grey-level --volume's iso-surface)")
    p.add_argument("--iso", default=None, help="with --method iso: the wall's grey level (default: Otsu's "
                                               "threshold of the volume, stated in the output)")
    p.add_argument("--smooth-um", default=None, help="with --method iso: smooth the grey levels by a Gaussian of "
                                                     "this σ [µm] before tracing (against noise and the facets of "
                                                     "the interpolant; default 0.5, 0: none)")
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
    p.add_argument("--fwhm", default="half-max", metavar="ESTIMATOR",
                   help="which width FWHM_R and FWHM_L are: half-max (the distribution's width at half its "
                        "maximum, default), lorentz-hist (a Lorentzian fitted to the histogram, the source's) or "
                        "lorentz-mle (2γ of a Cauchy maximum-likelihood fit); --json prints all three")
    p.add_argument("--max-rays", default="64000", help="most rays a --target-ci trace uses (default 64000)")
    p.add_argument("--out", default=None, help="per-ray dataset (.nc or .zarr)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--yes", action="store_true", help=YES_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress lines")
    p.set_defaults(func=cmd_trace)


def cmd_trace(args) -> int:
    from ..trace_job import check_rays_out, run, strict_json

    if args.out is not None:
        args.out = str(out_path(args.out))
        check_rays_out(Path(args.out))
    job = _trace_job(args)
    _, summary = run(job, out=None if args.out is None else Path(args.out), yes=args.yes,
                     progress=progress_mode(args.quiet),
                     log=None if args.quiet else lambda line: print(line, file=sys.stderr))
    if args.json:
        print(strict_json(summary))
        return 0
    lo, hi = summary["haze_ci"]
    target = job.target
    met = "" if target is None else (
        "; target_ci met" if summary["target_ci_met"] else f"; target_ci NOT met at max_rays {target.max_rays}")
    print(f"{summary['n_transmitted']}/{summary['n_rays']} transmitted "
          f"(method {summary['method']}{_iso_text(summary)}, exit {summary['exit']}): "
          f"FWHM_R {summary['fwhm_r_deg']:.3f}°, FWHM_L {summary['fwhm_l_deg']:.3f}° ({job.fwhm.estimator}), "
          f"haze {100 * summary['haze']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}], "
          f"{summary['seconds']:.1f} s{met}")
    return 0


def _trace_job(args):
    """``twray trace``'s arguments as a TraceJob (each checked, one line naming the field)."""
    from ..optics.iso import SMOOTH_UM
    from ..optics.references import reference
    from ..optics.settings import METHODS, Optics, check_method, settings_for
    from ..trace_job import TraceJob

    voxel = number(args.voxel_um, "voxel_um")
    if not voxel > 0:
        raise ParameterError(f"`voxel_um` must be > 0 µm, got voxel_um={voxel:g}")
    optics = Optics.of_delta(number(args.ri_polymer, "ri_polymer"), number(args.delta_ri, "delta_ri"),
                             seed=integer(args.seed, "seed", 0),
                             n_outside=1.0 if args.incidence_deg is not None else None).validate()
    rays = integer(args.rays, "rays", 1)
    target = _trace_target(args, rays)
    fwhm_spec = _fwhm_spec(args.fwhm)
    beam_um = number(args.beam_um, "beam_um")
    if not beam_um > 0:
        raise ParameterError(f"`beam_um` must be > 0 µm, got beam_um={beam_um:g}")
    if args.method is None:
        args.method = "accurate" if args.volume else "exact"  # a scan has voxels only
    changes = {"exit": args.exit}
    if args.step_vox is not None:
        changes["step_vox"] = number(args.step_vox, "step_vox")
    if args.fresnel:
        changes["fresnel"] = True
    if args.refine is not None:
        changes["refine"] = integer(args.refine, "refine", 1)
    elif args.volume and METHODS.get(args.method) == "voxels":
        changes["refine"] = 1  # a user volume is traced on its own voxels
    settings = settings_for(check_method(args.method), **changes)
    iso = None
    if args.iso is not None:
        if settings.method != "iso":
            raise ParameterError(f"`--iso` applies to --method iso, got --method {settings.method}")
        iso = number(args.iso, "iso")
    smooth_um = SMOOTH_UM if settings.method == "iso" else 0.0
    if args.smooth_um is not None:
        if settings.method != "iso":
            raise ParameterError(f"`--smooth-um` applies to --method iso, got --method {settings.method}")
        smooth_um = number(args.smooth_um, "smooth_um")
    wood = thickness_um = ref = None
    lattice_args = {"--pitch-um": args.pitch_um, "--wall-um": args.wall_um, "--r-outer-um": args.r_outer_um,
                    "--jitter": None if args.jitter == "0" else args.jitter}
    if not args.reference and any(v is not None for v in lattice_args.values()):
        given = next(k for k, v in lattice_args.items() if v is not None)
        raise ParameterError(f"`{given}` applies to --reference, not --{'volume' if args.volume else 'preset'}")
    if args.volume:
        if args.thickness_mm or args.overrides or args.config:
            raise ParameterError("`--thickness-mm`, `--set` and `--config` apply to --preset, not --volume")
    else:
        if args.thickness_mm is None:
            raise ParameterError(f"`--thickness-mm` is required with --{'preset' if args.preset else 'reference'}")
        thickness_um = number(args.thickness_mm, "thickness_mm") * 1000.0
        if not thickness_um > 0:
            raise ParameterError(f"`thickness_mm` must be > 0, got thickness_mm={thickness_um / 1000:g}")
        if args.reference:
            if args.overrides or args.config:
                raise ParameterError("`--set` and `--config` apply to --preset, not --reference")
            ref = reference(args.reference, pitch_um=_optional(args.pitch_um, "pitch_um"),
                            wall_um=_optional(args.wall_um, "wall_um"),
                            r_outer_um=_optional(args.r_outer_um, "r_outer_um"), jitter=number(args.jitter, "jitter"))
        else:
            wood = build_params(args.preset, args.config, parse_set(args.overrides))
    origin = None
    if args.beam_origin_um is not None:
        parts = args.beam_origin_um.split(",")
        if len(parts) != 2:
            raise ParameterError(f"`beam_origin_um` must be R,L [µm], got {args.beam_origin_um!r}")
        origin = tuple(number(v, "beam_origin_um") for v in parts)
    return TraceJob(settings=settings, optics=optics, rays=rays, beam_um=beam_um, voxel_um=voxel,
                    seed=optics.seed, volume=args.volume, wood=wood, reference=ref, thickness_um=thickness_um,
                    beam_origin_um=origin, incidence_deg=_incidence(args.incidence_deg), target=target,
                    fwhm=fwhm_spec, iso=iso, smooth_um=smooth_um)


def _iso_text(summary: dict) -> str:
    """Method iso: the threshold traced, and whether it was given or Otsu's."""
    if "iso" not in summary:
        return ""
    smooth = f", smoothed σ {summary['smooth_um']:g} µm" if summary.get("smooth_um") else ""
    return (f" at grey level {summary['iso']:.6g}" + (" (Otsu's threshold)" if summary["iso_from"] == "otsu" else "")
            + smooth)


def _fwhm_spec(name: str):
    """``--fwhm``: an estimator's name."""
    from ..analysis import ESTIMATORS, FwhmSpec

    if name not in ESTIMATORS:
        raise ParameterError(f"`fwhm` must be one of {', '.join(ESTIMATORS)}, got fwhm={name!r}")
    return FwhmSpec(name)


def _optional(text, field):
    return None if text is None else number(text, field)


def _trace_target(args, rays: int):
    """The precision ``--target-ci``/``--target-ci-fwhm`` ask for (None: trace ``--rays``)."""
    from ..analysis import Target

    if args.target_ci is None and args.target_ci_fwhm is None:
        return None
    haze = fwhm = None
    if args.target_ci is not None:
        haze = number(args.target_ci, "target_ci")
        if not 0 < haze <= 0.5:
            raise ParameterError(f"`target_ci` must be a haze half-width in (0, 0.5], got target_ci={haze:g}")
    if args.target_ci_fwhm is not None:
        fwhm = number(args.target_ci_fwhm, "target_ci_fwhm")
        if not fwhm > 0:
            raise ParameterError(f"`target_ci_fwhm` must be > 0 degree, got target_ci_fwhm={fwhm:g}")
    cap = integer(args.max_rays, "max_rays", rays)
    return Target(haze=haze, fwhm_deg=fwhm, max_rays=cap)


def _incidence(text: str | None) -> tuple[float, float]:
    """The beam's angles (R, L) in air from --incidence-deg [degree]."""
    if text is None:
        return (0.0, 0.0)
    parts = text.split(",")
    if len(parts) != 2:
        raise ParameterError(f"`incidence_deg` must be two angles R,L [degree], got {text!r}")
    angles = tuple(number(a, "incidence_deg") for a in parts)
    if not all(abs(a) < 90.0 for a in angles):
        raise ParameterError(f"`incidence_deg` angles must lie in (-90, 90) degrees, got {text!r}")
    return angles
