"""Building blocks of the model: counter-based randomness, renewal chains, vessel layout."""

import numpy as np
import pytest
from scipy import stats

from pipeline.microstructure import _constants, _lattice, _ray_cells, _vessels
from pipeline import rng as _rng
from pipeline.microstructure.model import model_constants
from pipeline.params import build_params


def test_hashed_uniforms_are_uniform_and_independent_of_call_order():
    seed = np.uint64(31)
    u = np.array([_rng.uniform(seed, _rng.NODE_R, i, -i, 7) for i in range(-5000, 5000)])
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    again = np.array([_rng.uniform(seed, _rng.NODE_R, i, -i, 7) for i in reversed(range(-5000, 5000))])
    assert np.array_equal(u, again[::-1])
    other = np.array([_rng.uniform(np.uint64(32), _rng.NODE_R, i, -i, 7) for i in range(-5000, 5000)])
    assert abs(np.corrcoef(u, other)[0, 1]) < 0.05


def test_fibre_chain_lengths_follow_the_length_distribution():
    seed, mean, sd, min_len = np.uint64(5), 1170.5, 290.5, 50.0
    x, lengths = -2.0e6, []
    while x < 2.0e6:  # walk the chain across the origin, far into negative L
        lo, hi = _lattice.chain_interval(x, seed, _rng.FIBRE_END, 3, -4, 100.0, mean, sd, min_len)
        assert lo <= x < hi
        lengths.append(hi - lo)
        x = hi
    lengths = np.array(lengths)
    assert lengths.mean() == pytest.approx(mean, rel=0.02)
    assert lengths.std() == pytest.approx(sd, rel=0.1)
    assert lengths.min() >= min_len


def test_vessel_layout_does_not_depend_on_the_region_asked_for():
    M = model_constants(build_params("birch"))
    seed = np.uint64(8)
    big = np.empty((4096, 5), np.int64)
    nb = _vessels.vessels_in_region(seed, M, -100, 100, -100, 100, big)
    small = np.empty((4096, 5), np.int64)
    ns = _vessels.vessels_in_region(seed, M, 10, 40, -30, 0, small)
    in_small = {tuple(r[:2]) for r in small[:ns]}
    in_big = {tuple(r[:2]) for r in big[:nb]}
    assert ns > 0 and in_small <= in_big
    # Hard core: members of different clusters never come closer than the box.
    rows = big[:nb]
    for i in range(nb):
        for j in range(i + 1, nb):
            if rows[i, 2] != rows[j, 2]:
                assert (abs(rows[i, 0] - rows[j, 0]) >= _constants.VHARD_R
                        or abs(rows[i, 1] - rows[j, 1]) >= _constants.VHARD_T)
    # Vessels keep clear of ray rows.
    for m in rows[:, 1]:
        assert not _ray_cells.near_ray(seed, M, m, _constants.VRAY_CLEAR)
