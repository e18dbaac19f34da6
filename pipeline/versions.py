"""Code versions that cache keys and provenance record: the bottom floor of the package.

A version changes when the numbers a piece of code produces for the same
inputs change, so that cached entries made by the old code are computed
again.  Each tracing method has its own: a change to one method leaves the
others' cached rays valid.
"""

from __future__ import annotations

# The cached stages of a study (docs/guide.md#cache).
#   micro 3: wood without ray cells keeps the vessels and fibre distortion of the same wood with
#            them (ray columns are a property of the lattice); wood with ray cells holds the same voxels.
#   rays 4: positions and path lengths stored in µm (the tracer interface's units), not voxels.
#   summary 4: γ = 0 exactly where more than half the angles are equal (it was ~1e-187).
#   summary 5: every width estimator (half-max the default, lorentz-hist, lorentz-mle), no interval
#              (a wood's own value; the pool holds the intervals).
#   pool 2: every estimator; intervals from resampling woods only (t on R - 1 d.o.f.), 2000 resamples;
#           variance components.
STAGES = {"micro": "3", "rays": "4", "summary": "5", "pool": "2"}

# The generator's version: the voxels of every wood (pinned by tests/test_microstructure.py).
GENERATOR = STAGES["micro"]

# One per tracing method: bump a method's when its rays change for the same inputs.
#   exact 3: regime surfaces crossed on long steps; a few rays in a thousand part at a crossing
#            where the phase flickers within rounding (1e-12 µm), and so differ after it.
#   exact 4: the normal is the switching primitive's analytic gradient (it was six central
#            differences); a crossing's primitive is sought wherever the step as taken was within the
#            others' clearance.  Rays move at rounding (docs/performance.md).
#   exact 5: the wood's steps are proven along the ray (pipeline/microstructure/surface_ray.py;
#            they were balls alone), and a crossing's root is sought from the lumen's own root on
#            the ray's frame, then by secants nudged past their roots.  Rays move at rounding.
#   iso 1: a grey-level scan's trilinear iso-surface, crossings as roots of its cubics.
TRACERS = {"paper": "7", "fast": "7", "accurate": "7", "exact": "5", "iso": "1"}

# Cached camera images (2: entries verified, key and digest).
CAMERA = "2"


def tracer(method: str) -> str:
    """The version of tracing method ``method``."""
    return TRACERS[method]
