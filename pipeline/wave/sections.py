"""R-T sections of twray's media, sampled for the wave solver from the model's own phase.

A section is uniform along L, so a 2-D field in the R-T plane is the exact scalar problem for
it, and rays launched in that plane stay in it: the reference lattices are sections by
construction; a wood is made one by :func:`extruded` (no ray cells, no fibre ends, the
fibres' jitter constant along L), and is sampled at L = 0 where ``exact`` traces the same wood.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..microstructure.model import generate_block
from ..params import Grid, WoodParams, validate
from .solver import Sampling

STRAIGHT_L_UM = 1e7  # control slices this far apart along L: the fibres' jitter is constant over a trace


def extruded(params: WoodParams) -> WoodParams:
    """``params`` as a section uniform along L: no ray cells, no end plates or fibre tips, no plies,
    control slices :data:`STRAIGHT_L_UM` apart."""
    return validate(dataclasses.replace(params, ray_cells=False, end_plates=False, fibre_tip_um=0.0, laminate=None,
                                        control_spacing_um=STRAIGHT_L_UM))


class LatticeSection:
    """A reference lattice (:class:`pipeline.optics.lattice.Lattice`) as a section."""

    def __init__(self, lattice):
        self.lattice = lattice

    def phase(self, r_um: np.ndarray, t_um: np.ndarray) -> np.ndarray:
        """(len(r_um), len(t_um)) uint8, 1 = wall."""
        return self.lattice.phase(r_um, t_um)


class WoodSection:
    """Generated wood of ``params`` (made :func:`extruded`) and ``seed``, at L = 0, as a section."""

    def __init__(self, params: WoodParams, seed: int):
        self.params = extruded(params)
        self.seed = int(seed)

    def phase(self, r_um: np.ndarray, t_um: np.ndarray) -> np.ndarray:
        """(len(r_um), len(t_um)) uint8 on the regular grids ``r_um``, ``t_um`` of one step
        (the generator's voxel centres)."""
        step = float(r_um[1] - r_um[0]) if r_um.size > 1 else float(t_um[1] - t_um[0])
        origin = (float(r_um[0]) - step / 2, float(t_um[0]) - step / 2, -step / 2)
        grid = Grid((r_um.size, t_um.size, 1), step, origin)
        return generate_block(self.params, grid, (0, 0, 0), (r_um.size, t_um.size, 1), seed=self.seed)[:, :, 0]


def wall_levels(section, *, r0_um: float, nx: int, j0: int, nz: int, sampling: Sampling) -> np.ndarray:
    """(nz, nx) uint8: the wall fraction, in levels of 1/sampling.levels, of cells [j0, j0 + nz)
    along T and [0, nx) along R from ``r0_um``, each the count of wall points of its
    ``per_dx`` × ``per_dz`` points of the ``sub_um`` grid."""
    s = sampling.sub_um
    r = r0_um + (np.arange(nx * sampling.per_dx) + 0.5) * s
    t = (j0 * sampling.per_dz + np.arange(nz * sampling.per_dz) + 0.5) * s
    ph = section.phase(r, t)
    counts = ph.reshape(nx, sampling.per_dx, nz, sampling.per_dz).sum(axis=(1, 3), dtype=np.int32)
    return np.ascontiguousarray(counts.T.astype(np.uint8))


def slices(section, *, r0_um: float, nx: int, nz: int, sampling: Sampling, block: int = 128):
    """The section's wall levels from T = 0, ``block`` slices at a time (an iterator of (≤block, nx))."""
    for j0 in range(0, nz, block):
        yield wall_levels(section, r0_um=r0_um, nx=nx, j0=j0, nz=min(block, nz - j0), sampling=sampling)
