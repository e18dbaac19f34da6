"""The report's effect sizes on known inputs: a doubled spread is a resolved hundred percent, the
reference is Table 1's default, rays must give the stored numbers, woods are paired, and a
resample of woods is reduced once whatever the woods' order."""

import json

import numpy as np
import pytest
import xarray as xr

from pipeline.analysis import fwhm
from pipeline.effects import effects, method_rows, per_ray, reduce_rays, resample, resample_key, resampled
from pipeline.report_tables import effects_markdown, method_markdown


def _study(theta_by_value, status=None, dim="thickness", values=(1.0, 2.0)):
    """A minimal study Dataset whose stored numbers are the reduction of its rays."""
    n = len(theta_by_value[0][0])
    tr = np.array([t[0] for t in theta_by_value])
    tl = np.array([t[1] for t in theta_by_value])
    st = np.ones_like(tr, dtype=np.int32) if status is None else status
    red = np.array([reduce_rays(tr[k], tl[k], st[k] == 1, np.arange(n)) for k in range(len(values))])
    ds = xr.Dataset({
        "theta_r": ((dim, "ray"), tr), "theta_l": ((dim, "ray"), tl),
        "status": ((dim, "ray"), st, {"flag_values": [1, 2, 3, 4, 5],
                                      "flag_meanings": "transmitted reflected side trapped tir_at_exit_face"}),
        "FWHM_R": (dim, red[:, 0]), "FWHM_L": (dim, red[:, 1]), "haze": (dim, red[:, 2]),
    }, coords={dim: list(values)})
    return ds


def test_a_doubled_spread_is_a_resolved_hundred_percent_wider_fwhm():
    rng = np.random.default_rng(5)
    r = np.degrees(np.arctan(0.03 * rng.standard_cauchy(600)))
    l_ = np.degrees(np.arctan(0.004 * rng.standard_cauchy(600)))
    ds = _study([(r, l_), (2 * r, l_)])
    effs = {e.quantity: e for e in effects("study-x", ds, n_boot=60)}
    assert effs["FWHM_R"].reference == "1" and effs["FWHM_R"].value == "2"
    # Doubling every angle doubles the Lorentz scale exactly, in every resample (paired).
    assert effs["FWHM_R"].change == pytest.approx(100.0, abs=1.0)
    assert effs["FWHM_R"].resolved and effs["FWHM_R"].ci[0] > 80
    assert effs["FWHM_L"].change == 0.0 and effs["FWHM_L"].ci == (0.0, 0.0) and not effs["FWHM_L"].resolved
    assert effs["haze"].change > 0 and effs["haze"].resolved


def test_the_reference_is_the_table1_default_not_the_first_value():
    rng = np.random.default_rng(2)
    base = rng.standard_cauchy(300)
    ds = _study([(k * base, base * 0.1) for k in (1, 2, 3)], dim="delta_ri", values=(-0.01, 0.01, 0.02))
    effs = effects("study-2", ds, n_boot=20)
    assert {e.reference for e in effs} == {"0.01"} and {e.value for e in effs} == {"-0.01", "0.02"}
    table = "\n".join(effects_markdown({"study-2": effs}))
    assert "delta_ri 0.01 → 0.02" in table and "delta_ri 0.01 → -0.01" in table


def test_effects_refuse_rays_that_do_not_give_the_stored_numbers():
    rng = np.random.default_rng(3)
    ds = _study([(rng.standard_cauchy(200), rng.standard_cauchy(200))] * 2)
    ds["FWHM_R"] = ds["FWHM_R"] * 1.01
    with pytest.raises(ValueError, match="do not reduce to the stored"):
        effects("study-x", ds, n_boot=5)


def test_untransmitted_rays_leave_the_widths_and_haze():
    rng = np.random.default_rng(4)
    r = rng.standard_cauchy(400)
    st = np.ones((2, 400), np.int32)
    st[1, :100] = 2  # reflected: not part of the second value's widths or haze
    ds = _study([(r, r / 10), (r, r / 10)], status=st)
    assert float(ds["FWHM_R"][1]) == pytest.approx(fwhm(r[100:]))


