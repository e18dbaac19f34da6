"""The exact references themselves (docs/methods.md#exact-references): lattices of tubes and honeycombs, traced exactly."""


import numpy as np
import pytest

from pipeline.analysis import fwhm, haze
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import settings_for
from pipeline.optics.lattice import honeycomb, tube_lattice
from pipeline.optics.validation import compare_with_exact, rod_deflection_deg, smoothed_ks, tube_deflection_deg

INDICES = [(1.50, 1.49), (1.49, 1.50), (1.51, 1.49), (1.49, 1.52)]


def lattices():
    """One of each family and packing, touching, merged and apart, jittered and regular."""
    return {
        "tubes square touching": tube_lattice(14.5, 7.25, 1.0, rotation_deg=8.0),
        "tubes hex merged": tube_lattice(14.5, 7.6, 1.4, packing="hex", rotation_deg=5.0),
        "tubes square apart": tube_lattice(20.0, 8.0, 3.0, rotation_deg=3.0),
        "honeycomb hex jittered": honeycomb(14.5, 2.0, jitter=0.15, seed=3),
        "honeycomb square": honeycomb(12.0, 1.5, packing="square", rotation_deg=3.0, jitter=0.05, seed=1),
    }


@pytest.mark.parametrize("n_wall, n_poly", [(1.50, 1.49), (1.49, 1.50), (1.60, 1.40)])
def test_one_rod_of_a_sparse_lattice_follows_the_rod_law_to_machine_precision(n_wall, n_poly):
    rod = tube_lattice(1000.0, 20.0, 20.0, origin_um=(0.0, 500.0))  # one rod ahead, the next far away
    b = np.linspace(-19.95, 19.95, 81)
    res = rod.trace_independently(np.column_stack([b, 0 * b, 0 * b]), (0, 1, 0), n_wall=n_wall, n_poly=n_poly,
                    thickness_um=1000.0)
    with np.errstate(invalid="ignore"):
        law = rod_deflection_deg(b, 20.0, n_wall / n_poly)
    ok = np.isfinite(law) & (res.events == 2)  # a less dense rod reflects the grazing rays totally
    assert ok.sum() > 60
    assert np.all(res.transmitted)
    np.testing.assert_allclose(res.theta_r[ok], law[ok], atol=1e-9)


def test_one_tube_follows_the_tube_law_and_reflects_totally_where_it_says():
    tube = tube_lattice(1000.0, 20.0, 3.0, origin_um=(0.0, 500.0))
    b = np.linspace(-19.95, 19.95, 161)
    res = tube.trace_independently(np.column_stack([b, 0 * b, 0 * b]), (0, 1, 0), n_wall=1.50, n_poly=1.49,
                     thickness_um=1000.0)
    law = tube_deflection_deg(b, 20.0, 3.0, 1.50 / 1.49)
    ok = np.isfinite(law)
    np.testing.assert_allclose(res.theta_r[ok], law[ok], atol=1e-9)
    # Through the lumen: four interfaces; past it: two; in between, reflected inside the wall.
    assert set(res.events[ok & (np.abs(b) < 17.0)]) == {4}
    assert set(res.events[ok & (np.abs(b) > 17.0 * 1.50 / 1.49)]) == {2}
    assert np.all(res.events[~ok] > 2)


@pytest.mark.parametrize("name", list(lattices()))
def test_index_matched_lattices_let_every_ray_through_undeflected(name):
    lat = lattices()[name]
    beam = square_beam(300, 150.0, seed=2)
    res = lat.trace_independently(beam.origins * 0.5, (0, 1, 0), n_wall=1.5, n_poly=1.5, thickness_um=100.0)
    assert np.all(res.transmitted) and res.events.sum() > 300
    assert np.all(res.direction == [0.0, 1.0, 0.0])


@pytest.mark.parametrize("lat", [tube_lattice(14.5, 7.6, 1.4, packing="hex"), honeycomb(14.5, 2.0),
                                 tube_lattice(14.5, 7.25, 1.0)],
                         ids=["tubes hex", "honeycomb hex", "tubes square"])
def test_a_lattice_symmetric_about_r_0_deflects_mirror_rays_oppositely(lat):
    b = np.linspace(0.113, 40.113, 57)
    o = np.column_stack([np.concatenate([b, -b]), np.zeros(114), np.zeros(114)])
    res = lat.trace_independently(o, (0, 1, 0), n_wall=1.50, n_poly=1.49, thickness_um=60.0)
    np.testing.assert_allclose(res.theta_r[:57], -res.theta_r[57:], atol=1e-9)
    assert np.array_equal(res.events[:57], res.events[57:])
    assert np.abs(res.theta_r).max() > 1.0


