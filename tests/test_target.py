"""Tracing to a target precision (`--target-ci`, `target_ci:`) and the haze interval."""

import json

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from pipeline.analysis import Target, haze_ci
from pipeline.cli import main
from pipeline.params import ParameterError
from pipeline.study.spec import load_study

STUDY = """\
title: to a target
preset: birch
seed: 3
realisations: 1
rays: 200
beam_um: 100
thickness_mm: 0.3
delta_ri: 0.01
trace: {method: fast}
target_ci: {target}
vary: {parameter: delta_ri, values: [0.01, 0.02]}
"""


@pytest.mark.parametrize("p, n", [(0.0, 100), (0.3, 40), (0.5, 1000), (1.0, 7)])
def test_the_haze_interval_is_wilsons_and_covers_95_percent(p, n):
    lo, hi = haze_ci(p, n)
    assert 0.0 <= lo <= p <= hi <= 1.0 and hi > lo
    # Wilson's bounds are where the score test just rejects: |p - q| = z sqrt(q (1 - q) / n).
    z = stats.norm.ppf(0.975)
    for q in (lo, hi):
        if 0 < q < 1:
            assert abs(p - q) == pytest.approx(z * np.sqrt(q * (1 - q) / n), rel=1e-9)
    # Coverage, exactly, from the binomial distribution at a true haze of 0.3.
    k = np.arange(n + 1)
    covered = np.array([haze_ci(x / n, n)[0] <= 0.3 <= haze_ci(x / n, n)[1] for x in k])
    assert 0.92 <= float(np.sum(stats.binom.pmf(k, n, 0.3)[covered])) <= 0.98


def test_a_target_is_met_only_when_every_asked_interval_is_narrow_enough():
    s = {"haze_ci": [0.30, 0.318], "fwhm_r_ci_deg": [2.0, 2.58], "fwhm_l_ci_deg": [0.1, 0.12]}
    assert Target(haze=0.01).met(s) and not Target(haze=0.0089).met(s)
    assert Target(fwhm_deg=0.3).met(s) and not Target(fwhm_deg=0.28).met(s)
    assert not Target(haze=0.01, fwhm_deg=0.28).met(s)
    assert not Target(haze=0.5).met({**s, "haze_ci": [float("nan"), float("nan")]})
    # Relative to FWHM_R itself: ±0.29° on 2.3° is ±12.6 %.
    s["fwhm_r_deg"] = 2.3
    assert Target(fwhm_r_rel=0.13).met(s) and not Target(fwhm_r_rel=0.12).met(s)
    assert Target(haze=0.01, fwhm_r_rel=0.12).shortfall(s) == pytest.approx(0.29 / 2.3 / 0.12)
    assert not Target(fwhm_r_rel=0.5).met({**s, "fwhm_r_deg": float("nan")})


