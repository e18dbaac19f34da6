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


def test_the_pull_back_bound_holds_between_any_two_points_of_a_tile_and_is_nearly_reached():
    """`exact` steps blindly by clearance / (the pull-back's Lipschitz bound): the bilinear
    pull-back of a real distortion tile never moves two points of the tile apart faster than the
    bound says, and the bound is not loose (its excess over 1 mostly reached), or steps would be
    needlessly short."""
    from pipeline.microstructure._distortion import pull_back
    from pipeline.microstructure.model import _tile
    from pipeline.microstructure.region import lipschitz_of_pull_back

    M = model_constants(build_params("birch"))
    G = M[_constants.PITCH] / _constants.GRID_PER_PITCH
    span = _constants.TILE * G
    rng = np.random.default_rng(5)
    for a, b in [(0, 0), (3, -2), (-7, 11)]:
        tile, _ = _tile(4, M.tobytes(), a, b)
        bound = lipschitz_of_pull_back(tile, G)
        worst = 0.0
        for _ in range(4000):
            p = np.array([a, b]) * span + rng.uniform(0.02, 0.98, 2) * span
            q = p + rng.normal(size=2) * rng.choice([1e-3, 0.1, 1.0, 5.0])
            if not (a * span <= q[0] < (a + 1) * span and b * span <= q[1] < (b + 1) * span):
                continue
            P = np.array(pull_back(tile, a * _constants.TILE, b * _constants.TILE, G, p[0], p[1]))
            Q = np.array(pull_back(tile, a * _constants.TILE, b * _constants.TILE, G, q[0], q[1]))
            worst = max(worst, np.linalg.norm(P - Q) / np.linalg.norm(p - q))
        assert 1.0 + 0.5 * (bound - 1.0) < worst <= bound, (a, b, worst, bound)


def test_a_woods_tiles_are_computed_once_up_to_its_ceiling_and_woods_are_let_go_whole(monkeypatch):
    """A worker keeps every distortion tile of the wood it traces up to the wood's ceiling (beyond the
    budget), lets other woods go whole, least recently used first, and past the ceiling the wood's
    own least recently used tiles: a wood's tiles are computed once while its shards run, the tiles
    its regions keep using stay however far other rays wander, and a tile computed again is the same."""
    from pipeline.microstructure import model

    M = model_constants(build_params("birch")).tobytes()
    computed = []
    kernel = model.distortion_tile

    def counted(seed, *args):
        computed.append((int(seed), int(args[1]), int(args[2])))
        return kernel(seed, *args)

    monkeypatch.setattr(model, "distortion_tile", counted)
    tiles = model._WoodTiles(budget=4, wood_cap=8)
    first = {}
    for _ in range(3):  # wood 1's shards: 6 tiles, over the budget of 4, each computed once
        for a in range(6):
            (tile, _), _ = tiles.get(1, M, a, 0)
            first.setdefault(a, tile)
    assert computed == [(1, a, 0) for a in range(6)] and tiles.held == 6
    tiles.get(2, M, 0, 0)  # another wood: wood 1 is let go whole
    assert tiles.held == 1 and list(tiles.woods) == [(2, M)]
    (again, _), made = tiles.get(1, M, 3, 0)
    assert made and np.array_equal(again, first[3])  # a tile is a pure function of its key
    (_, _), made = tiles.get(2, M, 0, 0)
    assert not made and tiles.held == 2  # within the budget both woods stay
    computed.clear()
    for a in range(10, 30):  # wood 3: a ray wandering over 20 tiles while tile (0, 0) is used throughout
        tiles.get(3, M, 0, 0)
        tiles.get(3, M, a, 0)
        assert len(tiles.woods[(3, M)]) <= 8 and tiles.held == sum(len(t) for t in tiles.woods.values())
    assert list(tiles.woods) == [(3, M)] and list(tiles.woods[(3, M)])[-2:] == [(0, 0), (29, 0)]
    assert computed.count((3, 0, 0)) == 1 and len(computed) == 21  # the tile in use never again
