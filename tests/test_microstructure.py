"""The wood model, measured: lumens, walls, vessels, ray cells, end plates, plies."""

import math
import time

import numpy as np
import pytest
from scipy import ndimage as ndi

from pipeline.microstructure.model import N_STATS, STAT_NAMES, generate_block, lumen_half_width_um
from pipeline.params import Grid, build_params, make_grid

V = 0.5  # µm


def block(size_um, *, seed, preset="birch", origin_um=(0.0, 0.0, 0.0), voxel_um=V, **overrides):
    p = build_params(preset, overrides=overrides)
    g = make_grid(size_um, voxel_um, origin_um, p)
    return generate_block(p, g, (0, 0, 0), g.shape, seed=seed)


def ridge_thickness_um(vol, voxel_um, step=10):
    """Median double-wall thickness from the distance-transform ridge of R-T slices."""
    out = []
    for k in range(0, vol.shape[2], step):
        wall = vol[:, :, k].astype(bool)
        d = ndi.distance_transform_edt(wall)
        ridge = wall & (d == ndi.maximum_filter(d, size=3))
        out.append(2.0 * d[ridge] - 1.0)
    return float(np.median(np.concatenate(out))) * voxel_um


def lumen_areas_um2(slice_rt, voxel_um):
    """Areas of the lumens (polymer components) not cut by the slice border."""
    lab, n = ndi.label(slice_rt == 0)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    areas = ndi.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
    keep = ~np.isin(np.arange(1, n + 1), border)
    return areas[keep] * voxel_um**2


@pytest.fixture(scope="module")
def birch():
    """The acceptance sample: 150 x 150 x 100 µm of birch at 0.5 µm."""
    return block((150, 150, 100), seed=1)


def test_birch_sample_shape_values_and_wall_fraction(birch):
    assert birch.shape == (300, 300, 200)
    assert birch.dtype == np.uint8
    assert set(np.unique(birch)) == {0, 1}
    assert 0.2 <= birch.mean() <= 0.4


def test_plain_fibre_lattice_wall_fraction_matches_geometry():
    # Inset ellipses in the brick lattice: 1 - π(c - t)(c + push - t) / (4c²) ≈ 0.323.
    vol = block((150, 150, 40), seed=2, vessels=False, ray_cells=False, end_plates=False,
                distortion=0.0, global_bend_um=0.0)
    c, t, push = 7.25, 1.0, 1.0
    expected = 1 - math.pi * (c - t) * (c + push - t) / (4 * c * c)
    assert vol.mean() == pytest.approx(expected, abs=0.02)


def test_fibre_lumen_size_distribution():
    vol = block((200, 200, 20), seed=3, vessels=False, ray_cells=False)
    areas = lumen_areas_um2(vol[:, :, 20], V)
    nominal = math.pi * (7.25 - 1.0) * (7.25 + 1.0 - 1.0)  # ≈ 142 µm²
    assert 150 < len(areas) <= 200  # (200 µm)² / (4 c²) ≈ 190 fibres, less those the border cuts
    assert np.median(areas) == pytest.approx(nominal, rel=0.15)
    # Jitter and per-cell walls spread the sizes, but no fibre is a vessel.
    spread = np.percentile(areas, 90) / np.percentile(areas, 10)
    assert 1.2 < spread < 2.5
    assert areas.max() < 3 * nominal


@pytest.mark.parametrize("wall_um, diameter_um", [(2.0, 14.5), (4.0, 29.0)])
def test_double_wall_thickness_follows_parameter(wall_um, diameter_um):
    # On 0.25 µm voxels: at 0.5 µm the ridge estimate moves in steps of ~0.5 µm from seed to seed.
    vol = block((100, 100, 20), seed=4, wall_thickness_um=wall_um, fibre_diameter_um=diameter_um,
                vessels=False, ray_cells=False, voxel_um=0.25)
    assert ridge_thickness_um(vol, 0.25) == pytest.approx(wall_um, abs=0.4)


