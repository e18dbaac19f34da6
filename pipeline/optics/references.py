"""Reference scenes a user traces by name (docs/guide.md#reference-scenes): lattices of tubes or
honeycomb cells whose exact optics is known, so that any method's error can be measured on a
geometry of one's choosing.

``exact`` traces a reference's own circles and lines (:meth:`Lattice.slab`, the march that traces
generated wood); a voxel method traces its voxelisation at the scene's voxel divided by the
method's ``refine`` (:meth:`Lattice.source`), as it traces generated wood.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from ..params import ParameterError
from .lattice import Lattice, honeycomb, tube_lattice
from .media import wood_medium
from .settings import traced_voxel_um

# name: (family, packing)
REFERENCES = {
    "tubes-square": ("tubes", "square"),
    "tubes-hex": ("tubes", "hex"),
    "cells-hex": ("cells", "hex"),
    "cells-square": ("cells", "square"),
}

REFERENCE_FIELDS = ("pitch_um", "wall_um", "r_outer_um", "jitter")  # what a reference scene sets [µm, fraction]


@dataclass(frozen=True)
class Reference:
    """A named reference lattice [µm]: tubes (outer radius ``r_outer_um``, half the pitch when None:
    touching tubes, as wood fibres touch) or cells (walls ``wall_um`` between the Voronoi cells of
    the sites), sites ``pitch_um`` apart, each moved by up to ``jitter`` × pitch."""

    name: str
    pitch_um: float
    wall_um: float
    r_outer_um: float | None = None
    jitter: float = 0.0

    def lattice(self, seed: int) -> Lattice:
        """The lattice of this reference; ``seed`` draws its sites' jitter."""
        family, packing = REFERENCES[self.name]
        if family == "tubes":
            r_outer = self.pitch_um / 2.0 if self.r_outer_um is None else self.r_outer_um
            return tube_lattice(self.pitch_um, r_outer, self.wall_um, packing=packing, jitter=self.jitter, seed=seed)
        return honeycomb(self.pitch_um, self.wall_um, packing=packing, jitter=self.jitter, seed=seed)

    def to_dict(self) -> dict:
        return asdict(self)


def reference(name: str, *, pitch_um: float | None, wall_um: float | None, r_outer_um: float | None = None,
              jitter: float = 0.0) -> Reference:
    """A validated :class:`Reference`; every bad value is a ParameterError naming the field."""
    if name not in REFERENCES:
        raise ParameterError(f"`reference` must be one of {', '.join(REFERENCES)}, got {name!r}")
    for field, value in (("pitch_um", pitch_um), ("wall_um", wall_um)):
        if value is None:
            raise ParameterError(f"`{field}` is required with a reference scene ({name}), e.g. "
                                 f"--pitch-um 14.5 --wall-um 2")
        if not (math.isfinite(value) and value > 0):
            raise ParameterError(f"`{field}` must be > 0 µm, got {field}={value:g}")
    if r_outer_um is not None and not name.startswith("tubes"):
        raise ParameterError(f"`r_outer_um` applies to tube references, not {name}")
    ref = Reference(name, float(pitch_um), float(wall_um), None if r_outer_um is None else float(r_outer_um),
                    float(jitter))
    try:
        ref.lattice(0)
    except ValueError as exc:  # the lattice's own checks name the field
        raise ParameterError(f"{exc} ({name})") from None
    return ref


def reference_medium(ref: Reference, *, seed: int, thickness_um: float, voxel_um: float, settings):
    """``ref`` of ``seed``, ``thickness_um`` thick, as the medium ``settings.method`` traces: its
    surfaces for ``exact``; for a voxel method, its voxelisation at ``voxel_um`` / refine."""
    lat = ref.lattice(seed)
    if settings.medium_kind == "surfaces":
        return lat.slab(thickness_um)
    return lat.source(thickness_um=thickness_um, voxel_um=traced_voxel_um(voxel_um, settings))


def scene_medium(*, wood, reference: Reference | None, seed: int, thickness_um: float, voxel_um: float, settings,
                 store=None, threads: int = 1):
    """The medium a scene traces: the reference lattice ``reference`` if given, else generated wood
    ``wood`` (:func:`~pipeline.optics.media.wood_medium`, its chunks from ``store`` when given), as
    ``settings.method`` traces it.  The one place a scene's medium is chosen."""
    if reference is not None:
        return reference_medium(reference, seed=seed, thickness_um=thickness_um, voxel_um=voxel_um, settings=settings)
    return wood_medium(wood, seed=seed, thickness_um=thickness_um, voxel_um=voxel_um, settings=settings, store=store,
                       threads=threads)
