"""The `exact` tracer's kernels compiled ahead, in two halves that two processes compile side by
side (docs/performance.md#compiling-the-kernels).

A first `exact` trace of generated wood compiles, one after the other, the wood's evaluation, the
analytic gradient of its surfaces, the march that calls both, and the Cauchy fit of its summary
(about two minutes on one core).  The evaluation and the gradient do not depend on each other, so
a study's first two workers each compile one half (:data:`PARTS`), and the march, compiled next
by each worker's first trace, loads both from the kernel cache.  With the kernels cached, a half
only loads them (well under a second), which the first trace would do anyway.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from ..analysis import cauchy_fit
from ..microstructure.region import context_tuple, phases, region_context
from ..microstructure.surface import new_cache
from ..microstructure.surface_gradient import gradient_at

PARTS = ("evaluation", "gradient")


@njit(cache=True, nogil=True)
def _normal(R, T, L, ctx, key, cache, out):
    """The march's normal (:func:`gradient_at`), compiled for the march's argument types."""
    return gradient_at(R, T, L, ctx, key, cache, out)


def compile_part(part: str, wood, seed: int = 0) -> float:
    """Compile (or load) one of :data:`PARTS` for ``wood`` (:class:`~pipeline.params.WoodParams`) in
    this process; returns the seconds it took."""
    if part not in PARTS:
        raise ValueError(f"`part` must be one of {', '.join(PARTS)}, got {part!r}")
    t0 = time.perf_counter()
    pitch = wood.node_pitch_um
    ctx = context_tuple(region_context(wood, seed, 4.0 * pitch, (-pitch, pitch), (-pitch, pitch)))
    if part == "evaluation":
        phases(np.array([[0.0, 2.0 * pitch, 0.0]]), 0.0, ctx)
    else:
        _normal(0.0, 2.0 * pitch, 0.0, ctx, np.zeros(5), new_cache(), np.zeros(3))
        cauchy_fit(np.tan(np.linspace(-1.4, 1.4, 64)))
    return time.perf_counter() - t0


def compile_on_workers(client, wood, seed: int = 0) -> list[float]:
    """:func:`compile_part` of each of :data:`PARTS` on its own worker of ``client`` (a
    ``distributed.Client``), side by side; nothing where it has fewer than two workers (one
    process compiles everything in turn anyway).  Returns each part's seconds."""
    workers = sorted(client.scheduler_info()["workers"])
    if len(workers) < 2:
        return []
    futures = [client.submit(compile_part, part, wood, seed, workers=[w], allow_other_workers=False, pure=False)
               for part, w in zip(PARTS, workers)]
    return client.gather(futures)