def test_wall_thickness_doubles_when_parameter_doubles():
    thin = block((150, 150, 30), seed=5, fibre_diameter_um=29.0, vessels=False, ray_cells=False)
    thick = block((150, 150, 30), seed=5, fibre_diameter_um=29.0, wall_thickness_um=4.0,
                  vessels=False, ray_cells=False)
    ratio = ridge_thickness_um(thick, V) / ridge_thickness_um(thin, V)
    assert 1.6 < ratio < 2.4
    assert thick.mean() > thin.mean() + 0.1


@pytest.mark.parametrize("vessels", [True, False])
def test_vessels_present_or_absent(vessels):
    vol = block((400, 400, 2), seed=6, voxel_um=1.0, vessels=vessels, ray_cells=False)
    areas = lumen_areas_um2(vol[:, :, 1], 1.0)
    fibre = np.median(areas)
    n_large = int(np.sum(areas > 6 * fibre))
    if vessels:
        # Birch: a vessel lumen ≈ π·19·20 µm² ≈ 8 fibre lumens; tens per mm².
        assert n_large >= 4
        assert np.median(areas[areas > 6 * fibre]) == pytest.approx(
            math.pi * (3.2 * 7.25 - 2.5) * (3 * 7.25 - 2.5), rel=0.3)
    else:
        assert n_large == 0


def ray_cell_lumens(vol, voxel_um):
    """Polymer components shaped like ray cells: longer along R than along L, short in L."""
    lab, n = ndi.label(vol == 0)
    count = 0
    for sl in ndi.find_objects(lab):
        ext = [(s.stop - s.start) * voxel_um for s in sl]
        if ext[2] < 25 and ext[0] > 1.2 * ext[2] and ext[0] > 10 and sl[2].start > 0 \
                and sl[2].stop < vol.shape[2]:
            count += 1
    return count


@pytest.mark.parametrize("ray_cells", [True, False])
def test_ray_cells_present_or_absent(ray_cells):
    vol = block((120, 300, 600), seed=7, voxel_um=1.0, ray_cells=ray_cells, vessels=False)
    n = ray_cell_lumens(vol, 1.0)
    if ray_cells:
        assert n >= 10
    else:
        assert n == 0


def end_plates(vol, voxel_um, plate_max_um=4.0, open_min_um=5.0):
    """Count short wall runs along L between two long polymer runs (closed lumens)."""
    count = 0
    for col in vol.reshape(-1, vol.shape[2]):
        edges = np.flatnonzero(np.diff(col.astype(np.int8))) + 1
        runs = np.diff(np.concatenate([[0], edges, [col.size]]))
        vals = col[np.concatenate([[0], edges])]
        for q in range(1, len(runs) - 1):
            if (vals[q] == 1 and runs[q] * voxel_um <= plate_max_um
                    and runs[q - 1] * voxel_um >= open_min_um and runs[q + 1] * voxel_um >= open_min_um):
                count += 1
    return count


def ray_row_distance_um(p, seed, t_um):
    """Distance along T from each of ``t_um`` to the nearest ray column's node row [µm]."""
    from pipeline.microstructure import _constants, _ray_cells
    from pipeline.microstructure.model import model_constants

    M = model_constants(p)
    k = np.arange(math.floor(t_um.min() / (M[_constants.RSPACE] * M[_constants.PITCH])) - 2,
                  math.ceil(t_um.max() / (M[_constants.RSPACE] * M[_constants.PITCH])) + 3)
    rows = np.array([_ray_cells.ray_row(seed, M, int(q)) for q in k]) * M[_constants.PITCH]
    return np.min(np.abs(t_um[:, None] - rows[None, :]), axis=1)


