"""pipeline.geometry_stats on synthetic volumes whose answers are known."""

import math

import numpy as np
import pytest

from pipeline.geometry_stats import volume_statistics

V = 0.5  # µm


def square_lattice(pitch=20, wall=4, periods=(8, 8), nl=12):
    """Square lumens of side pitch - wall on a square lattice; the wall between lumens is ``wall``."""
    cell = np.ones((pitch, pitch), np.uint8)
    h = wall // 2
    cell[h:pitch - (wall - h), h:pitch - (wall - h)] = 0
    plane = np.tile(cell, periods)
    return np.repeat(plane[:, :, None], nl, axis=2)


def test_square_lattice_known_answers():
    vol = square_lattice()
    s = volume_statistics(vol, V)
    assert s["wall_fraction"] == pytest.approx(1 - (16 / 20) ** 2)
    # Lumens 16 x 16 voxels = 8 x 8 µm; all 64 of them are inside every slice.
    assert s["fibre_lumen_d_um_median"] == pytest.approx(2 * math.sqrt(64 / math.pi))
    assert s["fibre_lumen_d_um_q25"] == s["fibre_lumen_d_um_q75"]
    assert s["fibre_lumens_counted"] == 64 * 12
    # The wall between two lumens: 4 voxels = 2 µm along R and T.
    for key in ("double_wall_r_um_median", "double_wall_t_um_median", "double_wall_um_median",
                "double_wall_um_q25", "double_wall_um_q75"):
        assert s[key] == pytest.approx(2.0)
    # Along T lines through lumens: 2 changes per 10 µm; 16 of every 20 R rows pass lumens.
    assert s["interfaces_per_mm_t"] == pytest.approx(200.0 * 16 / 20)
    # Ridge of 4-voxel walls: 2 d - 1 = 3 voxels (even thickness: one voxel low); corners thicker.
    assert s["wall_ridge_um_q25"] == pytest.approx(1.5)
    # Walls parallel to L: n_L = 0 everywhere.
    assert s["normal_l_median"] == pytest.approx(0.0, abs=1e-6)
    assert s["normal_l_p99"] == pytest.approx(0.0, abs=1e-6)
    assert s["normal_l_share_gt_0.1"] == 0.0
    assert s["vessel_area_fraction"] == 0.0
    assert s["ray_slice_share"] == 0.0


def test_unequal_walls_along_r_and_t():
    plane = np.ones((120, 120), np.uint8)
    for i in range(0, 120, 20):  # walls 6 voxels along R, 2 along T
        for j in range(0, 120, 12):
            plane[i + 3:i + 17, j + 1:j + 11] = 0
    s = volume_statistics(np.repeat(plane[:, :, None], 4, axis=2), V)
    assert s["double_wall_r_um_median"] == pytest.approx(3.0)
    assert s["double_wall_t_um_median"] == pytest.approx(1.0)
    # Odd thicknesses are exact at the ridge: 1 voxel (T walls) is the lower quartile.
    assert s["wall_ridge_um_q25"] == pytest.approx(0.5)


@pytest.mark.parametrize("theta_deg", [0.0, 10.0, 30.0])
def test_tilted_wall_normal(theta_deg):
    """A slab whose faces tilt by theta from L towards R: |n_L| = sin(theta)."""
    n = 64
    r, _, l = np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij")
    th = math.radians(theta_deg)
    x = (r - n / 2) * math.cos(th) - (l - n / 2) * math.sin(th)
    vol = (np.abs(x) < 8).astype(np.uint8)
    s = volume_statistics(vol, V)
    assert s["normal_l_median"] == pytest.approx(math.sin(th), abs=0.03)
    assert s["wall_fraction"] == pytest.approx(16 / (n * (math.cos(th) if th < 0.8 else 1)), rel=0.1)


def test_vessel_and_ray_detection():
    vol = square_lattice(periods=(10, 10), nl=10)
    rr, tt = np.mgrid[:200, :200]
    rho2 = (rr - 100) ** 2 + (tt - 100) ** 2
    vessel = rho2 < 40 ** 2  # 40 µm across, in a wall ring 2 µm thick
    vol[rho2 < 44 ** 2, :] = 1
    vol[vessel, :] = 0
    # A ray-like lumen, 30 µm along R and 4 µm along T, in 4 of the 10 slices.
    vol[20:180, 150:170, 2:6] = 1
    vol[50:110, 156:164, 2:6] = 0
    s = volume_statistics(vol, V)
    assert s["vessel_area_fraction"] == pytest.approx(vessel.sum() / vessel.size, rel=0.01)
    wall_outside = vol.sum(axis=(0, 1)) / (vessel.size - vessel.sum())
    assert s["wall_fraction_outside_vessels"] == pytest.approx(wall_outside.mean(), rel=0.01)
    assert s["ray_slice_share"] == pytest.approx(0.4)
    assert s["ray_lumens_per_slice"] == pytest.approx(0.4)
    assert s["ray_lumen_t_um_median"] == pytest.approx(4.0)
    # The vessel and the ray lumen do not count as fibre lumens.
    assert s["fibre_lumen_d_um_median"] == pytest.approx(2 * math.sqrt(64 / math.pi))


def test_rejects_non_3d():
    with pytest.raises(ValueError):
        volume_statistics(np.zeros((4, 4)), V)


def test_speed_on_a_realistic_volume():
    import time
    rng = np.random.default_rng(1)
    vol = square_lattice(pitch=29, wall=4, periods=(10, 10), nl=200)
    vol[rng.random(vol.shape) < 0.01] ^= 1
    t0 = time.perf_counter()
    volume_statistics(vol, V)
    assert time.perf_counter() - t0 < 60.0


def test_geometry_section(tmp_path):
    import json

    from pipeline.report_geometry import geometry_section
    assert geometry_section(tmp_path) == ""

    def stat(vals):
        m = sum(vals) / len(vals)
        return {"values": vals, "mean": m, "ci95": [m - 0.01, m + 0.01], "n": len(vals)}
    doc = {"port": {"voxel_um": 0.5, "size_um": [150, 150, 100], "per_seed": [{}, {}],
                    "stats": {"wall_fraction": stat([0.30, 0.30]), "normal_l_median": stat([0.1, 0.1])}},
           "twray": {"voxel_um": 0.5, "seeds": [1, 2],
                     "stats": {"wall_fraction": stat([0.40, 0.40]), "normal_l_median": stat([0.105, 0.105])}}}
    (tmp_path / "geometry.json").write_text(json.dumps(doc))
    md = geometry_section(tmp_path)
    assert md.startswith("### Geometry against the source's generator")
    assert "| wall fraction [%] | 30.0 [29.0, 31.0] | 40.0 [39.0, 41.0] | 1.33 |" in md
    assert "1 difference is resolved" in md and "×1.33" in md
