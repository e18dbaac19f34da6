"""Design maps: the ΔRI window that keeps haze below a limit, and `twray design`."""

import json

import numpy as np
import pytest
import xarray as xr

from pipeline.cli import main
from pipeline.design import edge_text, reading, window

T = np.array([0.5, 1.0, 2.0])
D = np.array([-0.03, -0.01, -0.002, 0.002, 0.01, 0.03])


def linear_map(slope_neg=20.0, slope_pos=10.0):
    """haze = slope · |ΔRI| · thickness [mm] (a different slope each side), interval ±20 %."""
    slope = np.where(D < 0, slope_neg, slope_pos)
    haze = np.minimum(T[:, None] * slope[None, :] * np.abs(D)[None, :], 1.0)
    ds = xr.Dataset({"haze": (("thickness", "delta_ri"), haze),
                     "haze_ci_lower": (("thickness", "delta_ri"), 0.8 * haze),
                     "haze_ci_upper": (("thickness", "delta_ri"), np.minimum(1.2 * haze, 1.0)),
                     "FWHM_R": (("thickness", "delta_ri"), 100 * haze),
                     "FWHM_R_ci_lower": (("thickness", "delta_ri"), 90 * haze),
                     "FWHM_R_ci_upper": (("thickness", "delta_ri"), 110 * haze)},
                    coords={"thickness": T, "delta_ri": D},
                    attrs={"title": "Design map: test", "trace_settings": json.dumps({"method": "exact"}),
                           "realisations": 3, "rays": 200, "scale": "paper"})
    return ds


def test_the_window_is_where_interpolated_haze_crosses_the_limit_and_its_interval_the_bounds_crossings():
    w = window(linear_map(), 1.0, 0.1)
    assert w["positive"].value == pytest.approx(0.1 / 10.0) and w["negative"].value == pytest.approx(0.1 / 20.0)
    assert w["positive"].lo == pytest.approx(0.01 / 1.2) and w["positive"].hi == pytest.approx(0.01 / 0.8)
    # Between thicknesses haze is interpolated linearly: at 1.5 mm, halfway between 1 and 2 mm.
    assert window(linear_map(), 1.5, 0.1)["positive"].value == pytest.approx(0.1 / 15.0)
    # Below the first ΔRI of the map the line from ΔRI = 0 (haze 0 exactly) is used.
    near = window(linear_map(), 0.5, 0.005)["positive"]
    assert near.value == pytest.approx(0.005 / 5.0) and near.below and near.traced_min == 0.002
    # ... and that line was not traced: no interval, marked as extrapolated wherever it is shown.
    assert np.isnan(near.lo) and np.isnan(near.hi)
    assert edge_text(near, "+") == ("+0.001 (extrapolated: below the smallest traced |ΔRI|, 0.002, on the line "
                                    "from ΔRI = 0; no interval)") and edge_text(near, "+", True) == "+0.001 †"
    far = window(linear_map(), 0.5, 0.9)["positive"]
    assert far.beyond and far.value == 0.03  # 0.5 · 10 · 0.03 = 0.15 < 0.9: the map's edge