@pytest.mark.parametrize("name", list(lattices()))
@pytest.mark.parametrize("n_wall, n_poly", [(1.50, 1.49), (1.49, 1.51)])
def test_an_exit_ray_traced_back_arrives_where_its_entry_ray_came_from(name, n_wall, n_poly):
    lat = lattices()[name]
    rng = np.random.default_rng(11)
    n = 300
    o = np.column_stack([rng.uniform(-70, 70, n), np.zeros(n), rng.uniform(-5, 5, n)])
    d = np.column_stack([rng.normal(0, 0.1, n), np.ones(n), rng.normal(0, 0.1, n)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    fwd = lat.trace_independently(o, d, n_wall=n_wall, n_poly=n_poly, thickness_um=150.0)
    t = fwd.transmitted
    assert t.mean() > 0.95 and fwd.events[t].mean() > 10
    back = lat.trace_independently(fwd.position[t], -fwd.direction[t], n_wall=n_wall, n_poly=n_poly, thickness_um=150.0,
                     backwards=True)
    assert np.all(back.transmitted)
    assert np.array_equal(back.events, fwd.events[t])
    np.testing.assert_allclose(back.position, o[t], atol=1e-5)
    np.testing.assert_allclose(-back.direction, d[t], atol=1e-7)


@pytest.mark.parametrize("name", list(lattices()))
def test_directions_stay_unit_and_the_optical_momentum_along_l_is_conserved(name):
    """Every normal lies in the R-T plane, so n·d_L is the same in every phase (Snell's
    law along L), and a total reflection keeps d_L."""
    lat = lattices()[name]
    n_wall, n_poly = 1.52, 1.48
    rng = np.random.default_rng(5)
    n = 400
    o = np.column_stack([rng.uniform(-70, 70, n), np.zeros(n), np.zeros(n)])
    d = np.column_stack([rng.normal(0, 0.2, n), np.ones(n), rng.uniform(0.1, 0.6, n)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    res = lat.trace_independently(o, d, n_wall=n_wall, n_poly=n_poly, thickness_um=80.0)
    np.testing.assert_allclose(np.linalg.norm(res.direction, axis=1), 1.0, atol=1e-12)
    start = lat.phase(o[:, 0], [0.0])[:, 0]
    n_start = np.where(start == 1, n_wall, n_poly)
    n_end = np.where(res.extras["medium"] == 1, n_wall, n_poly)
    np.testing.assert_allclose(n_end * res.direction[:, 2], n_start * d[:, 2], atol=1e-12)
    assert res.events.mean() > 5


@pytest.mark.parametrize("name", list(lattices()))
def test_the_phase_a_ray_ends_in_is_the_lattices_phase_there(name):
    lat = lattices()[name]
    beam = square_beam(400, 150.0, seed=8)
    res = lat.trace_independently(beam.origins * 0.5, (0, 1, 0), n_wall=1.50, n_poly=1.49, thickness_um=47.3)
    back = res.position - 1e-6 * res.direction
    phase = np.array([lat.phase([p[0]], [p[1]])[0, 0] for p in back])
    assert np.array_equal(phase, res.extras["medium"])
    assert 0 < res.extras["medium"].mean() < 1


@pytest.mark.parametrize("name", list(lattices()))
def test_the_voxel_source_of_a_lattice_is_its_voxelisation_chunk_by_chunk(name):
    lat = lattices()[name]
    src = lat.source(thickness_um=40.0, voxel_um=0.5, chunks=(32, 32, 8))
    whole = lat.voxelise(voxel_um=0.5, r0_um=-32.0, n_r=96, n_t=80, length=8)
    for i in (-2, -1, 0):
        for j in (0, 1, 2):
            got = src.get((i, j, 5))
            want = whole[(i + 2) * 32:(i + 3) * 32, j * 32:(j + 1) * 32]
            assert got.shape == want.shape and np.array_equal(got, want)
    assert 0.05 < whole.mean() < 0.6


def test_lattice_geometry_is_checked_and_named():
    with pytest.raises(ValueError, match="wall_um"):
        honeycomb(10.0, 6.0)
    with pytest.raises(ValueError, match="packing"):
        tube_lattice(10.0, 5.0, 1.0, packing="triangular")
    with pytest.raises(ValueError, match="jitter"):
        honeycomb(10.0, 1.0, jitter=0.4)
    with pytest.raises(ValueError, match="r_outer_um"):
        tube_lattice(10.0, 11.0, 1.0)
    with pytest.raises(ValueError, match="direction"):
        honeycomb(10.0, 1.0).trace_independently(np.zeros((1, 3)), (0, -1, 0), n_wall=1.5, n_poly=1.49, thickness_um=10)


def test_unbiased_normal_noise_of_a_tenth_of_a_degree_barely_moves_the_results():
    """The floor of any comparison of a method with the exact trace: normals off by
    0.1° at random (far better than voxels give) move FWHM_R a few % and haze < 2 points."""
    lat = honeycomb(14.5, 2.0, jitter=0.15, seed=3)
    beam = square_beam(3000, 300.0, seed=1)
    a = lat.trace_independently(beam.origins * 0.5, (0, 1, 0), n_wall=1.50, n_poly=1.49, thickness_um=250.0)
    b = lat.trace_independently(beam.origins * 0.5, (0, 1, 0), n_wall=1.50, n_poly=1.49, thickness_um=250.0,
                  normal_noise_deg=0.1)
    again = lat.trace_independently(beam.origins * 0.5, (0, 1, 0), n_wall=1.50, n_poly=1.49, thickness_um=250.0,
                      normal_noise_deg=0.1)
    assert np.array_equal(b.direction, again.direction)
    assert not np.array_equal(a.direction, b.direction)
    assert abs(fwhm(b.theta_r, "lorentz-mle") / fwhm(a.theta_r, "lorentz-mle") - 1) < 0.05
    assert abs(haze(b.direction) - haze(a.direction)) < 0.02


def test_smoothed_ks_ignores_what_no_instrument_resolves():
    rng = np.random.default_rng(0)
    x = np.concatenate([np.zeros(500), rng.standard_cauchy(500)])
    y = np.concatenate([rng.normal(0, 0.02, 500), rng.standard_cauchy(500)])
    from scipy import stats

    assert stats.ks_2samp(x, y).statistic > 0.2  # the atom at 0 against a spread of 0.02°
    assert smoothed_ks(x, y) < 0.06
    assert smoothed_ks(x, x + 1.0) > 0.3


# ---------------------------------------------------------------- the voxel methods against them
def test_accurate_meets_the_targets_on_tubes_with_walls_of_6_voxels():
    """Apart, with walls thicker than its smoothing, `accurate` is within the targets of
    its accuracy benchmark: FWHM_R within 10 %, haze within 3 points, KS within 0.06
    (measured: +4 % / +1.1 and +0 % / +0.3, KS 0.02-0.03 at 0.5 µm)."""
    lat = tube_lattice(20.0, 8.0, 3.0, rotation_deg=3.0)
    for n_wall, n_poly in ((1.50, 1.49), (1.49, 1.50)):
        r = compare_with_exact(lat, settings_for("accurate"), voxel_um=0.5, thickness_um=150.0, n_wall=n_wall,
                               n_poly=n_poly, n_rays=2000)
        assert r["traced_voxel_um"] == 0.25
        assert abs(r["fwhm_r_error"]) < 0.10 and abs(r["haze_error_points"]) < 3.0 and r["ks"] < 0.06, r


@pytest.mark.parametrize("family", ["tubes", "honeycomb"])
def test_refining_the_voxels_brings_accurate_closer_to_exact_optics(family):
    """Walls of 4 voxels at 0.5 µm, touching tubes or a jittered honeycomb: on its own voxels
    `accurate` errs by 18-243 % in FWHM_R; on voxels half as large (its default) by 5-137 %
    (the same wood, the model being a function of position)."""
    lat = (tube_lattice(14.5, 7.25, 2.0, rotation_deg=8.0) if family == "tubes"
           else honeycomb(14.5, 2.0, jitter=0.15, seed=3))
    err = {1: 0.0, 2: 0.0}
    for n_wall, n_poly in ((1.50, 1.49), (1.49, 1.50)):
        for refine in (1, 2):
            r = compare_with_exact(lat, settings_for("accurate", refine=refine), voxel_um=0.5,
                                   thickness_um=100.0, n_wall=n_wall, n_poly=n_poly, n_rays=1500)
            err[refine] += abs(r["fwhm_r_error"])
    assert err[2] < 0.6 * err[1]


@pytest.mark.parametrize("method, rays", [("paper", 150), ("fast", 1500), ("accurate", 1500)])
@pytest.mark.parametrize("family", ["tubes", "honeycomb"])
def test_every_method_is_compared_with_exact_optics_of_many_thin_walls(method, rays, family):
    """Every method, each reference family, both signs of ΔRI, at small size.  None meets the
    accuracy targets on walls of 4 voxels: they are measured and published by
    `make bench-accuracy` (results/accuracy.md).  What holds here: every ray crosses about
    as many interfaces as in exact optics (the paper's 2-voxel steps skip some oblique
    crossings: 12 % fewer on the tubes), and the results are off by at most a bound that
    catches a broken traversal or normal (walls passed unseen, normals at random: several
    hundred % and tens of haze points)."""
    lat = (tube_lattice(14.5, 7.25, 2.0, rotation_deg=8.0) if family == "tubes"
           else honeycomb(14.5, 2.0, jitter=0.15, seed=3))
    for n_wall, n_poly in ((1.50, 1.49), (1.49, 1.50)):
        r = compare_with_exact(lat, settings_for(method), voxel_um=0.5, thickness_um=100.0, n_wall=n_wall,
                               n_poly=n_poly, n_rays=rays)
        assert r["transmitted"] == rays
        assert abs(r["interfaces"] / r["interfaces_exact"] - 1) < (0.2 if method == "paper" else 0.1), r
        if method == "accurate":
            assert abs(r["fwhm_r_error"]) < 1.6 and abs(r["haze_error_points"]) < 6.0, r
        else:
            assert abs(r["fwhm_r_error"]) < 6.0 and abs(r["haze_error_points"]) < 40.0, r