def test_effects_over_woods_pair_the_woods_and_widen_with_them():
    """Two woods that scatter 1× and 3×: a value whose angles are all doubled is +100 % on every
    draw (paired), while each value's own interval spans the woods."""
    rng = np.random.default_rng(8)
    woods = [np.degrees(np.arctan(g * rng.standard_cauchy(400))) for g in (0.01, 0.03)]
    tr = np.array([woods, [2 * w for w in woods]])  # (value, realisation, ray)
    tl = tr / 10
    st = np.ones_like(tr, dtype=np.int32)
    every = [(0, np.arange(400)), (1, np.arange(400))]
    red = np.array([reduce_rays(tr[k], tl[k], st[k] == 1, every) for k in range(2)])
    ds = xr.Dataset({
        "theta_r": (("thickness", "realisation", "ray"), tr), "theta_l": (("thickness", "realisation", "ray"), tl),
        "status": (("thickness", "realisation", "ray"), st,
                   {"flag_values": [1, 2, 3, 4, 5],
                    "flag_meanings": "transmitted reflected side trapped tir_at_exit_face"}),
        "FWHM_R": ("thickness", red[:, 0]), "FWHM_L": ("thickness", red[:, 1]), "haze": ("thickness", red[:, 2]),
    }, coords={"thickness": [1.0, 2.0]})
    assert per_ray(ds, "theta_r").shape == (2, 2, 400)
    e = {x.quantity: x for x in effects("study-x", ds, n_boot=40)}
    assert e["FWHM_R"].change == pytest.approx(100.0, abs=1.0)
    assert e["FWHM_R"].ci[0] > 95 and e["FWHM_R"].ci[1] < 105


def test_the_same_rays_by_both_methods_differ_by_nothing_and_doubled_by_a_hundred_percent():
    rng = np.random.default_rng(9)
    r = np.degrees(np.arctan(0.02 * rng.standard_cauchy(300)))
    acc = _study([(r, r / 5), (r, r / 5)])
    for name in ("FWHM_R", "FWHM_L", "haze"):
        for b in ("lower", "upper"):
            acc[f"{name}_ci_{b}"] = acc[name]
    acc.attrs["trace_settings"] = json.dumps({"method": "exact"})
    same = method_rows({"study-x": acc}, {"study-x": acc}, n_boot=20)
    assert same[0]["FWHM_R_change"] == (0.0, (0.0, 0.0))
    pap = _study([(2 * r, r / 5), (2 * r, r / 5)])
    for name in ("FWHM_R", "FWHM_L", "haze"):
        for b in ("lower", "upper"):
            pap[f"{name}_ci_{b}"] = pap[name]
    pap.attrs["trace_settings"] = json.dumps({"method": "paper"})
    doubled = method_rows({"study-x": acc}, {"study-x": pap}, n_boot=20)
    assert (doubled[0]["ref"], doubled[0]["other"]) == ("exact", "paper")
    assert doubled[0]["FWHM_R_other"] == pytest.approx(2 * doubled[0]["FWHM_R_ref"], rel=1e-9)
    assert method_markdown(doubled)[0].startswith("| study | value | FWHM_R (°): exact · paper | paper − exact |")
    assert doubled[0]["FWHM_R_change"][0] == pytest.approx(100.0, abs=1.0)
    assert doubled[0]["FWHM_L_change"][0] == 0.0 and doubled[0]["rays_common"] == 300


def test_a_resample_of_woods_is_reduced_once_and_its_numbers_do_not_depend_on_the_woods_order():
    """The paired bootstraps reduce each distinct multiset of woods once: that is exact only if the
    half-max widths and haze of pooled rays do not depend on the order the woods come in."""
    rng = np.random.default_rng(3)
    n_real, n = 5, 400
    tr = rng.standard_cauchy((n_real, n)) * rng.uniform(0.5, 3.0, (n_real, 1))
    tl = rng.standard_normal((n_real, n))
    ok = rng.random((n_real, n)) < 0.9
    every = np.arange(n)
    for _ in range(20):
        woods = rng.integers(0, n_real, n_real)
        a = reduce_rays(tr, tl, ok, [(int(r), every) for r in woods])
        b = reduce_rays(tr, tl, ok, [(int(r), every) for r in rng.permutation(woods)])
        np.testing.assert_array_equal(a, b)
    calls = []
    draws = resampled(np.random.default_rng(9), n_real, n, 500, lambda idx: calls.append(idx) or len(calls))
    keys = [resample_key(resample(g, n_real, n), n_real) for g in [np.random.default_rng(9)] for _ in range(500)]
    assert len(calls) == len(set(keys)) < 500  # each multiset of woods reduced once
    assert [draws[i] == draws[keys.index(k)] for i, k in enumerate(keys)] == [True] * 500
    assert resample_key(resample(rng, 1, n), 1) is None  # one wood: its rays are redrawn, nothing is reused
