"""Wood realisations: a study traces every value on several woods (seeds seed, seed + 1, ...),
pools them, and states intervals that hold the wood-to-wood variation."""

import json

import numpy as np
import pytest
import xarray as xr

from pipeline.analysis import fwhm
from pipeline.summary import pool
from pipeline.cli import main
from pipeline.optics.rays import RayResult
from pipeline.optics.settings import settings_for
from pipeline.params import ParameterError
from pipeline.study.spec import load_study


def rays(gamma_r_deg, n, seed, *, gamma_l_deg=0.5):
    """A RayResult of ``n`` transmitted rays with Cauchy angles of half-width ``gamma``."""
    rng = np.random.default_rng(seed)
    tr = np.radians(np.clip(gamma_r_deg * rng.standard_cauchy(n), -80, 80))
    tl = np.radians(np.clip(gamma_l_deg * rng.standard_cauchy(n), -80, 80))
    d = np.stack([np.tan(tr), np.ones(n), np.tan(tl)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    z = np.zeros((n, 3))
    return RayResult(position=z, direction=d, exit_direction=d, status=np.ones(n, np.int8),
                     events=np.full(n, 10), path=np.zeros(n),
                     settings=settings_for("fast"))


def test_pooled_intervals_hold_the_wood_to_wood_variation():
    """Woods that scatter differently (half-widths 1°, 2°, 3°): the interval over woods is
    several times the ray-only one; 8 woods that scatter alike: about the same (t on 7 d.o.f.)."""
    differ = pool([rays(g, 800, s) for s, g in enumerate((1.0, 2.0, 3.0))], n_boot=120, seed=1)
    alike = pool([rays(2.0, 800, s) for s in range(8)], n_boot=120, seed=1)

    def width(p, key):
        return p[key][1] - p[key][0]

    assert width(differ, "fwhm_r_ci_deg") > 3 * width(differ, "fwhm_r_ray_ci_deg")
    assert width(alike, "fwhm_r_ci_deg") < 1.6 * width(alike, "fwhm_r_ray_ci_deg")
    # The point estimate is the fit to every ray pooled, realisation 0 first.
    pooled = np.concatenate([r.theta_r for r in [rays(g, 800, s) for s, g in enumerate((1.0, 2.0, 3.0))]])
    assert differ["fwhm_r_deg"] == pytest.approx(fwhm(pooled), rel=1e-9)
    assert differ["n_rays"] == differ["n_transmitted"] == 2400 and differ["realisations"] == 3
    for p in (differ, alike):
        for q in ("fwhm_r", "fwhm_l"):
            lo, hi = p[f"{q}_ci_deg"]
            assert lo <= p[f"{q}_deg"] <= hi


def test_one_realisation_gives_the_ray_interval_and_wilsons_haze_interval():
    one = pool([rays(2.0, 500, 7)], n_boot=60, seed=3)
    assert one["fwhm_r_ci_deg"] == one["fwhm_r_ray_ci_deg"] and one["haze_ci"] == one["haze_ray_ci"]


STUDY = """\
title: realisations
preset: birch
seed: 5
rays: 300
beam_um: 100
thickness_mm: 0.3
delta_ri: 0.02
trace: {method: fast}
vary: {parameter: delta_ri, values: [0.01, 0.02]}
"""


def test_realisations_from_the_file_the_scale_and_the_command_line(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(STUDY)
    assert load_study(path).realisations == 5  # the default at paper scale
    assert load_study(path, scale="small").realisations == 2  # at most 2 at small scale
    path.write_text(STUDY + "realisations: 3\n")
    st = load_study(path)
    assert st.realisations == 3 and load_study(path, realisations=1).realisations == 1
    # Realisation r is the wood and beam of seed + r, for every value alike.
    assert [st.realisation(i, r).seed for i in (0, 1) for r in range(3)] == [5, 6, 7, 5, 6, 7]
    assert st.realisation(1, 2).wood == st.realisation(0, 2).wood
    path.write_text(STUDY + "realisations: 0\n")
    with pytest.raises(ParameterError, match=r"line 10: `realisations` must be an integer in \[1, 1000\], got 0"):
        load_study(path)


def test_a_realisation_is_the_same_numbers_alone_or_among_others_and_rerun(tmp_path, capsys):
    """Realisation 1 of a 2-realisation study is the study of seed + 1 traced alone; a second
    run with more workers gives the same Dataset."""
    both = tmp_path / "both.yaml"
    both.write_text(STUDY + "realisations: 2\n")
    alone = tmp_path / "alone.yaml"
    alone.write_text(STUDY.replace("seed: 5", "seed: 6") + "realisations: 1\n")
    common = ["--scale", "small", "--cache", str(tmp_path / "c"), "--workers", "1"]
    assert main(["study", str(both), str(alone), *common, "--results", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "30 rays x 2 realisations" in out
    b = xr.open_zarr(tmp_path / "r" / "both.zarr", consolidated=False).load()
    a = xr.open_zarr(tmp_path / "r" / "alone.zarr", consolidated=False).load()
    assert b.sizes == {"delta_ri": 2, "realisation": 2, "ray": 30}
    np.testing.assert_array_equal(b.theta_r.isel(realisation=1).values, a.theta_r.isel(realisation=0).values)
    np.testing.assert_array_equal(b.FWHM_R_per_realisation.isel(realisation=1).values, a.FWHM_R.values)
    assert not np.array_equal(b.theta_r.isel(realisation=0).values, b.theta_r.isel(realisation=1).values)
    # The cache is shared: the two studies traced realisation 1's scenes once.
    keys = json.loads(b.attrs["cache_keys"])
    assert keys[0]["realisations"][1]["summary"] == json.loads(a.attrs["cache_keys"])[0]["realisations"][0]["summary"]
    # A fresh cache and two worker processes: the same numbers.
    assert main(["study", str(both), "--scale", "small", "--cache", str(tmp_path / "c2"), "--workers", "2",
                 "--results", str(tmp_path / "r2")]) == 0
    b2 = xr.open_zarr(tmp_path / "r2" / "both.zarr", consolidated=False).load()
    for name in ("FWHM_R", "FWHM_L", "haze", "FWHM_R_ci_lower", "FWHM_R_ci_upper", "theta_r"):
        np.testing.assert_array_equal(b[name].values, b2[name].values)
    assert main(["study", str(both), *common, "--results", str(tmp_path / "r"), "--realisations", "0"]) == 2
    assert "`realisations` must be" in capsys.readouterr().err