@pytest.mark.parametrize("argv, needle", [
    (["--thickness-mm", "3", "--haze-max", "0.2"], "`thickness_mm` must lie within the design map's 0.5-2 mm"),
    (["--thickness-mm", "1", "--haze-max", "20"], "`haze_max` must be a fraction in (0, 1), got haze_max=20"),
    (["--thickness-mm", "thick", "--haze-max", "0.2"], "`thickness_mm` must be a number"),
])
def test_bad_design_questions_are_one_line(tmp_path, argv, needle, capsys):
    linear_map().to_zarr(tmp_path / "m.zarr", consolidated=False)
    assert main(["design", "--map", str(tmp_path / "m.zarr"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and needle in err


def test_twray_design_prints_the_window_with_its_intervals(tmp_path, capsys):
    linear_map().to_zarr(tmp_path / "m.zarr", consolidated=False)
    assert main(["design", "--map", str(tmp_path / "m.zarr"), "--thickness-mm", "1", "--haze-max", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "haze <= 10 % at 1 mm for ΔRI from -0.005 [-0.0062, -0.0042] to +0.01 [+0.0083, +0.012]" in out
    assert "3 woods × 200 rays per cell, method exact" in out
    assert main(["design", "--results", str(tmp_path), "--thickness-mm", "1", "--haze-max", "0.1"]) == 2
    assert "run `make design`" in capsys.readouterr().err


def test_a_map_read_forwards_says_how_it_knows_each_value():
    ds = linear_map()
    r = reading(ds, 1.0, 0.01)  # a traced cell: its own value and interval
    assert r.how == "traced" and r.haze == pytest.approx((0.1, 0.08, 0.12)) and r.fwhm_r[0] == pytest.approx(10.0)
    r = reading(ds, 1.5, -0.006)  # between cells: linear in thickness, then in ΔRI, bounds alike
    assert r.how == "interpolated" and r.haze == pytest.approx((0.18, 0.144, 0.216))
    r = reading(ds, 1.0, 0.001)  # below the smallest traced |ΔRI|: on the line from 0, no interval
    assert r.how == "extrapolated" and r.haze[0] == pytest.approx(0.01) and np.isnan(r.haze[1:]).all()
    assert reading(ds, 2.0, 0.0).haze == (0.0, 0.0, 0.0)


def test_twray_design_answers_forwards_inside_and_in_air(tmp_path, capsys):
    (tmp_path / "design").mkdir()
    linear_map().to_zarr(tmp_path / "design" / "birch.zarr", consolidated=False)
    linear_map(slope_pos=20.0).assign_attrs(title="Design map: air").to_zarr(tmp_path / "design" / "birch-air.zarr",
                                                                            consolidated=False)
    assert main(["design", "--results", str(tmp_path), "--thickness-mm", "1", "--delta-ri", "0.01"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == ("Design map: test: haze 10 % [8, 12], FWHM_R (lorentz-mle) 10° [9, 11] at 1 mm, ΔRI +0.01 "
                      "(a traced cell)")
    assert out[1].startswith("Design map: air: haze 20 % [16, 24]")
    assert main(["design", "--results", str(tmp_path), "--thickness-mm", "1", "--delta-ri", "0.05"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "`delta_ri` must lie within the design map's -0.03 to 0.03" in err
    assert main(["design", "--results", str(tmp_path), "--thickness-mm", "1"]) == 2
    assert "`haze_max` or `delta_ri` must be given" in capsys.readouterr().err


def test_the_report_opens_with_every_traced_cell_of_both_maps_in_air_and_inside():
    from pipeline.design import glance_tables

    inside, air = linear_map(), linear_map(slope_pos=20.0)
    lines = glance_tables({"birch": inside, "birch-air": air})
    assert lines[0] == "**birch, haze [%]**, in air / inside"
    assert lines[2] == "| thickness [mm] \\ ΔRI | -0.03 | -0.01 | -0.002 | +0.002 | +0.01 | +0.03 |"
    # 1 mm: haze = slope · |ΔRI| (inside 10, in air 20 per unit ΔRI on the positive side)
    assert lines[5] == "| 1 | 60/60 | 20/20 | 4/4 | 4/2 | 20/10 | 60/30 |"
    fw = lines.index("**birch, FWHM_R (lorentz-mle) [°]**, in air / inside")
    assert lines[fw + 5] == "| 1 | 60/60 | 20/20 | 4/4 | 4/2 | 20/10 | 60/30 |"  # FWHM_R = 100 · haze


def test_table_values_keep_two_digits_and_never_go_to_powers_of_ten():
    from pipeline.design import two_digits

    assert [two_digits(x) for x in (0.123, 9.96, 12.5, 99.96, 105.3)] == ["0.12", "10", "12", "100", "105"]
