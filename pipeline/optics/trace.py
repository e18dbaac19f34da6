"""The tracer interface: ``trace(medium, beam, optics, settings) -> RayResult``, in µm.

Every caller (study, camera, command line, benchmarks) traces through here and
never asks which kind of medium it holds (docs/methods.md#media): a voxel
medium is marched by the voxel backend (:mod:`pipeline.optics.voxels`), a
surface medium marches its own walls; the entrance and exit faces are handled
once for both (:mod:`pipeline.optics.faces`), and Snell's law, total internal
reflection and the statistics are the same.
"""

from __future__ import annotations

import math


from ..params import ParameterError
from .faces import through_faces
from .media import kind_of
from .rays import Beam, RayResult, concatenate
from .settings import METHODS, Optics, TraceSettings
from .voxels import voxel_interior


def trace(medium, beam: Beam, optics: Optics, settings: TraceSettings) -> RayResult:
    """Trace ``beam`` (entry points on T = 0 [µm]) through ``medium`` with ``optics``.

    Parameters
    ----------
    medium : VoxelMedium or SurfaceMedium
        What the rays cross (:mod:`pipeline.optics.media`).
    beam : Beam
        Entry points [µm] and directions (inside the sample, or in the medium
        of index ``optics.n_outside``).
    optics : Optics
        Refractive indices, the outside medium and the Fresnel seed.
    settings : TraceSettings
        The method (it must trace this kind of medium) and its options.

    Returns
    -------
    RayResult
        One entry per ray, positions and path lengths [µm].
    """
    settings = settings.validate()
    optics = optics.validate()
    kind = kind_of(medium)
    if METHODS[settings.method] != kind:
        able = ", ".join(m for m, k in METHODS.items() if k == kind)
        raise ParameterError(f"`method` {settings.method!r} traces {METHODS[settings.method]}, but this medium "
                             f"offers {kind}: use {able}")
    interior = voxel_interior(medium, settings) if kind == "voxels" else _SurfaceInterior(medium)
    return through_faces(interior, beam.origins, beam.unit_directions(), beam.ray_ids, optics, settings)


class _SurfaceInterior:
    """A surface medium between the faces: it marches its own walls (in µm)."""

    def __init__(self, medium):
        self.medium = medium

    def entry_phase(self, origins):
        return self.medium.entry_phase(origins)

    def march(self, origins, dirs, phase, ray_ids, *, optics: Optics, settings: TraceSettings):
        out = self.medium.march_walls(origins, dirs, n_wall=optics.n_wall, n_poly=optics.n_poly,
                                         max_events=settings.max_events, fresnel=settings.fresnel, seed=optics.seed,
                                         ray_ids=ray_ids)
        return out, {}


TRACE_BATCHES = 40  # a long trace reports its progress batch by batch


def trace_in_batches(medium, beam: Beam, optics: Optics, settings: TraceSettings, *,
                     progress: str = "off", title: str = "twray trace") -> RayResult:
    """:func:`trace` over consecutive batches of the beam, as Dask tasks on the synchronous
    scheduler so that its progress shows (``progress``: "bar", "lines" or "off"; every ray
    is independent of the others, so the result equals one call's)."""
    n = len(beam.ray_ids)
    size = max(500, math.ceil(n / TRACE_BATCHES))
    if progress == "off" or n < 2 * size:
        return trace(medium, beam, optics, settings)
    import dask  # only here: its import is a tenth of a second of every short trace

    from ..progress import LocalLines

    parts = [dask.delayed(trace, pure=False)(medium, beam[lo:lo + size], optics, settings)
             for lo in range(0, n, size)]
    with LocalLines(title, progress):
        parts = dask.compute(*parts, scheduler="sync")
    return concatenate(parts)


def next_rays(target, rays: int, summary: dict) -> int | None:
    """How many rays the next round of a trace to ``target`` (a :class:`~pipeline.analysis.Target`)
    traces after ``rays`` gave ``summary``: twice as many, at most ``target.max_rays``; None when
    the target is met or the cap reached.  Study and trace both double this way."""
    if target is None or rays >= target.max_rays or target.met(summary):
        return None
    return min(2 * rays, target.max_rays)


def trace_to_target(medium, make_beam, optics: Optics, settings: TraceSettings, *, rays: int, target=None,
                    summarize, progress: str = "off") -> tuple[RayResult, dict]:
    """Trace ``make_beam(rays)`` and, while ``target`` is not met, the next rays of the same beam
    (``make_beam(n)`` must hold the rays of ``make_beam(m)`` first for m < n: each ray's
    position is a hash of the seed and its index), so that the result equals one trace of
    that many rays.  Returns the result and ``summarize(result)``."""
    result = trace_in_batches(medium, make_beam(rays), optics, settings, progress=progress)
    summary = summarize(result)
    while (n := next_rays(target, len(result.status), summary)) is not None:
        more = make_beam(n)[len(result.status):]
        result = concatenate([result, trace_in_batches(medium, more, optics, settings, progress=progress)])
        summary = summarize(result)
    return result, summary

