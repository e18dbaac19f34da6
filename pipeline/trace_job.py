"""One trace of a sample, as ``twray trace`` runs it: the medium (a user volume, generated
wood of a preset or a reference lattice), a square beam, the optics and a method; traced to a number of rays or to a
precision; summarised, and its rays written as a dataset."""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__, limits
from .analysis import FwhmSpec, Target
from .summary import summarize
from .optics.interface import STATUS_NAMES
from .optics.iso import IsoVolume
from .optics.rays import square_beam
from .optics.references import Reference, scene_medium
from .optics.settings import Optics, TraceSettings, check_paper_step, traced_voxel_um
from .optics.sources import ArraySource, load_volume
from .optics.trace import trace_to_target
from .params import ParameterError, WoodParams, build_params, check_voxel, make_grid
from .publish import check_replaceable, publish, staged_path
from .provenance import provenance_attrs


@dataclass(frozen=True)
class TraceJob:
    """What ``twray trace`` is asked: exactly one of ``volume`` (a path), ``wood`` and ``reference``.

    Lengths in µm; ``incidence_deg`` the beam's angles (R, L) in air, None for a
    beam along +T already inside the sample; ``target`` traces ``rays`` first,
    then doubles them until it is met.
    """

    settings: TraceSettings
    optics: Optics
    rays: int
    beam_um: float
    voxel_um: float
    seed: int
    volume: str | None = None
    wood: WoodParams | None = None
    reference: Reference | None = None  # a reference lattice of exact optics
    thickness_um: float | None = None
    beam_origin_um: tuple | None = None
    incidence_deg: tuple | None = None
    target: Target | None = None
    fwhm: FwhmSpec = FwhmSpec()  # which width FWHM_R and FWHM_L are
    iso: float | None = None  # method iso: the wall's grey level (None: Otsu's threshold of the volume)
    smooth_um: float = 0.0  # method iso: σ [µm] of a Gaussian smoothing of the grey levels (0: none)

    @property
    def traced_voxel_um(self) -> float:
        """The voxel the rays cross: a user volume's own, generated wood's refined by the method."""
        return self.voxel_um if self.volume else traced_voxel_um(self.voxel_um, self.settings)

    @property
    def direction(self) -> tuple:
        r, l = self.incidence_deg or (0.0, 0.0)
        return (math.tan(math.radians(r)), 1.0, math.tan(math.radians(l)))


def medium_of(job: TraceJob):
    """The medium ``job`` traces and the centre (R, L) of its beam [µm], after checking that the
    beam fits and the trace is not too big (before any work)."""
    if job.volume:
        if job.settings.medium_kind == "surfaces":
            raise ParameterError(f"`method` {job.settings.method} traces the analytic surfaces of generated wood, "
                                 f"and a --volume has voxels only: use --method iso (its grey levels' "
                                 f"iso-surface) or accurate (fast, paper: its voxels)")
        if job.settings.refine > 1:
            raise ParameterError(f"`refine` applies to generated wood (--preset); a --volume has only its "
                                 f"own voxels, got refine={job.settings.refine}")
        if job.settings.medium_kind == "fields":
            medium = IsoVolume(load_volume(job.volume), voxel_um=job.voxel_um, iso=job.iso, smooth_um=job.smooth_um)
        else:
            medium = ArraySource(load_volume(job.volume), voxel_um=job.voxel_um)
        nr, nt, nl = medium.shape
        centre = (nr * job.voxel_um / 2.0, nl * job.voxel_um / 2.0)
        # A user volume's cell pitch is unknown: the estimate assumes birch's.
        thickness_um, pitch, wall = nt * job.voxel_um, build_params("birch").fibre_diameter_um, None
    else:
        if job.settings.medium_kind == "fields":
            raise ParameterError("`method` iso traces the iso-surface of a grey-level scan: give --volume "
                                 "(generated wood and references have exact surfaces: --method exact)")
        if job.reference is None:
            check_voxel(job.voxel_um, job.wood)  # whatever the method
            if job.settings.medium_kind == "voxels":  # a voxel grid only where there are voxels
                make_grid((1.0, job.thickness_um, 1.0), job.voxel_um, (0.0, 0.0, 0.0), job.wood)
        medium = scene_medium(wood=job.wood, reference=job.reference, seed=job.seed, thickness_um=job.thickness_um,
                              voxel_um=job.voxel_um, settings=job.settings, threads=os.cpu_count() or 1)
        centre = (0.0, 0.0)
        pitch, wall = ((job.reference.pitch_um, job.reference.wall_um) if job.reference is not None
                       else (job.wood.fibre_diameter_um, job.wood.wall_thickness_um))
        thickness_um = job.thickness_um
    if job.beam_origin_um is not None:
        centre = job.beam_origin_um
    voxel = job.traced_voxel_um
    check_paper_step(job.settings, job.voxel_um, wall)
    half = job.beam_um / 2
    if job.volume and not (centre[0] - half >= 0 and centre[0] + half <= nr * voxel
                           and centre[1] - half >= 0 and centre[1] + half <= nl * voxel):
        raise ParameterError(f"`beam_um` must fit the volume's R-L face ({nr * voxel:g} x {nl * voxel:g} µm) "
                             f"around the beam's centre, got beam_um={job.beam_um:g}")
    rays = job.rays if job.target is None else job.target.max_rays
    return medium, centre, limits.trace_estimate(rays=rays, beam_um=job.beam_um, thickness_um=thickness_um,
                                                 voxel_um=voxel, pitch_um=pitch, method=job.settings.method,
                                                 wood=not job.volume,
                                                 generated=not job.volume and job.reference is None,
                                                 params=job.wood, delta_ri=job.optics.delta_ri) \
        + limits.summary_estimate(rays)


