"""Rays against waves as a study: regime files, sections from the model's phase, and `twray wave` on a
real Dask cluster (cached, the same numbers bit for bit in the workers and here)."""

import math
import textwrap

import numpy as np
import pytest
import xarray as xr

from pipeline.cli import main
from pipeline.microstructure.model import generate_block
from pipeline.params import Grid, ParameterError, build_params
from pipeline.wave.regime import load_regime, ray_origins, run_case
from pipeline.wave.sections import WoodSection, wall_levels
from pipeline.wave.solver import Sampling

TINY = """\
title: tiny
realisations: 2
positions: 1
beam_um: 40
rays: 300
wavelengths: 2
delta_ri: [0.001, 0.03]
geometries:
  - {name: tubes, reference: tubes-hex, pitch_um: 14.5, wall_um: 2.0, jitter: 0.1, thickness_mm: 0.03}
"""


def _write(tmp_path, text, name="tiny.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


@pytest.mark.parametrize("edit, message", [
    ("extra: 1\n", "unknown key `extra`"),
    ("delta_ri: [0.0, 0.01]\n", "`delta_ri` must be a list of non-zero numbers"),
    ("sampling: {sub_um: 0.1}\n", r"`sampling` gives dx = 0.3 µm, more than λ/\(2n\)"),
    ("geometries:\n  - {name: x, reference: tubes-hex, preset: birch, pitch_um: 14.5, wall_um: 2, thickness_mm: 0.1}\n",
     "give either `reference`"),
    ("geometries:\n  - {name: x, reference: tubes-hex, pitch_um: 14.5, thickness_mm: 0.1}\n", "`wall_um` is required"),
    ("geometries:\n  - {name: x, preset: birch, thickness_mm: 0.1, set: {wall_thickness_um: -1}}\n",
     "wall_thickness_um"),
])
def test_a_bad_regime_file_is_one_line_naming_the_field(tmp_path, edit, message):
    text = TINY[:TINY.index("geometries:")] if edit.startswith("geometries") else "".join(
        line for line in TINY.splitlines(keepends=True) if line.split(":")[0] != edit.split(":")[0])
    path = _write(tmp_path, text + edit)
    with pytest.raises(ParameterError, match=message) as err:
        load_regime(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_wood_section_is_the_generators_phase_and_uniform_along_l():
    sec = WoodSection(build_params("birch"), 3)
    s = Sampling(sub_um=0.1, per_dx=2, per_dz=2)
    lev = wall_levels(sec, r0_um=40.0, nx=300, j0=10, nz=200, sampling=s)
    for l_um in (0.0, 300.0):  # the generator's own voxels of the same wood, at two depths along L
        grid = Grid((600, 400, 1), 0.1, (40.0, 2.0, l_um - 0.05))
        block = generate_block(sec.params, grid, (0, 0, 0), (600, 400, 1), seed=3)[:, :, 0]
        counts = block.reshape(300, 2, 200, 2).sum(axis=(1, 3)).T
        assert np.mean(counts != lev) < 1e-3  # the same cells (the fibres' jitter is constant along L)
        if l_um == 0.0:
            assert np.array_equal(counts, lev)
    assert 0.2 < lev.mean() / s.levels < 0.45  # birch's wall fraction


def test_the_beam_rays_are_drawn_from_the_gaussian_intensity(tmp_path):
    regime = load_regime(_write(tmp_path, TINY.replace("rays: 300", "rays: 20000")))
    r = ray_origins(regime, 1, 0, 100.0)[:, 0]
    assert np.mean(r) == pytest.approx(100.0, abs=0.2)
    assert np.std(r) == pytest.approx(regime.beam_um / 4, rel=0.02)  # intensity exp(-2 x²/w0²): σ = w0/2
    assert np.array_equal(r, ray_origins(regime, 1, 0, 100.0)[:, 0])


def test_twray_wave_on_a_cluster_is_cached_and_bit_for_bit_the_cases_computed_here(tmp_path, capsys):
    path = _write(tmp_path, TINY)
    args = [str(path), "--results", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"), "--workers", "2",
            "--quiet"]
    assert main(["wave", *args]) == 0
    first = capsys.readouterr().out
    assert "2 cases computed" in first
    ds = xr.open_zarr(tmp_path / "out" / "tiny.zarr").load()
    regime = load_regime(path)
    here = run_case(regime, regime.geometries[0], 1)
    assert np.array_equal(ds["haze_wave"].sel(geometry="tubes", exit="internal", realisation=1).values,
                          here["haze_wave_internal"])
    assert np.array_equal(ds["FWHM_R_half_max_ray"].sel(geometry="tubes", exit="air", realisation=1).values,
                          here["half-max_ray_air"])
    # physics: at ΔRI 0.001 nearly all light is the unscattered beam and neither says haze; at 0.03 both do
    weak, strong = ds.sel(geometry="tubes", exit="internal", delta_ri=0.001), ds.sel(geometry="tubes", exit="internal",
                                                                                  delta_ri=0.03)
    assert float(weak["wave_coherent"].min()) > 0.95 and float(weak["haze_wave"].max()) < 0.01
    assert float(strong["haze_wave"].min()) > 0.1 and float(strong["haze_ray"].min()) > 0.1
    assert float(ds["wave_lost"].max()) < 0.01 and float(ds["wave_reflected"].max()) < 0.01
    assert main(["wave", *args]) == 0
    assert "0 cases computed" in capsys.readouterr().out
    again = xr.open_zarr(tmp_path / "out" / "tiny.zarr")
    assert again.attrs["twray_digest"] == ds.attrs["twray_digest"]
    assert math.isfinite(float(ds["haze_difference"].sel(geometry="tubes", exit="internal", delta_ri=0.03)))


def test_a_wave_cases_cache_key_changes_with_its_ray_tracers_version(tmp_path, monkeypatch):
    """A case holds rays beside its waves: a new version of their method must compute it again (the
    key held only the waves' version, and a regime retraced with a new `exact` kept its old rays)."""
    from pipeline import versions
    from pipeline.wave.regime import RAY_METHOD
    from pipeline.wave.run import case_path, case_record

    regime = load_regime(_write(tmp_path, TINY))
    g = regime.geometries[0]
    before = case_path(tmp_path, case_record(regime, g, 0))
    assert case_path(tmp_path, case_record(load_regime(_write(tmp_path, TINY)), g, 0)) == before
    monkeypatch.setitem(versions.TRACERS, RAY_METHOD, versions.TRACERS[RAY_METHOD] + "-next")
    assert case_path(tmp_path, case_record(regime, g, 0)) != before


def test_a_wood_bounded_along_r_lets_rays_out_through_its_sides():
    """A section's window: rays that end beyond [r_lo, r_hi] leave with status SIDE, the others as in
    the unbounded wood, ray for ray."""
    from pipeline.optics.interface import SIDE
    from pipeline.optics.rays import Beam
    from pipeline.optics.settings import Optics, TraceSettings
    from pipeline.optics.trace import trace
    from pipeline.optics.wood_surface import WoodSurface

    params = WoodSection(build_params("birch"), 2).params
    origins = np.zeros((40, 3))
    origins[:, 0] = np.linspace(20.0, 80.0, 40)
    dirs = np.tile([0.0, 1.0, 0.0], (40, 1))
    dirs[::2] = [0.8, 0.6, 0.0]  # every other ray heads steeply along +R
    beam, optics = Beam(origins, dirs, np.arange(40)), Optics.of_delta(1.49, 0.01)
    free = trace(WoodSurface(params, thickness_um=60.0, seed=2), beam, optics, TraceSettings(method="exact"))
    boxed = trace(WoodSurface(params, thickness_um=60.0, seed=2, r_bounds_um=(0.0, 100.0)), beam, optics,
                  TraceSettings(method="exact"))
    out = free.position[:, 0] > 100.0
    assert out.any() and np.all(boxed.status[out] == SIDE)
    keep = boxed.status != SIDE
    assert keep.sum() >= 20 and np.array_equal(boxed.exit_direction[keep], free.exit_direction[keep])


def test_the_reports_wave_section_is_the_committed_map():
    """REPORT.md's "Where geometrical optics holds" prints the committed map's values, and the map
    says what the physics must: at the smallest ΔRI nearly all light is the unscattered beam and
    both pictures see little haze; the reflection the solver leaves out stays below 1 % of the power."""
    from pathlib import Path

    from pipeline.publish import open_dataset
    from pipeline.report_wave import regime_table

    root = Path(__file__).resolve().parents[1]
    ds = open_dataset(root / "results" / "paper" / "wave" / "regime.zarr")
    report = (root / "results" / "REPORT.md").read_text()
    for line in regime_table(ds):
        assert line in report
    weakest = ds.sel(delta_ri=min(abs(float(v)) for v in ds["delta_ri"].values), exit="internal")
    assert float(weakest["wave_coherent"].min()) > 0.9
    assert float(weakest["haze_wave"].max()) < 0.05 and float(weakest["haze_ray"].max()) < 0.05
    assert float(ds["wave_reflected"].max()) < 0.01
    # light lost at the window's sides beyond 1 % only where the map says so (window_limited)
    lost = ds["wave_lost"].mean("realisation")
    assert bool(((lost <= 0.01) | (ds["window_limited"] == 1)).all()) and float(lost.max()) < 0.06


def test_twray_design_says_what_the_map_measured_at_the_windows_edges(capsys):
    from pathlib import Path

    from pipeline.publish import open_dataset
    from pipeline.wave.run import verdict_at

    root = Path(__file__).resolve().parents[1]
    ds = open_dataset(root / "results" / "paper" / "wave" / "regime.zarr")
    base = verdict_at(ds, "birch", 1.0, 0.01)  # Table 1's base scene: rays' haze high, their width wider
    assert not base["holds"] and base["haze_difference"] > 0.02 and base["fwhm_r_ratio"] > 1.1
    assert verdict_at(ds, "birch", 1.0, 0.013)["delta_ri"] == 0.01  # the nearest measured ΔRI within 2x
    assert verdict_at(ds, "birch", 1.0, -0.002) is None  # the nearest negative one (-0.01) is 5x away
    assert verdict_at(ds, "birch", 0.5, 0.01) is None  # no 0.5 mm section
    assert main(["design", "--preset", "birch", "--thickness-mm", "1", "--haze-max", "0.2",
                 "--results", str(root / "results" / "paper")]) == 0
    line = capsys.readouterr().out.splitlines()[1]
    assert line.startswith("  ray optics at this window's edges: -") and line.count("(") >= 2


def test_the_waves_numbers_have_converged_in_the_sampling_steps(tmp_path):
    """Halving dx and dz (and the phase's grid) moves a lattice case's haze by < 0.5 points and its
    widths by < 3 % at every ΔRI (make bench-wave measures the same on the map's sections)."""
    import dataclasses

    regime = load_regime(_write(tmp_path, TINY.replace("wavelengths: 2", "wavelengths: 1")))
    g = dataclasses.replace(regime.geometries[0], thickness_um=20.0)
    s = regime.sampling
    base = run_case(regime, g, 0)
    fine = run_case(dataclasses.replace(regime, sampling=Sampling(s.sub_um / 2, s.per_dx, s.per_dz)), g, 0)
    assert np.all(np.abs(fine["haze_wave_internal"] - base["haze_wave_internal"]) < 0.005)
    assert np.allclose(fine["half-max_wave_internal"], base["half-max_wave_internal"], rtol=0.03)