def test_switching_ray_cells_off_changes_the_ray_tissue_alone():
    """One factor at a time (study 5-1): the same vessels, and the same voxels farther than the
    ray band and its squeeze (~80 µm) from every ray column."""
    from pipeline.microstructure import _vessels
    from pipeline.microstructure.model import model_constants

    seed = 3
    p_on, p_off = build_params("birch"), build_params("birch", overrides={"ray_cells": False})
    on = block((200, 600, 200), seed=seed, voxel_um=1.0)
    off = block((200, 600, 200), seed=seed, voxel_um=1.0, ray_cells=False)
    lists = []
    for p in (p_on, p_off):
        out = np.empty((4096, 5), np.int64)
        n = _vessels.vessels_in_region(seed, model_constants(p), -40, 70, -40, 120, out)
        lists.append(out[:n])
    assert len(lists[0]) >= 20 and np.array_equal(lists[0], lists[1])
    differ = on != off
    assert 0.02 < differ.mean() < 0.3  # the ray tissue is there, then gone
    far = ray_row_distance_um(p_on, seed, np.arange(on.shape[1]) * 1.0) > 80.0
    assert far.sum() >= 30 and not differ[:, far, :].any()


def test_switching_vessels_off_leaves_the_fibres_away_from_vessels():
    """Study 5-2: the fibre lattice does not move; fibres differ only where the vessels stood
    and where the vessels pushed them (a dipole decaying over ~100 µm)."""
    from pipeline.microstructure import _constants, _vessels
    from pipeline.microstructure.model import model_constants

    seed = 3
    on = block((200, 400, 50), seed=seed, voxel_um=1.0)
    off = block((200, 400, 50), seed=seed, voxel_um=1.0, vessels=False)
    M = model_constants(build_params("birch"))
    out = np.empty((4096, 5), np.int64)
    n = _vessels.vessels_in_region(seed, M, -40, 70, -40, 90, out)
    c_r, c_t = out[:n, 0] * M[_constants.PITCH], out[:n, 1] * M[_constants.PITCH]
    r, t = np.arange(on.shape[0]) * 1.0, np.arange(on.shape[1]) * 1.0
    dist = np.sqrt((r[:, None, None] - c_r) ** 2 + (t[None, :, None] - c_t) ** 2).min(axis=2)
    differ = (on != off).mean(axis=2)
    assert differ[dist < 20].mean() > 0.2  # vessel lumens became fibres
    assert (dist > 80).sum() > 500 and differ[dist > 80].mean() < 1e-3


def test_fibre_end_plates_close_lumens():
    with_plates = block((100, 100, 300), seed=8, voxel_um=1.0, vessels=False, ray_cells=False)
    without = block((100, 100, 300), seed=8, voxel_um=1.0, vessels=False, ray_cells=False,
                    end_plates=False)
    # ≈ 50 fibres x 300/1170 ends each; a plate spans tens of (R, T) columns.
    n_with, n_without = end_plates(with_plates, 1.0), end_plates(without, 1.0)
    assert n_with > 200
    # Without plates only rare wiggles of a lumen edge look like one.
    assert n_without < 0.05 * n_with
    diff = with_plates != without
    assert diff.any() and np.all(with_plates[diff] == 1)  # plates only add wall


def mean_run_of_lines(lines):
    """Mean length of polymer runs along a set of 1-D lines."""
    runs = []
    for line in lines:
        d = np.diff(np.pad(line == 0, 1).astype(np.int8))
        runs.append(np.flatnonzero(d == -1) - np.flatnonzero(d == 1))
    return float(np.mean(np.concatenate(runs)))


def mean_run(img, axis):
    """Mean polymer run along an axis of a 2-D image."""
    return mean_run_of_lines(np.moveaxis(img, axis, 0).T)


