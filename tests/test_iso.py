"""Method iso (pipeline/optics/iso.py, _iso_march.py): a grey-level volume traced on the iso-surface
of its trilinear interpolant, against analytic surfaces: a plane at a known angle (trilinear
interpolation holds a linear field exactly), a thin wall crossed twice inside one cell, a sphere's
level set; and its one-line errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.optics.interface import TRANSMITTED, TRAPPED
from pipeline.optics.iso import IsoVolume, otsu_threshold
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
    assert main(["trace", "--volume", str(path), "--method", "iso", "--delta-ri", "0.01", "--beam-um", "50"]) == 2
    assert "`beam_um` must fit the volume" in capsys.readouterr().err
