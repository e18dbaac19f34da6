"""Method iso (pipeline/optics/iso.py, _iso_march.py): a grey-level volume traced on the iso-surface
of its trilinear interpolant, against analytic surfaces: a plane at a known angle (trilinear
interpolation holds a linear field exactly), a thin wall crossed twice inside one cell, a sphere's
level set; and its one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.optics.interface import TRANSMITTED, TRAPPED
from pipeline.optics.iso import SMOOTH_UM, IsoVolume, otsu_threshold
from pipeline.params import ParameterError


def _snell(d, n, n1, n2):
    """The refracted unit direction (an independent statement of Snell's law), n facing the ray."""
    d = np.asarray(d, float) / np.linalg.norm(d)
    n = np.asarray(n, float) / np.linalg.norm(n)
    if n @ d > 0:
        n = -n
    cos_i = -(n @ d)
    eta = n1 / n2
    return eta * d + (eta * cos_i - math.sqrt(1.0 - eta * eta * (1.0 - cos_i * cos_i))) * n


def _plane_volume(tan_r: float, level: float, shape=(24, 24, 24), h: float = 1.0):
    """Grey level T + tan_r·R at every voxel centre: the iso-surface at ``level`` is the plane
    T + tan_r·R = level, exactly, between the outermost centres."""
    i, j, k = np.meshgrid(*[np.arange(s) for s in shape], indexing="ij")
    r, t = (i + 0.5) * h, (j + 0.5) * h
    return IsoVolume(t + tan_r * r + 0.0 * k, voxel_um=h, iso=level)


@pytest.mark.parametrize("n_poly, n_wall", [(1.49, 1.50), (1.50, 1.49), (1.0, 1.5)])
def test_a_plane_at_a_known_angle_refracts_by_snells_law(n_poly, n_wall):
    tan_r, level = math.tan(math.radians(25.0)), 15.0
    vol = _plane_volume(tan_r, level)
    start = np.array([[9.3, 0.0, 7.1]])
    d = np.array([[0.05, 1.0, -0.02]])
    d /= np.linalg.norm(d)
    out = vol.march_walls(start, d, n_wall=n_wall, n_poly=n_poly, max_events=10)
    assert out["status"][0] == TRANSMITTED and out["events"][0] == 1 and out["medium"][0] == 1
    want = _snell(d[0], (tan_r, 1.0, 0.0), n_poly, n_wall)
    assert np.abs(out["direction"][0] - want).max() < 1e-12
    # Where it crossed: on the plane; then straight to the exit face T = 24 µm.
    s = (level - start[0, 1] - tan_r * start[0, 0]) / (d[0, 1] + tan_r * d[0, 0])
    hit = start[0] + s * d[0]
    assert abs(hit[1] + tan_r * hit[0] - level) < 1e-9
    exit_point = hit + (24.0 - hit[1]) / want[1] * want
    assert np.abs(out["position"][0] - exit_point).max() < 1e-9
    assert out["path"][0] == pytest.approx(s + np.linalg.norm(exit_point - hit), abs=1e-9)


def test_two_crossings_inside_one_cell_are_both_found():
    """Along the cell's diagonal the field is 3t(1 - t): above 0.5 between t = (1 ± 1/√3)/2, below it
    at both of the cell's corners, where a sampler of the corners sees nothing."""
    g = np.zeros((6, 3, 6))
    g[:2, :2, :2] = 1.0
    g[0, 0, 0] = g[1, 1, 1] = 0.0
    vol = IsoVolume(g, voxel_um=1.0, iso=0.5)
    d = np.array([[1.0, 1.0, 1.0]]) / math.sqrt(3.0)
    start = np.zeros((1, 3))
    out = vol.march_walls(start, d, n_wall=1.5, n_poly=1.5, max_events=10)
    assert out["status"][0] == TRANSMITTED and out["events"][0] == 2 and out["medium"][0] == 0
    assert np.array_equal(out["direction"][0], d[0])
    first = vol.march_walls(start, d, n_wall=1.5, n_poly=1.5, max_events=1)
    assert first["status"][0] == TRAPPED
    t = (1.0 - 1.0 / math.sqrt(3.0)) / 2.0  # the first root, in cell units along the diagonal from (0.5, 0.5, 0.5)
    assert np.abs(first["position"][0] - (0.5 + t)).max() < 1e-9


def test_a_spheres_level_set_is_met_on_the_interpolant_with_its_gradient_as_normal():
    shape, h = (30, 30, 30), 0.5
    i, j, k = np.meshgrid(*[np.arange(s) for s in shape], indexing="ij")
    c = np.array([7.6, 8.1, 7.4])
    dist = np.sqrt(((i + 0.5) * h - c[0]) ** 2 + ((j + 0.5) * h - c[1]) ** 2 + ((k + 0.5) * h - c[2]) ** 2)
    vol = IsoVolume(5.0 - dist, voxel_um=h, iso=0.0)  # wall inside a sphere of radius 5 µm
    rng = np.random.default_rng(3)
    starts = np.column_stack([c[0] + rng.uniform(-2, 2, 40), np.zeros(40), c[2] + rng.uniform(-2, 2, 40)])
    dirs = np.column_stack([rng.uniform(-0.1, 0.1, 40), np.ones(40), rng.uniform(-0.1, 0.1, 40)])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    out = vol.march_walls(starts, dirs, n_wall=1.55, n_poly=1.49, max_events=1)
    assert (out["status"] == TRAPPED).all() and (out["medium"] == 1).all()
    p = out["position"]
    assert np.abs(vol.field(p)).max() < 1e-9  # on the interpolant's level set
    step = 1e-6
    for q in range(len(p)):
        grad = np.array([(vol.field(p[q] + e)[0] - vol.field(p[q] - e)[0]) / (2 * step) for e in np.eye(3) * step])
        want = _snell(dirs[q], grad, 1.49, 1.55)
        assert np.abs(out["direction"][q] - want).max() < 1e-6


def test_otsu_splits_two_grey_levels_and_is_stated_in_the_output(tmp_path, capsys):
    rng = np.random.default_rng(1)
    g = np.where(rng.random((40, 30, 40)) < 0.3, 200.0, 40.0) + rng.normal(0, 5, (40, 30, 40))
    assert 60 < otsu_threshold(g) < 180
    path = tmp_path / "grey.npy"
    np.save(path, g.astype(np.float32))
    assert main(["trace", "--volume", str(path), "--method", "iso", "--voxel-um", "0.5", "--delta-ri", "0.01",
                 "--beam-um", "10", "--rays", "60"]) == 0
    line = capsys.readouterr().out
    assert "method iso at grey level" in line and "(Otsu's threshold)" in line


@pytest.mark.parametrize("make, message", [
    (lambda: IsoVolume(np.full((4, 4, 4), np.nan), voxel_um=1.0, iso=0.5), "`volume` must hold finite grey levels"),
    (lambda: IsoVolume(np.arange(64.0).reshape(4, 4, 4), voxel_um=1.0, iso=99.0),
     "`iso` must lie in the volume's grey levels [0, 63)"),
    (lambda: IsoVolume(np.ones((4, 4, 4)), voxel_um=1.0), "`volume` holds one grey level"),
    (lambda: IsoVolume(np.ones((4, 4)), voxel_um=1.0), "`volume` must be a 3-D array"),
])
def test_bad_grey_volumes_are_refused_in_one_line(make, message):
    with pytest.raises(ParameterError) as err:
        make()
    assert message in str(err.value) and "\n" not in str(err.value)


def test_iso_applies_to_grey_volumes_only(tmp_path, capsys):
    path = tmp_path / "grey.npy"
    np.save(path, np.arange(8000.0).reshape(20, 20, 20))
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.1", "--method", "iso", "--delta-ri", "0.01"]) == 2
    assert "give --volume" in capsys.readouterr().err
    assert main(["trace", "--volume", str(path), "--iso", "3", "--delta-ri", "0.01", "--beam-um", "5"]) == 2
    assert "`--iso` applies to --method iso" in capsys.readouterr().err
    assert main(["trace", "--volume", str(path), "--smooth-um", "0.5", "--delta-ri", "0.01", "--beam-um", "5"]) == 2
    assert "`--smooth-um` applies to --method iso, got --method accurate" in capsys.readouterr().err
    assert main(["trace", "--volume", str(path), "--method", "iso", "--delta-ri", "0.01", "--beam-um", "50"]) == 2
    assert "`beam_um` must fit the volume" in capsys.readouterr().err


def test_a_grey_scan_holds_each_voxels_wall_fraction_whatever_its_slabs(monkeypatch):
    """A voxel's grey level is the wall fraction of its supersample³ fine voxels of the same wood (the
    generator's own voxels), the same when generated in other slabs; the noise is per voxel."""
    from pipeline.microstructure import grey as grey_mod
    from pipeline.microstructure.model import generate_block
    from pipeline.params import Grid, build_params

    params = build_params("birch")
    grid = Grid((16, 12, 10), 0.5, (-4.0, 0.0, -2.5))
    scan = grey_mod.grey_volume(params, grid, seed=2, supersample=3)
    fine = generate_block(params, Grid((48, 36, 30), 0.5 / 3, grid.origin_um), (0, 0, 0), (48, 36, 30), seed=2)
    assert np.array_equal(scan, fine.reshape(16, 3, 12, 3, 10, 3).mean(axis=(1, 3, 5)).astype(np.float32))
    assert scan.min() == 0 and scan.max() == 1 and len(np.unique(scan)) > 10  # lumens, walls and partial volumes
    noisy = grey_mod.grey_volume(params, grid, seed=2, supersample=3, noise=0.05, noise_seed=7)
    monkeypatch.setattr(grey_mod, "SLAB_FINE_VOXELS", 48 * 36 * 27)  # one coarse L layer a slab
    assert np.array_equal(noisy, grey_mod.grey_volume(params, grid, seed=2, supersample=3, noise=0.05, noise_seed=7))
    assert 0.04 < float(np.std(noisy - scan)) < 0.06
    with pytest.raises(ParameterError, match="`supersample` must be an integer in"):
        grey_mod.grey_volume(params, grid, seed=2, supersample=0)


def test_a_generated_grey_scan_is_traced_end_to_end(tmp_path, capsys):
    scan = tmp_path / "scan.npy"
    assert main(["generate", "--preset", "birch", "--size-um", "30,20,30", "--voxel-um", "0.5", "--grey",
                 "--supersample", "2", "--noise", "0.02", "--out", str(scan)]) == 0
    assert "grey-level scan, shape (60, 40, 60)" in capsys.readouterr().out
    grey = np.load(scan)
    assert grey.dtype == np.float32 and grey.shape == (60, 40, 60) and 0.2 < float(grey.mean()) < 0.8
    assert main(["trace", "--volume", str(scan), "--method", "iso", "--iso", "0.5", "--voxel-um", "0.5",
                 "--delta-ri", "0.01", "--beam-um", "10", "--rays", "40", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["iso"] == 0.5 and out["iso_from"] == "given" and out["n_rays"] == 40
    assert out["smooth_um"] == SMOOTH_UM == 0.5  # the pre-filter unless told
    assert main(["trace", "--volume", str(scan), "--method", "iso", "--iso", "0.5", "--voxel-um", "0.5",
                 "--delta-ri", "0.01", "--beam-um", "10", "--rays", "40", "--smooth-um", "0"]) == 0
    line = capsys.readouterr().out
    assert "method iso at grey level 0.5," in line and "smoothed" not in line  # 0: the raw interpolant
    assert main(["generate", "--preset", "birch", "--size-um", "30,20,30", "--noise", "0.1",
                 "--out", str(tmp_path / "v.zarr")]) == 2
    assert "`--noise` applies to --grey" in capsys.readouterr().err
    assert main(["generate", "--preset", "birch", "--size-um", "30,20,30", "--grey", "--out", str(tmp_path / "g.zarr")]) == 2
    assert "must be a .npy file" in capsys.readouterr().err and not (tmp_path / "g.zarr").exists()


def test_a_grey_volume_goes_through_the_same_faces_as_every_medium():
    """Through `trace`: index-matched, a beam from air leaves into air along its own direction; a ray
    entering beside the volume leaves through a side; `exact` is refused on it by name."""
    import dataclasses

    from pipeline.optics.interface import SIDE
    from pipeline.optics.rays import Beam, square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    rng = np.random.default_rng(4)
    vol = IsoVolume(rng.random((40, 20, 40)), voxel_um=0.5, iso=0.5)
    s = dataclasses.replace(settings_for("iso"), exit="air")
    air = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
    res = trace(vol, square_beam(30, 4.0, (10.0, 10.0), seed=3, direction=air), Optics(1.5, 1.5, n_outside=1.0), s)
    assert np.all(res.status == TRANSMITTED) and res.events.sum() > 30
    np.testing.assert_allclose(res.exit_direction, np.broadcast_to(air, (30, 3)), atol=1e-12)
    outside = trace(vol, Beam(np.array([[-3.0, 0.0, 5.0]]), np.array([[0.0, 1.0, 0.0]]), np.array([0])),
                    Optics(1.5, 1.49), settings_for("iso"))
    assert outside.status[0] == SIDE
    with pytest.raises(ParameterError, match="`method` 'exact' traces surfaces, but this medium offers fields: use iso"):
        trace(vol, square_beam(3, 4.0, (10.0, 10.0), seed=3), Optics(1.5, 1.49), settings_for("exact"))


def test_a_ray_that_starts_on_a_cell_face_does_not_cross_again_there():
    """A clean scan's wall fractions are multiples of 1/64, so the threshold ½ lies exactly on many
    voxel centres, that is on faces of the cells the march walks. There two cells' cubics can round
    F to opposite sides: a ray of this birch scan (found in bench_iso) met one, refracted, and its
    restart in the neighbouring cell counted the same face again, back and forth, 2000 times
    (trapped). Until a ray has moved, its phase is the one it left the crossing with."""
    from pipeline.microstructure.grey import grey_volume
    from pipeline.optics.rays import Beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace
    from pipeline.params import Grid, build_params

    # Voxels R 140-199, L 110-149 of a 160 µm birch scan centred on the wood's origin.
    scan = grey_volume(build_params("birch"), Grid((60, 500, 40), 0.5, (-10.0, 0.0, -25.0)), seed=1, supersample=4)
    ray = Beam(np.array([[19.67782767, 0.0, 10.4565875]]), np.array([[0.0, 1.0, 0.0]]), np.array([88]))
    r = trace(IsoVolume(scan, voxel_um=0.5, iso=0.5), ray, Optics.of_delta(1.49, 0.01, seed=1), settings_for("iso"))
    assert r.status[0] == TRANSMITTED and r.events[0] < 100


def test_a_volume_read_in_blocks_as_rays_reach_them_gives_the_same_rays_bit_for_bit(tmp_path, monkeypatch):
    """Rays stopped at a block's edge and resumed once it is read go on exactly as through the whole
    volume in one block: the same rays whatever the block size and however few blocks the pool
    holds; a narrow beam through a Zarr array reads only the blocks around its path, and each of the
    store's chunks once, though blocks straddle them."""
    import zarr

    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    rng = np.random.default_rng(11)
    # Smooth random walls (a sum of a few plane waves): many crossings, oblique normals.
    i, j, k = np.meshgrid(*[np.arange(n) for n in (48, 40, 48)], indexing="ij")
    grey = sum(np.cos(0.3 * (a * i + b * j + c * k) + p) for a, b, c, p in rng.normal(0, 1, (6, 4)))
    beam = square_beam(80, 6.0, (12.0, 12.0), seed=2, direction=(0.2, 1.0, -0.1))
    optics = Optics(1.5, 1.49)
    whole = trace(IsoVolume(grey, voxel_um=0.5, iso=0.1, block=64), beam, optics, settings_for("iso"))
    assert whole.events.sum() > 400
    store = zarr.create_array(tmp_path / "grey.zarr", shape=grey.shape, chunks=(8, 8, 8), dtype="f8")
    store[...] = grey
    store_reads = []
    getitem = type(store).__getitem__

    def counted(self, key):
        store_reads.append(key)
        return getitem(self, key)

    monkeypatch.setattr(type(store), "__getitem__", counted)
    from pipeline.optics import iso
    monkeypatch.setattr(iso, "SAMPLE_VOXELS", grey.size // 4)  # the threshold's sample: every 4th slice, not chunks
    for block, memory in ((5, 10 ** 9), (5, 4 * 6 ** 3 * 8), (8, 10 ** 9)):
        vol = IsoVolume(zarr.open_array(tmp_path / "grey.zarr", mode="r"), voxel_um=0.5, iso=0.1, block=block,
                        memory_bytes=memory)
        part = trace(vol, beam, optics, settings_for("iso"))
        for name in ("position", "exit_direction", "status", "events", "path"):
            np.testing.assert_array_equal(getattr(part, name), getattr(whole, name), err_msg=f"{name}, block {block}")
        every = math.prod(-(-n // block) for n in grey.shape)
        if memory > 10 ** 6:
            assert vol.blocks_read < every / 2, (vol.blocks_read, every)
        # Blocks (and their one-voxel halo) straddle the store's 8³ chunks: each chunk read once.
        reads = [key for key in store_reads if isinstance(key, tuple) and all(k.step is None for k in key)]
        starts = [tuple(k.start for k in key) for key in reads]
        assert all(a % 8 == 0 for st in starts for a in st) and len(set(starts)) == len(starts) > 0, starts
        assert len(reads) < vol.chunk_reader.whole_reads  # what reading each block at once would decompress
        store_reads.clear()


def test_a_non_finite_grey_level_is_named_when_its_block_is_read(monkeypatch):
    """A large volume's threshold comes from every k-th L slice; a bad voxel elsewhere is found, and
    named, when a ray reaches its block."""
    from pipeline.optics import iso
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    grey = np.random.default_rng(1).random((40, 20, 40))
    grey[30, 5, 35] = np.inf
    monkeypatch.setattr(iso, "SAMPLE_VOXELS", grey.size // 4)
    vol = IsoVolume(grey, voxel_um=1.0, block=8)
    assert vol.iso_sample == "every 4th L slice" and 0.3 < vol.iso < 0.7
    with pytest.raises(ParameterError) as err:
        trace(vol, square_beam(5, 4.0, (30.0, 35.0), seed=1), Optics(1.5, 1.49), settings_for("iso"))
    assert str(err.value) == "`volume` must hold finite grey levels, got 1 that are not (the first at voxel (30, 5, 35))"


@pytest.mark.parametrize("blur, noise", [(0.0, 0.0), (0.3, 0.02)])
def test_a_lazy_grey_scan_is_the_whole_scan_part_by_part(blur, noise):
    """Each part of a LazyGreyScan, generated when read (a blurred one with its kernel's halo, its
    noise keyed by the voxel's index in the whole scan), is bit for bit that part of grey_volume's
    scan, and only the tiles a read touches are generated."""
    from pipeline.microstructure import grey
    from pipeline.params import Grid, build_params

    p, g = build_params("birch"), Grid((70, 40, 66), 0.5, (-10.0, 0.0, -12.0))
    whole = grey.grey_volume(p, g, seed=3, supersample=2, blur_um=blur, noise=noise, noise_seed=5)
    lazy = grey.LazyGreyScan(p, g, seed=3, supersample=2, blur_um=blur, noise=noise, noise_seed=5)
    np.testing.assert_array_equal(lazy[5:30, 3:20, 40:66], whole[5:30, 3:20, 40:66])
    t = grey.TILE
    assert lazy.tiles_generated == math.prod(len(range(a // t, -(-b // t))) for a, b in ((5, 30), (3, 20), (40, 66)))
    np.testing.assert_array_equal(lazy[:, :, ::3], whole[:, :, ::3])


def test_a_smoothed_volume_is_traced_block_by_block_as_if_smoothed_whole():
    """--smooth-um: each block is smoothed with the halo its kernel reaches, so the rays are those of
    the whole volume smoothed at once by scipy, whatever the blocks; smoothing noise away brings the
    normals back towards the clean surface's."""
    from scipy.ndimage import gaussian_filter

    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    rng = np.random.default_rng(5)
    i, j, k = np.meshgrid(*[np.arange(n) for n in (40, 36, 40)], indexing="ij")
    clean = (np.cos(0.35 * i + 0.2 * j) + np.cos(0.3 * k - 0.25 * j)).astype(np.float32)
    noisy = (clean + rng.normal(0, 0.3, clean.shape)).astype(np.float32)
    beam = square_beam(60, 6.0, (10.0, 10.0), seed=2)
    optics, s = Optics(1.5, 1.49), settings_for("iso")
    whole = trace(IsoVolume(gaussian_filter(noisy, sigma=1.5, mode="nearest"), voxel_um=0.5, iso=0.0), beam,
                  optics, s)
    for block in (64, 5):
        part = trace(IsoVolume(noisy, voxel_um=0.5, iso=0.0, smooth_um=0.75, block=block), beam, optics, s)
        np.testing.assert_array_equal(part.exit_direction, whole.exit_direction, err_msg=f"block {block}")
    raw = trace(IsoVolume(noisy, voxel_um=0.5, iso=0.0), beam, optics, s)
    ref = trace(IsoVolume(clean, voxel_um=0.5, iso=0.0), beam, optics, s)
    assert raw.events.sum() > 1.3 * ref.events.sum()  # noise adds crossings the clean surface does not have
    assert abs(whole.events.sum() - ref.events.sum()) < abs(raw.events.sum() - ref.events.sum())


@pytest.mark.parametrize("n_wall, n_poly", [(1.55, 1.5), (1.5, 1.55)])
def test_a_smooth_field_of_a_tube_lattice_refracts_ray_by_ray_as_the_exact_lattice(n_wall, n_poly):
    """The field w/2 − |d − r_mid| (d: distance to the nearest tube axis) is the tube lattice's walls as a
    level set; traced with iso at voxels h, every ray meets the interfaces of the lattice's independent
    exact tracer (ray-circle roots) for >= 97 % of the rays, and the exit directions part from the exact
    ones by what the trilinear gradient's first-order error allows: less than 0.02° (median) at h = 0.05
    µm, about half of it at h = 0.1 µm, so ray by ray the two agree as the field is resolved."""
    from pipeline.optics.lattice import tube_lattice
    from pipeline.optics.rays import Beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    p, ro, w, thick = 14.5, 6.0, 2.0, 30.0
    lat = tube_lattice(p, ro, w)
    rng = np.random.default_rng(3)
    n = 300
    org = np.zeros((n, 3))
    org[:, 0], org[:, 2] = rng.uniform(-20, 20, n), 0.2
    d0 = np.array([0.05, 1.0, 0.0]) / np.linalg.norm([0.05, 1.0, 0.0])
    ex = lat.trace_independently(org, np.broadcast_to(d0, (n, 3)), n_wall=n_wall, n_poly=n_poly, thickness_um=thick)
    medians = []
    for h in (0.1, 0.05):
        r0, nr, nt = -30.0, int(60 / h), int(thick / h)
        rr, tt = np.meshgrid(r0 + (np.arange(nr) + 0.5) * h, (np.arange(nt) + 0.5) * h, indexing="ij")
        d = np.hypot(rr - p * np.round(rr / p), tt - p * np.round(tt / p))
        field = np.broadcast_to((w / 2 - np.abs(d - (ro - w / 2)))[:, :, None], (nr, nt, 4))
        res = trace(IsoVolume(field, voxel_um=h, iso=0.0), Beam(org - np.array([r0, 0.0, 0.0]), d0, np.arange(n)),
                    Optics(n_wall, n_poly), settings_for("iso"))
        assert np.mean(res.events == ex.events) >= 0.97 and ex.events.mean() > 5
        medians.append(np.median(np.degrees(np.arccos(np.clip(np.sum(ex.direction * res.direction, axis=1), -1, 1)))))
    assert medians[1] < 0.02 and medians[1] < 0.7 * medians[0], medians


def test_a_lattices_grey_section_holds_each_voxels_wall_fraction():
    """Over whole periods the mean wall fraction is the tubes' area fraction π(ro² − ri²)/p²; a voxel far
    from any wall is 0, one inside a thick wall 1."""
    from pipeline.optics.lattice import tube_lattice

    p, ro, w, h = 14.5, 6.0, 2.0, 0.5
    sec = tube_lattice(p, ro, w).grey_section(voxel_um=h, r0_um=0.0, n_r=int(4 * p / h), n_t=int(4 * p / h),
                                              supersample=8)
    assert sec.shape == (116, 116) and sec.dtype == np.float32
    assert abs(sec.mean() - math.pi * (ro ** 2 - (ro - w) ** 2) / p ** 2) < 2e-3
    assert sec[0, 0] == 0.0  # the lumen at the site (0, 0)
    assert sec[int(5.0 / h), 0] == 1.0  # R 5-5.5 µm, T 0-0.5 µm: inside the wall (4 < r < 6)


def test_a_partial_volume_scan_of_a_flat_wall_is_faceted_and_a_one_voxel_prefilter_flattens_it():
    # results/accuracy.md, "Why `iso`'s FWHM_L comes out high": the refraction of each ray gives the
    # normal it was refracted by.  A wall along the grid's planes scans to a field constant along its
    # plane: every normal is the wall's.  Turned 20° in R-T and tilted 5° towards L, the trilinear
    # iso-surface of the wall fractions has facets: normals several degrees off, also along L, and
    # the same at half the voxel (the facets scale with it); a Gaussian pre-filter of one voxel
    # leaves a fraction of that.
    from pipeline.optics.validation import iso_wall_normals

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))

    aligned = iso_wall_normals(0.0, 0.0, voxel_um=0.5, rays=200)
    assert aligned["angle_deg"].size == 200 and aligned["angle_deg"].max() < 1e-6
    raw = iso_wall_normals(5.0, 20.0, voxel_um=0.5, rays=400)
    half = iso_wall_normals(5.0, 20.0, voxel_um=0.25, rays=400)
    smooth = iso_wall_normals(5.0, 20.0, voxel_um=0.5, smooth_um=0.5, rays=400)
    assert raw["angle_deg"].size == half["angle_deg"].size == smooth["angle_deg"].size == 400
    assert rms(raw["angle_deg"]) > 4.0 and rms(raw["along_l_deg"]) > 1.0
    assert rms(half["angle_deg"]) == pytest.approx(rms(raw["angle_deg"]), rel=1e-6)
    assert rms(smooth["angle_deg"]) < 0.3 * rms(raw["angle_deg"])
    assert rms(smooth["along_l_deg"]) < 0.3 * rms(raw["along_l_deg"])
