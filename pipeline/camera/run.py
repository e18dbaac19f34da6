"""Rendering a camera file (docs/methods.md#virtual-camera): plan its images against the cache,
render what is missing as one Dask graph, publish the Dataset and PNGs.

The one orchestrator of a camera run, whatever calls it (``twray camera``,
benchmarks, tests), in the shape of :mod:`pipeline.study`: the images are
planned (:mod:`.plan`), their row blocks are graph tasks (:mod:`.tasks`,
:mod:`.graph`) and the outputs are written (:mod:`.dataset`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from .. import limits
from ..request import GraphRequest
from .dataset import write_outputs
from .graph import compute
from .plan import ROWS_PER_TASK, plan_blocks, plan_camera
from .scene import load_camera
from .tasks import load_entry

FIT = "use fewer pixels or samples, a smaller or thinner sheet, or larger voxels"  # when a camera run is too big


@dataclass(frozen=True, kw_only=True)
class CameraRequest(GraphRequest):
    """What ``twray camera`` asks for (:func:`render`)."""

    file: str
    rows_per_task: int = ROWS_PER_TASK


@dataclass
class CameraOutcome:
    """What :func:`render` did: the study, its image entries (with the row blocks each had cached
    before the run, on a dry run), the files written and how long it took."""

    study: object
    entries: list
    blocks: dict
    paths: list
    seconds: float
    dry_run: bool = False


def render(request: CameraRequest, *, open_client, log) -> CameraOutcome:
    """Load the camera file of ``request``, refuse what could not fit, plan its images against the
    cache, and (unless a dry run) render what is missing on the client ``open_client()`` opens and
    write the Dataset and PNGs."""
    study = load_camera(request.file, scale=request.scale, method=request.method)
    limits.check(request.started + limits.camera_estimate(study.images), what="`camera`", yes=True,
                 disk_path=request.cache, fit=FIT)
    t0 = time.perf_counter()
    entries = plan_camera(study, request.cache)
    todo = [e for e in entries if not e.cached]
    blocks = {e.key: plan_blocks(e, request.cache, request.rows_per_task) for e in todo}  # an interrupted run's are kept
    left = [sum(b.hi - b.lo for b in blocks[e.key] if not b.cached) for e in todo]
    est = request.started + limits.camera_estimate([e.config for e in todo], rows=left)
    if todo:  # the workers' first rows compile the kernels where this checkout has not yet on this machine
        est = est + limits.compiling({e.config.settings.medium_kind for e in todo}, request.workers)
    if est.cpu_s >= limits.SHOW_ESTIMATE_S:
        log(f"twray camera: estimate for the {len(todo)} image{'' if len(todo) == 1 else 's'} to render "
            f"(the part of the sheet its rays reach): {est.text()}")
    if request.dry_run:
        return CameraOutcome(study, entries, blocks, [], time.perf_counter() - t0, dry_run=True)
    limits.check(est, what="`camera`", yes=request.yes, disk_path=request.cache, fit=FIT)
    if not all(e.cached for e in entries):
        resumed = sum(b.cached for bs in blocks.values() for b in bs)
        if resumed:
            log(f"twray camera: {resumed} of {sum(len(bs) for bs in blocks.values())} row blocks were "
                "rendered by an earlier run and are read, not rendered")
        with open_client() as client:
            compute(entries, client, request.cache, rows_per_task=request.rows_per_task, progress=request.progress)
        entries = plan_camera(study, request.cache)
    paths = write_outputs(study, entries, request.results)
    return CameraOutcome(study, entries, blocks, paths, time.perf_counter() - t0)


def describe(outcome: CameraOutcome, results: str) -> list[str]:
    """The lines ``twray camera`` prints: a dry run's images, or what each rendered image saw."""
    study = outcome.study
    if outcome.dry_run:
        lines = []
        for e in outcome.entries:
            done = sum(b.cached for b in outcome.blocks.get(e.key, ()))
            state = "cached" if e.cached else "to render" + (f", {done} of {len(outcome.blocks[e.key])} row "
                                                             "blocks done" if done else "")
            lines.append(f"{study.name} {e.config.name}: {state} ({e.key[:12]})")
        return lines
    lines = [f"{outcome.paths[0]}: {study.title} (scale {study.scale}, {study.images[0].camera.samples} "
             f"samples per pixel, {study.images[0].settings.method})"]
    for e in outcome.entries:
        d = load_entry(e)
        c = e.config
        n = d["image"].size * c.camera.samples
        lines.append(f"  {c.name}: f {c.camera.focal_mm:g} mm, m {c.camera.magnification:.4g}, "
                     + ("no sheet" if c.sheet is None else
                        f"ΔRI {c.sheet.delta_ri:.3g}, gap {c.sheet.gap_um:g} µm, "
                        f"{float(d['interfaces_per_ray']):.1f} interfaces/ray")
                     + f", {int(d['lost'].sum())}/{n} samples lost")
    return lines + [f"wrote {len(outcome.paths)} files under {Path(results)} in {outcome.seconds:.1f} s"]
