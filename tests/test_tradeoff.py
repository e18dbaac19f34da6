"""The trade-off benchmark's reductions (the sweep itself is `make tradeoff`, not a test)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.effects import paired_change, reduce_rays

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_tradeoff as T  # noqa: E402

RNG = np.random.default_rng(5)
THETA_R = np.clip(RNG.standard_cauchy(3000) * 2.0, -60, 60)
THETA_L = np.clip(RNG.standard_cauchy(3000) * 0.5, -60, 60)


def wood(method, voxel, rays, wall_s, stretch=1.0, *, half_f=0.1, half_h=0.01):
    """A wood point whose rays are the reference's first ``rays``, θ_R stretched by ``stretch``."""
    angles = (THETA_R[:rays] * stretch, THETA_L[:rays].copy(), np.ones(rays, bool))
    f_r, f_l, h = reduce_rays(*angles, np.arange(rays), T.ESTIMATOR)
    return {"scene": "birch_1mm", "method": method, "voxel_um": voxel, "rays": rays, "step_vox": math.nan,
            "reference": False, "fwhm_r": f_r, "fwhm_r_ci": [f_r - half_f, f_r + half_f], "fwhm_l": f_l,
            "haze": h, "haze_ci": [h - half_h, h + half_h], "wall_s": wall_s, "angles": angles}


def test_paired_change_sees_a_stretch_that_an_interval_over_independent_rays_would_drown():
    ref = (THETA_R[:500], THETA_L[:500], np.ones(500, bool))
    other = (1.1 * THETA_R[:500], THETA_L[:500], np.ones(500, bool))
    change, ci = paired_change(ref, other, n_boot=200)
    assert change[0] == pytest.approx(10.0, abs=0.1) and ci[0, 0] > 9.0 and ci[0, 1] < 11.0
    assert change[1] == 0.0 and ci[1, 0] == ci[1, 1] == 0.0  # θ_L untouched: no change, no spread
    assert change[2] >= 0.0  # stretching θ_R only moves rays out of the haze cone's inside


def test_wood_errors_are_against_the_exact_trace_of_the_same_rays():
    rows = [wood("exact", math.nan, 3000, 60.0), wood("exact", math.nan, 500, 10.0),
            wood("fast", 0.5, 500, 5.0, 1.3, half_f=0.4, half_h=0.03)]
    T.errors(rows)
    ref, small, fast = rows
    assert ref["reference"] and not small["reference"]  # the exact trace with the most rays
    assert small["fwhm_r_bias"] == 0.0 and small["haze_bias"] == 0.0  # its first 500 rays are these
    assert small["fwhm_r_error"] == pytest.approx(0.1)  # exact: its interval alone
    ref500 = reduce_rays(THETA_R[:500], THETA_L[:500], np.ones(500, bool), np.arange(500), T.ESTIMATOR)
    assert fast["ref_fwhm_r"] == pytest.approx(ref500[0])
    assert fast["fwhm_r_bias"] == pytest.approx(fast["fwhm_r"] - ref500[0])
    assert fast["fwhm_r_bias_pct"] == pytest.approx(30.0, abs=0.3)
    assert fast["fwhm_r_bias_ci"][0] < 30.0 < fast["fwhm_r_bias_ci"][1]
    assert fast["fwhm_r_error"] == pytest.approx(math.hypot(fast["fwhm_r_bias"], 0.4))
    assert fast["fwhm_r_rel_error"] == pytest.approx(fast["fwhm_r_error"] / ref500[0])


def test_lattice_errors_are_against_the_lattice_tracer():
    r = {"scene": "tubes_exact", "method": "fast", "voxel_um": 0.5, "rays": 1000, "step_vox": math.nan,
         "reference": False, "fwhm_r": 6.0, "fwhm_r_ci": [5.9, 6.1], "haze": 0.5, "haze_ci": [0.49, 0.51],
         "wall_s": 1.0, "fwhm_l": 0.0, "exact": {"fwhm_r": 5.0, "haze": 0.45, "fwhm_l": 0.0}}
    T.errors([r])
    assert r["haze_bias"] == pytest.approx(0.05) and r["fwhm_r_error"] == pytest.approx(math.hypot(1.0, 0.1))
    assert r["ref_kind"].startswith("exact optics")


def test_the_recommendation_is_the_cheapest_setting_that_meets_the_target():
    rows = [wood("exact", math.nan, 3000, 90.0, half_f=0.05, half_h=0.005),
            wood("accurate", 0.5, 3000, 30.0, 1.01, half_f=0.05, half_h=0.005),
            wood("fast", 0.5, 1000, 3.0, 1.07, half_f=0.05, half_h=0.02),
            wood("fast", 1.0, 1000, 1.0, 1.4, half_f=0.3, half_h=0.02)]
    T.errors(rows)
    lines = [ln for ln in T.recommend(rows) if ln.startswith("| birch_1mm")]
    assert "`accurate` at 0.5 µm, 3000 rays" in lines[0]  # ±1 point, ±5 %
    assert "`fast` at 0.5 µm, 1000 rays" in lines[1]  # ±3 points, ±10 %: fast at 1 µm is off by 40 %
    assert "`fast` at 0.5 µm" in lines[2]
    assert all("none of the swept" in ln for ln in T.recommend(rows) if ln.startswith("| balsa_1mm"))
    table = "\n".join(T.wood_errors_md(rows))
    assert "`fast` at 1 µm, 1000 rays | +40 %" in table and "| birch_1mm | `exact`, 1000 rays | 0 (reference)" not in table


def test_a_point_traced_with_each_kind_of_method_gives_a_row(monkeypatch):
    """Every point kind of the sweep runs to its row: `exact` (whose results carry no voxel
    diagnostics: it reads no voxels) and a voxel method on the same wood, on the same entry points.
    The sweep once ran 39 minutes and then failed on its first `exact` row."""
    monkeypatch.setattr(T, "N_BOOT", 20)
    rows = [T.run_point({"scene": "birch_0.25mm", "method": m, "voxel_um": v, "rays": 12, "step_vox": math.nan,
                         "reference": False}) for m, v in (("exact", math.nan), ("fast", 1.0))]
    exact, fast = rows
    assert exact["voxels_read"] == 0.0 and fast["voxels_read"] > 0
    for r in rows:
        assert r["transmitted"] > 0 and math.isfinite(r["haze"]) and r["interfaces_per_ray"] > 10
        assert r["angles"][0].shape == (12,)  # kept for the paired bias against the reference


def test_an_exact_point_is_unbiased_against_the_reference_of_which_its_rays_are_the_first(monkeypatch):
    """A wood's `exact` point traces the first rays of its reference: its bias is none, which needs
    the reference's widths by the points' own estimator (the reference was once reduced by the
    project's default, half-max, against the points' Lorentz MLE: a bias of 2-3° on every point)."""
    monkeypatch.setattr(T, "N_BOOT", 20)
    pts = [{"scene": "birch_0.25mm", "method": "exact", "voxel_um": math.nan, "rays": n, "step_vox": math.nan,
            "reference": False} for n in (30, 15)]
    rows = [T.run_point(p) for p in pts]
    T.errors(rows)
    ref, small = rows
    assert ref["reference"] and not small["reference"]
    assert small["fwhm_r_bias"] == 0.0 and small["haze_bias"] == 0.0
    assert small["ref_fwhm_r"] == small["fwhm_r"]
