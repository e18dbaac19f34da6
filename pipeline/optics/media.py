"""The media a trace runs through, as the tracer interface sees them (docs/methods.md#media).

Two kinds, each traced by the methods of its kind (``settings.METHODS``):

* a **voxel medium** is a two-phase volume read chunk by chunk: generated
  wood (:class:`~pipeline.optics.sources.WoodSource`), a user volume
  (:class:`~pipeline.optics.sources.ArraySource`) or a voxelised reference
  lattice (:class:`~pipeline.optics.lattice.LatticeSource`);
* a **surface medium** knows its walls analytically and answers where a ray
  segment first meets one, and the wall's normal there, inside its own Numba
  kernel, applying the shared interface physics of
  :mod:`pipeline.optics.interface`: generated wood's own surfaces
  (:class:`~pipeline.optics.wood_surface.WoodSurface`) and the exact reference
  lattices (:class:`~pipeline.optics.lattice.LatticeSlab`).

Study, camera and command line build a medium and call
:func:`pipeline.optics.trace.trace`; they never ask which kind they hold.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from .settings import traced_voxel_um
from .sources import WoodSource
from .wood_surface import WoodSurface


@runtime_checkable
class VoxelMedium(Protocol):
    """A two-phase voxel volume (1 = wall, 0 = polymer), axes [R, T, L], read by chunks."""

    voxel_um: float  # side of a voxel [µm]
    shape: tuple  # voxels along (R, T, L); 0 along R or L: unbounded
    chunks: tuple  # chunk shape [voxels]
    unbounded: tuple  # (along R, along L)
    token: object  # what its voxels depend on (equal tokens: equal chunks), or None

    def inside(self, idx) -> bool:
        """Whether chunk ``idx`` holds voxels of the volume."""

    def get_many(self, indices) -> dict:
        """The voxels of each chunk of ``indices``, by chunk index."""


@runtime_checkable
class SurfaceMedium(Protocol):
    """A slab of analytic walls from T = 0 to T = ``thickness_um`` [µm]."""

    thickness_um: float

    def entry_phase(self, origins_um: np.ndarray) -> np.ndarray:
        """The phase (1 wall, 0 polymer) each ray enters at its entry point (T = 0)."""

    def march_walls(self, origins_um: np.ndarray, directions: np.ndarray, *, n_wall: float, n_poly: float,
                       max_events: int, fresnel: bool = False, seed: int = 0, ray_ids=None) -> dict:
        """March rays from their entry points (T = 0, directions inside the sample) to where they
        leave; returns per-ray arrays ``position`` [µm], ``direction``, ``status``, ``events``,
        ``path`` [µm], ``medium`` (the phase each ends in) and any extras of the medium's own.
        With ``fresnel``, a refracted ray is reflected instead with the Fresnel reflectance, drawn
        from the streams of (``seed``, ray id, interface)."""


def kind_of(medium) -> str:
    """"voxels", "surfaces" or "fields": which protocol ``medium`` answers (a field, a grey-level
    scan's iso-surface, marches its own walls as a surface medium does, and says so)."""
    if getattr(medium, "medium_kind", None) == "fields" and isinstance(medium, SurfaceMedium):
        return "fields"
    if isinstance(medium, SurfaceMedium):
        return "surfaces"
    if isinstance(medium, VoxelMedium):
        return "voxels"
    raise TypeError(f"a medium must be a voxel medium or a surface medium, got {type(medium).__name__}")


def wood_medium(params, *, seed: int, thickness_um: float, voxel_um: float, settings, store=None, threads: int = 1):
    """Generated wood of ``params`` and ``seed``, ``thickness_um`` thick, as the medium that
    ``settings.method`` traces: for ``exact`` its analytic surfaces (no voxels, ``voxel_um`` unused);
    for a voxel method, its chunks at the scene's ``voxel_um``
    divided by the method's ``refine`` (from ``store`` when given, a
    :class:`~pipeline.microstructure.store.WoodChunkStore` of that wood and voxel)."""
    if settings.medium_kind == "surfaces":
        return WoodSurface(params, thickness_um=thickness_um, seed=seed, threads=threads)
    return WoodSource(params, thickness_um=thickness_um, voxel_um=traced_voxel_um(voxel_um, settings), seed=seed,
                      store=store, threads=threads)
