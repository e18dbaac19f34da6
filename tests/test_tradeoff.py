"""The trade-off benchmark's reductions (the sweep itself is `make tradeoff`, not a test)."""

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_tradeoff as T  # noqa: E402


def row(scene, method, voxel, rays, wall_s, fwhm_r, haze, *, half_f=0.1, half_h=0.01, reference=False, exact=None):
    r = {"scene": scene, "method": method, "voxel_um": voxel, "rays": rays, "step_vox": math.nan,
         "reference": reference, "fwhm_r": fwhm_r, "fwhm_r_ci": [fwhm_r - half_f, fwhm_r + half_f],
         "haze": haze, "haze_ci": [haze - half_h, haze + half_h], "wall_s": wall_s, "fwhm_l": 0.0}
    if exact:
        r["exact"] = exact
    return r


def test_errors_split_into_bias_against_the_reference_and_the_interval():
    rows = [row("birch_1mm", "accurate", 0.25, 2000, 90.0, 10.0, 0.80, half_f=0.2, reference=True),
            row("birch_1mm", "fast", 0.5, 500, 5.0, 13.0, 0.84, half_f=0.4, half_h=0.03),
            row("tubes_exact", "fast", 0.5, 1000, 1.0, 6.0, 0.5,
                exact={"fwhm_r": 5.0, "haze": 0.45, "fwhm_l": 0.0})]
    T.errors(rows)
    ref, fast, tubes = rows
    assert fast["fwhm_r_bias"] == pytest.approx(3.0) and fast["fwhm_r_half"] == pytest.approx(0.4)
    assert fast["fwhm_r_error"] == pytest.approx(math.hypot(3.0, 0.4))
    assert fast["haze_error"] == pytest.approx(math.hypot(0.04, 0.03))
    assert fast["fwhm_r_rel_error"] == pytest.approx(math.hypot(3.0, 0.4) / 10.0)
    assert ref["fwhm_r_error"] == pytest.approx(0.2)  # the reference: its interval alone
    assert tubes["ref_kind"] == "exact optics, same rays" and tubes["haze_bias"] == pytest.approx(0.05)


def test_the_recommendation_is_the_cheapest_setting_that_meets_the_target():
    rows = [row("birch_1mm", "accurate", 0.25, 2000, 90.0, 10.0, 0.80, half_f=0.05, half_h=0.005, reference=True),
            row("birch_1mm", "accurate", 0.5, 4000, 30.0, 10.1, 0.801, half_f=0.05, half_h=0.005),
            row("birch_1mm", "fast", 0.5, 1000, 3.0, 10.5, 0.81, half_f=0.3, half_h=0.02),
            row("birch_1mm", "fast", 1.0, 1000, 1.0, 14.0, 0.9, half_f=0.3, half_h=0.02)]
    T.errors(rows)
    lines = [ln for ln in T.recommend(rows) if ln.startswith("| birch_1mm")]
    assert "`accurate` at 0.5 µm, 4000 rays" in lines[0]  # ±1 point, ±5 %
    assert "`fast` at 0.5 µm, 1000 rays" in lines[1]  # ±3 points, ±10 %: fast at 1 µm is off by 40 %
    assert "`fast` at 0.5 µm" in lines[2]
    assert all("none of the swept" in ln for ln in T.recommend(rows) if ln.startswith("| balsa_1mm"))
