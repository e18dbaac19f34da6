"""Studies over several parameters at once: a product grid of cells, each cached on its own."""

import json
import os

import numpy as np
import pytest
import xarray as xr

from pipeline.cli import main
from pipeline.params import ParameterError
from pipeline.study.plan import plan_study
from pipeline.study.spec import load_study

BASE = """\
title: grid
preset: birch
seed: 2
realisations: 2
rays: 300
beam_um: 120
thickness_mm: 0.4
delta_ri: 0.01
"""


def study(tmp_path, vary: str, name="grid.yaml"):
    path = tmp_path / name
    path.write_text(BASE + vary)
    return path


def args(path, tmp_path):
    return ["study", str(path), "--scale", "small", "--cache", str(tmp_path / "c"), "--results",
            str(tmp_path / "r"), "--workers", "1"]


def test_a_grid_has_a_dimension_per_parameter_and_each_cell_is_the_1d_study_of_its_value(tmp_path, capsys):
    grid = study(tmp_path, "vary: {thickness_mm: [0.3, 0.6], delta_ri: [0.02, -0.01, 0.005]}\n")
    st = load_study(grid, scale="small")
    assert st.shape == (2, 3) and len(st.scenes) == 6
    assert st.scenes[1].thickness_um == pytest.approx(30.0) and st.scenes[1].delta_ri == -0.01  # C order
    assert main(args(grid, tmp_path) + ["--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len([ln for ln in lines if " realisation " in ln]) == 12  # 6 cells x 2 woods, nothing cached
    assert "grid thickness=0.3, delta_ri=-0.01 realisation 1:" in "\n".join(lines)
    assert main(args(grid, tmp_path)) == 0
    ds = xr.open_zarr(tmp_path / "r" / "grid.zarr", consolidated=False)
    assert ds.FWHM_R.dims == ("thickness", "delta_ri")
    assert ds.theta_r.dims == ("thickness", "delta_ri", "realisation", "ray")
    assert list(ds.delta_ri.values) == [0.02, -0.01, 0.005] and ds.thickness.attrs["units"] == "mm"
    assert ds.thickness_traced.values.tolist() == [[0.03] * 3, [0.06] * 3]
    # Thicker is hazier, at every ΔRI: the grid is not a copy of one value.
    assert np.all(ds.FWHM_R.sel(thickness=0.6).values > ds.FWHM_R.sel(thickness=0.3).values)
    # The 1-D study of one row and of one column: the same numbers, bit for bit.
    row = study(tmp_path, "thickness_mm: 0.6\nvary: {parameter: delta_ri, values: [-0.01, 0.005]}\n", "row.yaml")
    col = study(tmp_path, "delta_ri: 0.02\nvary: {parameter: thickness_mm, values: [0.3, 0.6]}\n", "col.yaml")
    for path in (row, col):
        assert main(args(path, tmp_path)) == 0
    r = xr.open_zarr(tmp_path / "r" / "row.zarr", consolidated=False)
    c = xr.open_zarr(tmp_path / "r" / "col.zarr", consolidated=False)
    for name in ("theta_r", "theta_l", "FWHM_R", "haze_ci_upper", "FWHM_L_per_realisation"):
        np.testing.assert_array_equal(r[name].values, ds[name].sel(thickness=0.6, delta_ri=[-0.01, 0.005]).values)
        np.testing.assert_array_equal(c[name].values, ds[name].sel(delta_ri=0.02).values)


def test_extending_one_axis_traces_only_the_new_cells(tmp_path):
    grid = study(tmp_path, "realisations: 1\nvary: {thickness_mm: [0.3], delta_ri: [0.01, 0.02]}\n")
    assert main(args(grid, tmp_path)) == 0
    entries = {p: p.stat().st_mtime_ns for p in (tmp_path / "c").rglob("*") if p.is_file() and p.parent.name != "logs"}
    grid.write_text(BASE + "realisations: 1\nvary: {thickness_mm: [0.3, 0.5], delta_ri: [0.01, 0.02]}\n")
    plan = plan_study(load_study(grid, scale="small"), tmp_path / "c")
    assert [s.cached for s in plan.summaries] == [True, True, False, False]
    assert main(args(grid, tmp_path)) == 0
    for p, t in entries.items():
        assert p.stat().st_mtime_ns == t, p  # nothing recomputed or rewritten
    ds = xr.open_zarr(tmp_path / "r" / "grid.zarr", consolidated=False)
    assert ds.haze.shape == (2, 2) and np.all(np.isfinite(ds.haze.values))
    assert json.loads(ds.attrs["cache_keys"])[2]["value"] == "0.5, 0.01"


@pytest.mark.parametrize("vary, needle", [
    ("vary: {thickness_mm: [], delta_ri: [0.01]}", "line 9: `vary.thickness_mm` must be a non-empty list, got []"),
    ("vary: {thickness_mm: [0.5], delta_ri: [0.01, 0.01]}", "line 9: `vary.delta_ri` must not repeat a value"),
    ("vary: {thickness_mm: [0.5], colour: [1, 2]}", "line 9: unknown parameter `vary.colour`"),
    ("vary: {thickness_mm: [0.5], vessels: [maybe]}", "line 9: `vary.vessels`: `vessels` must be true or false"),
    ("vary: {}", "line 9: `vary` must be a mapping with `parameter` and `values`, or of parameters"),
    ("vary: {parameter: delta_ri, delta_ri: [0.01]}", "line 9: `vary` must be a mapping"),
])
def test_bad_grids_are_one_line_naming_file_line_and_field(tmp_path, vary, needle, capsys):
    path = study(tmp_path, vary + "\n", "bad.yaml")
    with pytest.raises(ParameterError) as err:
        load_study(path)
    assert needle in str(err.value) and "bad.yaml" in str(err.value)
    assert main(args(path, tmp_path)) == 2
    msg = capsys.readouterr().err.strip()
    assert msg.count("\n") == 0 and "bad.yaml" in msg
    assert not os.path.exists(tmp_path / "c") and not os.path.exists(tmp_path / "r")