def test_trace_to_a_target_doubles_the_rays_and_equals_one_trace_of_that_many(capsys):
    base = ["trace", "--preset", "birch", "--thickness-mm", "0.1", "--delta-ri", "0.01", "--beam-um", "100",
            "--method", "fast", "--seed", "2", "--json", "--quiet"]
    assert main(base + ["--rays", "50", "--target-ci", "0.05"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["target_ci_met"] and got["n_rays"] in (100, 200, 400, 800, 1600)
    lo, hi = got["haze_ci"]
    assert (hi - lo) / 2 <= 0.05
    # Half as many rays would not have met it (the doubling stops at the first that does).
    assert main(base + ["--rays", str(got["n_rays"] // 2)]) == 0
    half = json.loads(capsys.readouterr().out)
    assert (half["haze_ci"][1] - half["haze_ci"][0]) / 2 > 0.05
    assert main(base + ["--rays", str(got["n_rays"])]) == 0
    once = json.loads(capsys.readouterr().out)
    for k in ("haze", "haze_ci", "fwhm_r_deg", "fwhm_l_deg", "fwhm_r_ci_deg"):
        assert once[k] == got[k], k
    # A cap below what the target needs: reported, not met, exit 0.
    assert main(base + ["--rays", "50", "--target-ci", "0.001", "--max-rays", "100"]) == 0
    capped = json.loads(capsys.readouterr().out)
    assert capped["n_rays"] == 100 and capped["target_ci_met"] is False


@pytest.mark.parametrize("args, message", [
    (["--target-ci", "0"], "`target_ci` must be a haze half-width in (0, 0.5], got target_ci=0"),
    (["--target-ci", "nan"], "`target_ci` must be a finite number"),
    (["--target-ci-fwhm", "-1"], "`target_ci_fwhm` must be > 0 degree, got target_ci_fwhm=-1"),
    (["--target-ci", "0.1", "--max-rays", "10"], "`max_rays` must be >= 50, got max_rays=10"),
])
def test_bad_targets_are_one_line_exit_2(args, message, capsys):
    code = main(["trace", "--preset", "birch", "--thickness-mm", "0.05", "--delta-ri", "0.01",
                 "--rays", "50", *args])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("target, message", [
    ("0", "`target_ci.haze` must be a number in (0, 0.5], got 0"),
    ("{haze: 0.01, wobble: 1}", "unknown key `target_ci.wobble`"),
    ("{max_rays: 1000}", "`target_ci` must give `haze`, `fwhm_deg` or `fwhm_r_rel`"),
    ("{haze: 0.1, over: realisations}", "`target_ci.over` must be `rays` (more rays) or `woods`"),
    ("{fwhm_r_rel: 3}", "`target_ci.fwhm_r_rel` must be a number in (0, 1], got 3"),
    ("{haze: 0.1, over: woods, max_realisations: 0}", "`target_ci.max_realisations` must be a positive integer"),
    ("{haze: 0.1, max_rays: 1.5}", "`target_ci.max_rays` must be a positive integer, got 1.5"),
])
def test_bad_target_ci_in_a_study_is_named(tmp_path, target, message):
    path = tmp_path / "t.yaml"
    path.write_text(STUDY.replace("{target}", target))
    with pytest.raises(ParameterError, match=r"t.yaml.*" + message.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]")):
        load_study(path)


def test_a_study_traced_to_a_target_reuses_its_shards_and_equals_a_study_of_that_many_rays(tmp_path, capsys):
    path = tmp_path / "t.yaml"
    path.write_text(STUDY.replace("{target}", "{haze: 0.07, max_rays: 4000}"))
    args = ["--scale", "small", "--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r"),
            "--shard-rays", "20", "--workers", "1", "--threads", "2", "--quiet"]
    assert main(["study", str(path), *args]) == 0
    err = capsys.readouterr().err
    assert "tracing 40 rays" in err  # small scale: 20 rays first, then doubled
    ds = xr.open_zarr(tmp_path / "r" / "t.zarr", consolidated=False)
    n = ds.sizes["ray"]
    assert ds.attrs["rays"] == n and ds.attrs["target_ci_met"] == 1 and n > 20
    assert np.all((ds.haze_ci_upper - ds.haze_ci_lower).values / 2 <= 0.07)
    assert ds.haze_ci_lower.attrs["interval"] == "Wilson score (binomial)"
    shards = sorted(p.name for p in (tmp_path / "c" / "rays").iterdir())
    # Every round's shards were kept and reused: n / 20 shards per value, not more.
    assert len(shards) == 2 * n // 20
    # The same study with that many rays and no target: the same cache entries, the same numbers.
    plain = tmp_path / "plain.yaml"
    plain.write_text(STUDY.replace("target_ci: {target}\n", "").replace("rays: 200", f"rays: {n * 10}"))
    assert main(["study", str(plain), *args]) == 0
    assert sorted(p.name for p in (tmp_path / "c" / "rays").iterdir()) == shards
    other = xr.open_zarr(tmp_path / "r" / "plain.zarr", consolidated=False)
    for name in ("FWHM_R", "FWHM_L", "haze", "haze_ci_lower", "theta_r"):
        assert np.array_equal(ds[name].values, other[name].values), name


WOODS = STUDY.replace("realisations: 1", "realisations: 2").replace("rays: 200", "rays: 40").replace(
    "beam_um: 100", "beam_um: 60").replace("thickness_mm: 0.3", "thickness_mm: 0.08")


def test_a_study_traced_to_a_target_over_woods_adds_woods_and_equals_a_study_of_that_many(tmp_path, capsys):
    """More woods, not more rays, narrow the interval with the woods: the study is traced on as
    many woods as its widest interval asks for (the first ones reused), and equals the same study
    with that many realisations and no target, bit for bit."""
    path = tmp_path / "t.yaml"
    path.write_text(WOODS.replace("{target}", "{haze: 0.06, over: woods, max_realisations: 12}"))
    args = ["--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r"), "--shard-rays", "40",
            "--workers", "1", "--threads", "2", "--quiet"]
    assert main(["study", str(path), *args]) == 0
    err = capsys.readouterr().err
    ds = xr.open_zarr(tmp_path / "r" / "t.zarr", consolidated=False)
    n = ds.sizes["realisation"]
    assert f"tracing {n} woods" in err and 2 < n <= 12, err
    assert ds.sizes["ray"] == 40 and json.loads(ds.attrs["target_ci"])["over"] == "woods"
    half = (ds.haze_ci_upper - ds.haze_ci_lower).values / 2
    assert ds.attrs["target_ci_met"] == int(np.all(half <= 0.06))
    assert ds.attrs["target_ci_met"] == 1 or n == 12
    # Each wood's shards once: the first two woods were not traced again.
    assert len(list((tmp_path / "c" / "rays").iterdir())) == 2 * n
    plain = tmp_path / "plain.yaml"
    plain.write_text(WOODS.replace("target_ci: {target}\n", "").replace("realisations: 2", f"realisations: {n}"))
    assert main(["study", str(plain), *args]) == 0
    other = xr.open_zarr(tmp_path / "r" / "plain.zarr", consolidated=False)
    for name in ("FWHM_R", "FWHM_R_ci_lower", "haze", "haze_ci_upper", "theta_r", "haze_per_realisation"):
        assert np.array_equal(ds[name].values, other[name].values), name
    # The quick scale traces at most 5 woods: the target is not pursued beyond, and the run says so.
    assert main(["study", str(path), *args, "--scale", "quick", "--results", str(tmp_path / "q")]) == 0
    err = capsys.readouterr().err
    quick = xr.open_zarr(tmp_path / "q" / "t.zarr", consolidated=False)
    assert quick.sizes["realisation"] <= 5 and quick.attrs["target_ci_met"] == 0
    assert "still wider than target_ci at the cap of 5 woods (quick scale): --scale paper traces to the target" in err


def test_a_study_with_a_target_over_woods_is_costed_at_its_cap_of_woods_not_of_rays(tmp_path):
    from pipeline.limits import study_estimate
    from pipeline.study.spec import at_target_cap

    path, plain = tmp_path / "t.yaml", tmp_path / "plain.yaml"
    path.write_text(WOODS.replace("{target}", "{haze: 0.06, over: woods, max_realisations: 7}"))
    plain.write_text(WOODS.replace("target_ci: {target}\n", "").replace("realisations: 2", "realisations: 7"))
    st = load_study(path)
    capped = at_target_cap(st)
    assert st.realisations == 2 and capped.realisations == 7 and st.scenes[0].rays == 40
    assert study_estimate(capped.all_scenes(), shard_rays=40).cpu_s == pytest.approx(
        study_estimate(load_study(plain).all_scenes(), shard_rays=40).cpu_s)
    # The quick scale traces at most 5 woods, its target too; small at most 2.
    assert load_study(path, scale="quick").scenes[0].target.max_realisations == 5
    assert at_target_cap(load_study(path, scale="small")).realisations == 2