def run(job: TraceJob, *, out: Path | None = None, yes: bool = False, progress: str = "off", log=None) -> tuple:
    """``twray trace``'s one library call: check ``job`` and what it would cost (refused unless
    ``yes`` past the confirmation threshold), trace it, and publish its rays to ``out`` (when given);
    the RayResult [µm] and its summary.  ``log``: given a line where it compiles its kernels first."""
    medium, centre, est = medium_of(job)
    rays = job.rays if job.target is None else job.target.max_rays
    compiling = limits.compiling({job.settings.medium_kind}, 1)
    # Said in the refusal's one line where it is refused, else as a line of its own before it compiles.
    limits.check(limits.startup(1) + compiling + est, what=f"`trace` of {rays} rays", yes=yes,
                 fit="trace fewer rays (--rays; a study traces them by shards), a narrower beam (--beam-um) "
                     "or a thinner sample", note=limits.first_run_note(compiling))
    first = limits.first_run_line("trace", compiling)
    if first and log is not None:
        log(first)
    result, summary = trace_medium(job, medium, centre, progress=progress)
    if out is not None:
        write_rays(result, summary, out, job_inputs(job, centre))
    return result, summary


def trace_medium(job: TraceJob, medium, centre, *, progress: str = "off") -> tuple:
    """Trace ``job`` through ``medium``: the RayResult [µm] and its summary (with the target's
    outcome, the seconds it took and, for generated wood, the voxels it generated)."""
    t0 = time.perf_counter()

    def beam(n):
        return square_beam(n, job.beam_um, centre, seed=job.seed, direction=job.direction)

    result, summary = trace_to_target(medium, beam, job.optics, job.settings, rays=job.rays, target=job.target,
                                      summarize=lambda r: summarize(r, spec=job.fwhm, seed=job.seed), progress=progress)
    if job.target is not None:
        summary["target_ci"] = job.target.to_dict()
        summary["target_ci_met"] = job.target.met(summary)
    if job.settings.medium_kind == "fields":  # the threshold the walls were traced at, and where it came from
        summary.update({"iso": medium.iso, "iso_from": medium.iso_from, "smooth_um": medium.smooth_um})
    summary.update({"delta_ri": job.optics.delta_ri, "ri_polymer": job.optics.n_poly,
                    "incidence_deg": list(job.incidence_deg or (0.0, 0.0)),
                    "seconds": time.perf_counter() - t0, **result.diagnostics})
    if job.settings.medium_kind == "voxels":  # a surface medium reads and generates no voxels
        summary["refine"] = result.settings.refine
        if not job.volume:  # the wood the trace needed, against what it read
            chunks = medium.generated if job.reference is not None else len(medium.distinct)
            summary["voxels_generated"] = chunks * math.prod(medium.chunks)
    return result, summary


def job_inputs(job: TraceJob, centre) -> dict:
    """The resolved inputs of ``job`` (provenance of its rays dataset)."""
    return {"volume": job.volume, "params": None if job.wood is None else job.wood.to_dict(),
            "reference": None if job.reference is None else job.reference.to_dict(),
            "thickness_mm": None if job.thickness_um is None else job.thickness_um / 1000.0,
            "voxel_um": job.voxel_um, "traced_voxel_um": job.traced_voxel_um, "delta_ri": job.optics.delta_ri,
            "ri_polymer": job.optics.n_poly, "rays": job.rays, "beam_um": job.beam_um,
            "beam_centre_um": list(centre), "incidence_deg": list(job.incidence_deg or (0.0, 0.0)),
            "seed": job.seed, "settings": job.settings.to_dict(), "fwhm": job.fwhm.to_dict(), "iso": job.iso,
            "smooth_um": job.smooth_um}


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
    return json.dumps(_finite_or_none(value), allow_nan=False)


def check_rays_out(out: Path) -> None:
    """A per-ray result replaces only an earlier twray result: never another folder or file."""
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


def write_rays(result, summary: dict, out, inputs: dict) -> None:
    """The per-ray result [µm] as a CF dataset at ``out`` (.nc or .zarr), published atomically."""
    import xarray as xr

    from .publish import write_zarr

    codes = sorted(STATUS_NAMES)
    ds = xr.Dataset(
        {
            "theta_r": ("ray", result.theta_r, {"long_name": "exit angle in the R-T plane", "units": "degree"}),
            "theta_l": ("ray", result.theta_l, {"long_name": "exit angle in the L-T plane", "units": "degree"}),
            "exit_r": ("ray", result.position[:, 0], {"long_name": "exit position R", "units": "um"}),
            "exit_l": ("ray", result.position[:, 2], {"long_name": "exit position L", "units": "um"}),
            "direction": (("ray", "axis"), result.exit_direction, {"long_name": "exit direction (R, T, L)",
                                                                  "units": "1"}),
            "incident_direction": (("ray", "axis"), result.incident, {
                "long_name": "direction of the ray had nothing deflected it (haze is measured from it)",
                "units": "1"}),
            "path_length": ("ray", result.path, {"long_name": "geometric path length", "units": "um"}),
            "n_interfaces": ("ray", result.events.astype("int32"), {"long_name": "interfaces met"}),
            "status": ("ray", result.status.astype("int32"), {
                "long_name": "ray status", "flag_values": codes,
                "flag_meanings": " ".join(STATUS_NAMES[c] for c in codes)}),
        },
        coords={"ray": range(result.status.size), "axis": np.array(["R", "T", "L"], dtype=object)},
        attrs={"Conventions": "CF-1.10", "title": "twray per-ray trace result",
               "source": f"twray {__version__}", "summary": strict_json(summary)},
    )
    ds.attrs.update(provenance_attrs(inputs, result.settings.method))
    out = Path(out)
    check_rays_out(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    try:
        if out.suffix == ".zarr":
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

