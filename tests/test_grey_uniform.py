"""Grey scans made with proven one-phase voxels (pipeline/microstructure/_grey_uniform.py): the
same numbers as supersampling every voxel, with most voxels not supersampled."""

import numpy as np
import pytest

from pipeline.microstructure import grey
from pipeline.microstructure._grey_uniform import UniformVoxels, applies
from pipeline.microstructure.model import generate_block
from pipeline.params import Grid, build_params

WOODS = {
    "balsa": ("balsa", {}),
    # Rotated plies: the generator classifies their fine voxels at a rounded L', which the proof's
    # radius must cover; plies 12 µm thick, so the part below crosses two ply boundaries.
    "balsa laminate [0/30/-60]": ("balsa", {"laminate": (0, 30, -60), "ply_thickness_um": 12.0}),
}


@pytest.mark.parametrize("wood", WOODS)
def test_proven_voxels_give_the_supersampled_scan_bit_for_bit(wood):
    preset, overrides = WOODS[wood]
    p = build_params(preset, overrides=overrides)
    g = Grid((90, 61, 37), 0.5, (-20.0, 0.0, -9.0))  # tiles and boxes cut short at the edges
    proven = grey.LazyGreyScan(p, g, seed=4, supersample=3)
    every = grey.LazyGreyScan(p, g, seed=4, supersample=3)
    assert proven.uniform is not None
    every.uniform = None  # each voxel supersampled, as for birch
    a, b = proven[:, :, :], every[:, :, :]
    np.testing.assert_array_equal(a, b)
    # Both phases and the walls between them are in the part, and most voxels were decided on
    # fewer than one point evaluation each instead of 27 fine voxels.
    assert 0.03 < a.mean() < 0.5 and ((a > 0) & (a < 1)).mean() > 0.02
    assert proven.uniform.evaluations < 0.75 * a.size
    assert np.array_equal(grey.grey_volume(p, g, seed=4, supersample=3), b)


def test_only_scans_of_polygonal_cells_inside_the_slab_are_proven():
    """Birch's fibre lumens are cheaper to supersample than to evaluate (docs/performance.md), and
    the model lists no ply below T = 0."""
    balsa = build_params("balsa")
    assert applies(balsa, Grid((8, 8, 8), 0.5, (0.0, 0.0, 0.0)))
    assert not applies(balsa, Grid((8, 8, 8), 0.5, (0.0, -1.0, 0.0)))
    assert not applies(build_params("birch"), Grid((8, 8, 8), 0.5, (0.0, 0.0, 0.0)))
    assert grey.LazyGreyScan(build_params("birch"), Grid((8, 8, 8), 0.5), seed=1).uniform is None


@pytest.mark.parametrize("wood", WOODS)
def test_a_voxel_is_proven_only_where_no_fine_voxel_can_differ(wood):
    """Every proven voxel's fine voxels all have its phase; every voxel whose fine voxels differ is
    left undecided (NaN)."""
    preset, overrides = WOODS[wood]
    p = build_params(preset, overrides=overrides)
    g = Grid((45, 38, 23), 0.5, (-8.0, 3.0, -5.0))
    s = 4
    known = UniformVoxels(p, g, 9, s).decide((0, 0, 0), g.shape)
    fine = generate_block(p, Grid(tuple(n * s for n in g.shape), g.voxel_um / s, g.origin_um), (0, 0, 0),
                          tuple(n * s for n in g.shape), seed=9)
    frac = fine.reshape(45, s, 38, s, 23, s).mean(axis=(1, 3, 5))
    decided = ~np.isnan(known)
    assert decided.mean() > 0.4
    np.testing.assert_array_equal(known[decided], frac[decided])
    mixed = (frac > 0) & (frac < 1)
    assert mixed.any() and not (mixed & decided).any()


def test_a_block_generated_where_needed_holds_those_voxels_only():
    p = build_params("birch")
    g = Grid((4000, 4000, 4000), 0.25, (-500.0, 0.0, -500.0))
    start, shape = (2000, 30, 2000), (24, 16, 32)
    full = generate_block(p, g, start, shape, seed=2)
    need = np.random.default_rng(1).random((6, 4, 8)) < 0.3
    part = generate_block(p, g, start, shape, seed=2, need=need.view(np.uint8))
    wanted = need.repeat(4, 0).repeat(4, 1).repeat(4, 2)
    np.testing.assert_array_equal(part[wanted], full[wanted])
    assert not part[~wanted].any()
    for bad in ((5, 4, 8), (0, 4, 8), (6, 4)):
        with pytest.raises(ValueError, match=rf"need of shape \({', '.join(map(str, bad))},?\) does not divide "
                                             r"the block \(24, 16, 32\)"):
            generate_block(p, g, start, shape, seed=2, need=np.ones(bad, np.uint8))