def diag_runs(img):
    """Mean polymer run along the R+L and the R-L diagonals of an (R, L) image."""
    n = min(img.shape)
    offsets = range(-n // 2, n // 2)
    diag = [np.diagonal(img, o) for o in offsets]
    anti = [np.diagonal(img[::-1], o) for o in offsets]
    return mean_run_of_lines(diag), mean_run_of_lines(anti)


def test_laminate_plies_are_rotated_in_the_LR_plane():
    vol = block((150, 100, 150), seed=9, laminate=(0, 90, 45, -45), ply_thickness_um=25.0,
                vessels=False, ray_cells=False)
    plies = [vol[:, 50 * q + 25, :] for q in range(4)]  # (R, L) images mid-ply
    r0, l0 = mean_run(plies[0], 0), mean_run(plies[0], 1)
    r90, l90 = mean_run(plies[1], 0), mean_run(plies[1], 1)
    assert l0 > 4 * r0  # fibres along L
    assert r90 > 4 * l90  # fibres along R
    d45, a45 = diag_runs(plies[2])
    dm45, am45 = diag_runs(plies[3])
    # ±45° plies: fibres along one diagonal of the L-R plane, the other for -45°.
    assert max(d45, a45) > 3 * min(d45, a45)
    assert max(dm45, am45) > 3 * min(dm45, am45)
    assert (d45 > a45) != (dm45 > am45)


def test_laminate_ply_boundaries_follow_T():
    vol = block((60, 100, 60), seed=10, laminate=(0, 90), ply_thickness_um=50.0)
    plain = block((60, 100, 60), seed=10)
    # The first ply is a rotated copy of nothing: an unrotated ply with its own seed
    # and offset, so it differs from the plain wood but has the same wall fraction.
    assert not np.array_equal(vol[:, :100], plain[:, :100])
    assert abs(vol[:, :100].mean() - plain[:, :100].mean()) < 0.08


def test_balsa_thin_walls_and_solid_fraction():
    vol = block((200, 200, 100), seed=11, preset="balsa")
    assert 0.07 <= vol.mean() <= 0.15
    # Walls of 2.8 voxels at 0.5 µm: measured on 0.25 µm voxels, where the ridge estimate is finer.
    fibres = block((120, 120, 10), seed=11, preset="balsa", vessels=False, ray_cells=False, voxel_um=0.25)
    assert ridge_thickness_um(fibres, 0.25, step=5) == pytest.approx(1.4, abs=0.4)


def test_same_seed_same_voxels_other_seed_other_voxels():
    a = block((40, 40, 40), seed=12)
    b = block((40, 40, 40), seed=12)
    c = block((40, 40, 40), seed=13)
    assert np.array_equal(a, b)
    assert (a != c).mean() > 0.2


@pytest.mark.parametrize("overrides", [{}, {"fibre_tip_um": 60.0}], ids=["flat ends", "fibre tips"])
def test_a_block_is_the_same_voxels_as_the_corresponding_part_of_a_larger_one(overrides):
    p = build_params("birch", overrides=overrides)
    g = make_grid((100, 100, 100), V, (0, 0, 0), p)
    whole = generate_block(p, g, (0, 0, 0), g.shape, seed=14)
    part = generate_block(p, g, (37, 101, 55), (50, 60, 70), seed=14)
    assert np.array_equal(part, whole[37:87, 101:161, 55:125])


def test_region_10_mm_away_costs_the_same_as_at_the_origin():
    """Nothing is walked from the origin: the work for a block is set by the block.

    Work counters are compared (they vary only with the local amount of
    distortion), and, as a guard on what counters cannot see, the time ratio
    with a generous bound: walking fibre chains from the origin would cost ~9x.
    """
    p = build_params("birch")
    shape = (96, 96, 96)
    counts, times = [], []
    for origin in [(0.0, 0.0, 0.0), (10_000.0, 10_000.0, 10_000.0)]:
        g = make_grid((48, 48, 48), V, origin, p)
        generate_block(p, g, (0, 0, 0), shape, seed=15)  # warm the distortion-tile cache
        stats = np.zeros(N_STATS, np.int64)
        best = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            vol = generate_block(p, g, (0, 0, 0), shape, seed=15, stats=stats)
            best = min(best, time.perf_counter() - t0)
        counts.append(dict(zip(STAT_NAMES, stats // 3)))
        times.append(best)
        assert 0.2 < vol.mean() < 0.45
    near, far = counts
    assert far["voxels"] == near["voxels"]
    for name in ("node_states", "chain_lookups"):
        assert far[name] == pytest.approx(near[name], rel=0.3), name
    assert times[1] < 2.0 * times[0]


# Digests of blocks generated at HEAD of the micro cache version below.  The
# cached wood (results/cache/micro) is keyed by parameters and that version,
# not by the code, so a change of voxels must come with a new version.
PINNED = [
    # (preset, overrides, start, shape, what the block holds, sha256 of its bytes)
    ("birch", {}, (0, 512, 0), (64, 64, 64), "a biseriate ray band",
     "cc4454cab98ec585c659bb681c1d549ecdb8843de8b825569a9a9db27d2e0014"),
    ("birch", {}, (640, 768, -128), (64, 64, 64), "a vessel",
     "59a46577765c2fcf2da261222275d4eafdbad82f9b864cbb5816b43e0d03bee1"),
    ("birch", {}, (-1060, 400, 0), (64, 64, 64), "the shared wall of a vessel pair",
     "925d671d9674f43cbb533a889e58f9403a11700a6f4e15f77e04d311b02c0198"),
    ("birch", {"ray_cells": False}, (0, 512, 0), (64, 64, 64), "where a ray band is, without ray cells",
     "a34e53a590947b10d37ab0a25289f2bff77d278b95c194fdc23d1a58223ff13f"),
    ("balsa", {}, (0, 0, 0), (48, 48, 48), "polygon cells",
     "071386c8f93bd6e373c5c6cdc6fe786a83e8d6952167bd808c85d09986d192e2"),
    ("birch", {"fibre_tip_um": 150.0}, (0, 0, 0), (64, 64, 64), "overlapping fibre tips",
     "ec97ef734a02ce2d604e6bbbd4a58ec8c27919a423d0caf50c3e151421a67c79"),
    ("birch", {"laminate": [0, -45, 90, 45, 0]}, (0, 0, 0), (48, 48, 48), "rotated plies",
     "7654afa564a6dbc9740f017a22874067d71f25cc670f510d67614cb03be2606e"),
]


@pytest.mark.parametrize("preset, overrides, start, shape, holds, digest", PINNED,
                         ids=[row[4] for row in PINNED])
def test_generated_voxels_are_pinned_for_the_cache_version(preset, overrides, start, shape, holds,
                                                           digest):
    import hashlib

    from pipeline.versions import STAGES as VERSIONS

    p = build_params(preset, overrides=overrides)
    g = make_grid((100, 100, 100), V, (0, 0, 0), p)
    got = hashlib.sha256(generate_block(p, g, start, shape, seed=1).tobytes()).hexdigest()
    # Version 2 holds the voxels of version 1, stored with chunk digests; version 3 those of
    # version 2 wherever the wood has ray cells (without them, vessels no longer move).
    assert VERSIONS["micro"] == "3", "new micro version: re-pin these digests"
    assert got == digest, (f"the voxels of {holds} changed; if that is intended, bump "
                           f"STAGES['micro'] in pipeline/versions.py and re-pin")


def test_the_same_wood_at_half_the_voxel_agrees_at_every_shared_voxel_centre():
    """What `refine` relies on: the model is a function of position, so wood generated on
    0.25 µm voxels is the 0.5 µm wood at the centres the two grids share."""
    p = build_params("birch")
    coarse = generate_block(p, Grid((0, 0, 0), 0.5, (0.0, 0.0, 0.0)), (-20, 3, 40), (48, 40, 32), seed=4)
    fine = generate_block(p, Grid((0, 0, 0), 0.25, (0.125, 0.125, 0.125)), (-40, 6, 80), (96, 80, 64), seed=4)
    assert 0.2 < coarse.mean() < 0.6
    assert np.array_equal(coarse, fine[::2, ::2, ::2])


def wall_runs_inside_lumens_um(vol, voxel_um, open_min_um=5.0):
    """Lengths of the wall runs along L that close a lumen: between two polymer runs of
    at least ``open_min_um`` (end plates, or the oblique walls between fibre tips)."""
    out = []
    for col in vol.reshape(-1, vol.shape[2]):
        edges = np.flatnonzero(np.diff(col.astype(np.int8))) + 1
        runs = np.diff(np.concatenate([[0], edges, [col.size]]))
        vals = col[np.concatenate([[0], edges])]
        for q in range(1, len(runs) - 1):
            if vals[q] == 1 and min(runs[q - 1], runs[q + 1]) * voxel_um >= open_min_um:
                out.append(runs[q] * voxel_um)
    return np.array(out)


@pytest.fixture(scope="module")
def tip_woods():
    """The plain fibre lattice (no vessels, rays or distortion) with flat end plates and with
    overlapping fibre tips of 75 and 150 µm; 100 x 100 x 900 µm at 1 µm."""
    common = dict(seed=8, voxel_um=1.0, vessels=False, ray_cells=False, distortion=0.0,
                  global_bend_um=0.0, node_jitter=0.0, wall_variation=0.0)
    return {tip: block((100, 100, 900), fibre_tip_um=float(tip), **common) for tip in (0, 75, 150)}


def test_fibre_tips_are_oblique_walls_inclined_by_their_length(tip_woods):
    """Between overlapping tips the lumen is crossed by a wall 2t thick whose trace moves across
    the lumen (half-width w) at w/λ per µm of L; a line along L inside the lumen therefore meets
    wall over 2t·λ/w µm: a slope of w/λ (2.4° at λ = 150 µm), against 2 µm flat plates."""
    t, w = 1.0, lumen_half_width_um(build_params("birch"))  # w ≈ 6.74 µm
    flat = wall_runs_inside_lumens_um(tip_woods[0], 1.0)
    assert flat.size > 200 and np.median(flat) <= 3.0  # the 2 µm end plates
    medians = {}
    for lam in (75, 150):
        runs = wall_runs_inside_lumens_um(tip_woods[lam], 1.0)
        assert runs.size > 200
        medians[lam] = float(np.median(runs))
        expected = 2 * t * lam / w
        assert 0.85 * expected < medians[lam] < 1.15 * expected, (lam, medians[lam], expected)
        assert np.mean(runs <= 3.0) < 0.05  # no flat plate is left
    assert 1.7 < medians[150] / medians[75] < 2.3


def test_fibre_tips_add_the_wall_of_their_oblique_plates(tip_woods):
    """Each fibre boundary (one per ~1170 µm of a fibre) trades a 2 µm flat plate across the
    lumen for an oblique wall of volume 2t·λ·A/w (A the lumen area): the wall fraction grows
    by the lumen fraction times (2tλ/w − 2 µm)/1170 µm."""
    t, ell, w = 1.0, 1170.5, lumen_half_width_um(build_params("birch"))
    lumen = 1.0 - tip_woods[0].mean()
    for lam in (75, 150):
        grown = tip_woods[lam].mean() - tip_woods[0].mean()
        expected = lumen * (2 * t * lam / w - 2.0) / ell
        assert 0.85 * expected < grown < 1.15 * expected, (lam, grown, expected)


def test_fibre_tips_leave_everything_but_the_fibre_ends():
    """Tips change the walls near fibre boundaries only: vessels, rays and lumen outlines stay."""
    flat = block((100, 100, 200), seed=5, voxel_um=1.0)
    tips = block((100, 100, 200), seed=5, voxel_um=1.0, fibre_tip_um=150.0)
    differ = flat != tips
    assert 0.002 < differ.mean() < 0.05
    # Oblique walls fill lumen (polymer -> wall); the flat plates they replace open (wall -> polymer).
    assert (tips[differ] == 1).mean() > 0.7


KEY_TABLE1_DEFAULT_WOOD = "b10f58756b3b44b14247aeb4"  # birch, seed 1, traced on 0.25 µm voxels


def test_a_wood_without_fibre_tips_keeps_its_cache_key():
    """fibre_tip_um is left out of cache keys at 0, so the woods traced before it existed
    (every committed study) keep their keys and cached chunks."""
    from pipeline.microstructure.store import wood_record

    birch = build_params("birch")
    assert "fibre_tip_um" not in wood_record(birch, 1, 0.25)["wood"]
    tipped = build_params("birch", overrides={"fibre_tip_um": 150.0})
    assert wood_record(tipped, 1, 0.25)["wood"]["fibre_tip_um"] == 150.0
    # The key of Table 1's default wood, realisation 0, as the committed studies were traced.
    from pipeline.cache import cache_key
    assert cache_key(wood_record(birch, 1, 0.25)) == KEY_TABLE1_DEFAULT_WOOD
