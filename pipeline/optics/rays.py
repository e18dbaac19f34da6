"""What goes into a trace and what comes out, whatever the medium: a beam and a RayResult.

Positions and lengths are in µm in the sample's frame [R, T, L]; the entrance
face is T = 0 and the exit face T = thickness.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .. import rng
from ..params import ParameterError
from .interface import STATUS_NAMES, TRANSMITTED
from .settings import TraceSettings


@dataclass
class Beam:
    """Rays entering the T = 0 face.

    origins : (N, 3) entry points (their T is taken as 0); direction : (3,) one
    direction for every ray, or (N, 3) one per ray; inside the sample, or in the
    outside medium when the optics name ``n_outside``.  ray_ids : (N,) each
    ray's index in its beam (the key of its random streams).

    Given to :func:`pipeline.optics.trace.trace`, positions are in µm; the
    voxel backend's own ``trace_in_voxels`` takes them in voxels.
    """

    origins: np.ndarray
    direction: np.ndarray
    ray_ids: np.ndarray

    def unit_directions(self) -> np.ndarray:
        """(N, 3) unit directions, one per ray; a ParameterError unless each is non-zero and
        points into the sample (+T)."""
        n = len(self.ray_ids)
        dirs = np.array(np.broadcast_to(np.asarray(self.direction, np.float64), (n, 3)))
        norms = np.linalg.norm(dirs, axis=1)
        if np.any(~(norms > 0)) or np.any(dirs[:, 1] <= 0):
            raise ParameterError("beam directions must be non-zero and point into the sample (+T)")
        dirs /= norms[:, None]
        return dirs

    def __getitem__(self, part: slice) -> "Beam":
        """Rays ``part`` of the beam (the same rays, whatever the split)."""
        d = self.direction if np.ndim(self.direction) == 1 else self.direction[part]
        return Beam(self.origins[part], d, self.ray_ids[part])


def square_beam(n_rays: int, width: float, centre=(0.0, 0.0), *, seed: int,
                direction=(0.0, 1.0, 0.0)) -> Beam:
    """``n_rays`` at uniformly random points of a width × width square of the L-R face,
    centred on ``centre`` (R, L), in the units of ``width``.

    Each ray's position is a hash of (seed, ray id): the beam is the same
    however the rays are later split into shards.
    """
    if n_rays < 1:
        raise ParameterError(f"`rays` must be >= 1, got {n_rays}")
    ids = np.arange(n_rays, dtype=np.int64)
    u = rng.uniform_table(np.uint64(seed), rng.BEAM, ids, 2, 0)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    if d[1] <= 0:
        raise ParameterError(f"`direction` must point into the sample (+T), got {tuple(direction)}")
    origins = np.zeros((n_rays, 3))
    origins[:, 0] = centre[0] + (u[:, 0] - 0.5) * width
    origins[:, 2] = centre[1] + (u[:, 1] - 0.5) * width
    return Beam(origins, d, ids)


# The voxel backend's per-ray counts among a RayResult's extras: normals that fell back (no
# gradient; the face and the direction disagreed; a wall thinner than the smoothing, normal
# taken at the face point), and the voxels read (the path, and each interface's neighbourhood).
VOXEL_COUNTS = ("degenerate_normals", "face_disagreements", "thin_wall_normals", "voxels_read")


@dataclass
class RayResult:
    """Per-ray outcome of a trace (angles in degrees; positions and lengths in µm from
    :func:`pipeline.optics.trace.trace`, in voxels from the voxel backend's ``trace_in_voxels``)."""

    position: np.ndarray  # (N, 3) exit (or last) point
    direction: np.ndarray  # (N, 3) final direction inside the sample
    exit_direction: np.ndarray  # (N, 3) after the exit-medium setting
    status: np.ndarray  # (N,) codes of STATUS_NAMES
    events: np.ndarray  # (N,) interfaces met
    path: np.ndarray  # (N,) geometric path length
    settings: TraceSettings
    # (N, 3) the direction each ray would leave in, in the convention of
    # exit_direction, had nothing deflected it (haze is measured from it);
    # None: every ray came in along +T.  NaN where that undeflected ray could
    # not leave into air (total reflection at the exit face).
    incident: np.ndarray | None = None
    # Per-ray arrays its backend adds: "medium" (the phase each ray ends in), and the voxel
    # methods' counts (VOXEL_COUNTS) or the exact march's "evaluations" and "passes".
    extras: dict = field(default_factory=dict)
    # Numbers of the whole trace its backend adds (voxel methods: "chunks_loaded",
    # "traced_voxel_um"); none for a surface medium.
    diagnostics: dict = field(default_factory=dict)

    @property
    def transmitted(self) -> np.ndarray:
        return self.status == TRANSMITTED

    @property
    def theta_r(self) -> np.ndarray:
        d = self.exit_direction
        return np.degrees(np.arctan2(d[:, 0], d[:, 1]))

    @property
    def theta_l(self) -> np.ndarray:
        d = self.exit_direction
        return np.degrees(np.arctan2(d[:, 2], d[:, 1]))

    def voxel_counts(self) -> dict[str, int]:
        """The voxel backend's counts (VOXEL_COUNTS) summed over the rays; none for a surface medium."""
        return {name: int(np.sum(self.extras[name])) for name in VOXEL_COUNTS if name in self.extras}

    def counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.status == code)) for code, name in STATUS_NAMES.items()}

    def scaled(self, factor: float) -> "RayResult":
        """The same result with positions and path lengths multiplied by ``factor``."""
        return dataclasses.replace(self, position=self.position * factor, path=self.path * factor)


def concatenate(parts: list[RayResult]) -> RayResult:
    """RayResults of consecutive parts of one beam as one (counts among the diagnostics added)."""
    first = parts[0]
    merged = {f.name: np.concatenate([getattr(p, f.name) for p in parts])
              for f in dataclasses.fields(first) if isinstance(getattr(first, f.name), np.ndarray)}
    extras = {k: np.concatenate([p.extras[k] for p in parts]) for k in first.extras}
    diagnostics = {k: sum(p.diagnostics[k] for p in parts) if isinstance(v, int) else v
                   for k, v in first.diagnostics.items()}
    return dataclasses.replace(first, **merged, extras=extras, diagnostics=diagnostics)
