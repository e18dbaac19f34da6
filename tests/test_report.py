"""The reproduction report and its figures: every number matches its dataset, every linked
figure exists, the effect sizes are right on known inputs, and the figure helpers draw real
physics (straight rays in index-matched wood, the wood's own sections)."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from pipeline.analysis import image_quality
from pipeline.cli import main
from pipeline.figures import sections, structure_label, trajectories
from pipeline.microstructure.model import tip_wall_angle_deg
from pipeline.params import build_params
from pipeline.report import (FIBRE_TIPS, TABLE1, build_report, effects, effects_markdown, figure_links,
                             fibre_tip_rows, load_table1, table1_rows)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
REPORT = RESULTS / "REPORT.md"


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------ the committed report
@pytest.fixture(scope="module")
def report_text():
    return REPORT.read_text()


@pytest.fixture(scope="module")
def tables():
    return load_table1(RESULTS / "paper")


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _numbers(cell: str) -> list[float]:
    return [float(x) for x in re.findall(r"[-+]?\d+\.\d+|[-+]?\d+", cell)]


def test_every_table1_number_in_the_report_is_its_dataset_value(report_text, tables):
    rows = {(r["study"], r["value"]): r for r in table1_rows(tables)}
    seen = 0
    for line in report_text.splitlines():
        cells = _cells(line)
        if len(cells) != 9 or cells[0] not in TABLE1:
            continue
        r = rows[(cells[0], cells[2])]
        assert cells[1] == r["parameter"]
        for cell, key, nd in ((cells[3], "FWHM_R", 2), (cells[4], "FWHM_L", 2), (cells[5], "haze", 1)):
            value, lo, hi = _numbers(cell)
            np.testing.assert_allclose([value, lo, hi], [r[key], *r[f"{key}_ci"]], atol=0.51 * 10 ** -nd)
        assert cells[6] == f"{r['transmitted']}/{r['rays']}"
        np.testing.assert_allclose(_numbers(cells[7])[0], r["interfaces_per_ray"], atol=0.051)
        np.testing.assert_allclose(_numbers(cells[8]), r["FWHM_R_each"], atol=0.0051)
        assert len(r["FWHM_R_each"]) == 5
        seen += 1
    assert seen == len(rows) == 22


def test_the_report_is_what_its_datasets_give_today(report_text):
    """Regenerated from the committed datasets, the report is the committed one, word for word:
    no number in it is typed or stale."""
    assert build_report(RESULTS) == report_text


def test_every_table_row_of_the_report_has_its_header_s_columns(report_text):
    """A '|' inside a cell (|ΔRI|) must be escaped, or Markdown splits the row."""
    tables, current = [], []
    for line in report_text.splitlines() + [""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            tables.append(current)
            current = []
    assert len(tables) >= 5
    for rows in tables:
        widths = {len(re.split(r"(?<!\\)\|", row)) for row in rows}
        assert len(widths) == 1, rows[0]


def test_every_figure_the_report_links_exists_and_is_a_png(report_text):
    links = figure_links(report_text)
    assert len(links) >= 15
    for link in links:
        path = REPORT.parent / link
        assert path.is_file(), link
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", link


def test_the_readme_links_the_report_and_shows_a_figure_in_its_first_screen():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    first_screen = "\n".join(readme.splitlines()[:40])
    figure = figure_links(first_screen)
    assert figure and (ROOT / figure[0]).is_file()
    assert "results/REPORT.md" in first_screen
    quick = readme.split("## Quick start", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    assert [line.split("#")[0].strip() for line in quick.strip().splitlines()] == \
        ["make table1 SCALE=small", "make test"]


# ------------------------------------------------------------------ effects
def _study(theta_by_value, status=None, dim="thickness", values=(1.0, 2.0)):
    """A minimal study Dataset whose stored numbers are the reduction of its rays."""
    from pipeline.report import reduce_rays

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
    from pipeline.analysis import fwhm

    assert float(ds["FWHM_R"][1]) == pytest.approx(fwhm(r[100:]))


def test_effects_over_woods_pair_the_woods_and_widen_with_them():
    """Two woods that scatter 1× and 3×: a value whose angles are all doubled is +100 % on every
    draw (paired), while each value's own interval spans the woods."""
    from pipeline.report import reduce_rays, per_ray

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
    from pipeline.report import method_rows

    rng = np.random.default_rng(9)
    r = np.degrees(np.arctan(0.02 * rng.standard_cauchy(300)))
    acc = _study([(r, r / 5), (r, r / 5)])
    for name in ("FWHM_R", "FWHM_L", "haze"):
        for b in ("lower", "upper"):
            acc[f"{name}_ci_{b}"] = acc[name]
    same = method_rows({"study-x": acc}, {"study-x": acc}, n_boot=20)
    assert same[0]["FWHM_R_change"] == (0.0, (0.0, 0.0))
    pap = _study([(2 * r, r / 5), (2 * r, r / 5)])
    for name in ("FWHM_R", "FWHM_L", "haze"):
        for b in ("lower", "upper"):
            pap[f"{name}_ci_{b}"] = pap[name]
    doubled = method_rows({"study-x": acc}, {"study-x": pap}, n_boot=20)
    assert doubled[0]["FWHM_R_change"][0] == pytest.approx(100.0, abs=1.0)
    assert doubled[0]["FWHM_L_change"][0] == 0.0 and doubled[0]["rays_common"] == 300


# ------------------------------------------------------------------ image quality
def test_image_quality_of_the_ideal_image_is_perfect_and_of_grey_is_nil():
    ideal = np.ones((20, 20))
    ideal[5:15, 8:12] = 0.0
    q = image_quality(ideal, ideal)
    assert q["rmse"] == 0.0 and q["contrast"] == q["ideal_contrast"] == 1.0
    grey = np.full_like(ideal, 0.6)
    assert image_quality(grey, ideal)["contrast"] == pytest.approx(0.0, abs=1e-12)
    half = 0.5 + 0.5 * (ideal - 0.5)  # levels 0.25 and 0.75: contrast 0.5
    assert image_quality(half, ideal)["contrast"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="one shape"):
        image_quality(ideal[:3], ideal)
    with pytest.raises(ValueError, match="both light"):
        image_quality(ideal, np.ones_like(ideal))


# ------------------------------------------------------------------ figure helpers
def test_structure_labels_name_what_differs_from_the_preset():
    base = build_params("birch")
    assert structure_label(base, base)[0] == "birch"
    slug, caption = structure_label(build_params("birch", overrides={"vessels": False,
                                                                     "fibre_diameter_um": 29}), base)
    assert slug == "fibre-diameter-29-no-vessels"
    assert caption == "birch, fibre diameter 29 µm, no vessels"


def test_sections_are_faces_of_one_block_of_the_wood():
    from pipeline.microstructure.model import generate_block
    from pipeline.params import Grid

    p = build_params("birch")
    sec = sections(p, 4, size_um=(20.0, 15.0, 10.0))
    assert sec["rt"].shape == (40, 30) and sec["lt"].shape == (30, 20) and sec["lr"].shape == (40, 20)
    block = generate_block(p, Grid((40, 30, 20), 0.5, (0.0, 0.0, 0.0)), (0, 0, 0), (40, 30, 20), seed=4)
    np.testing.assert_array_equal(sec["rt"], block[:, :, 0])
    np.testing.assert_array_equal(sec["lt"], block[-1])
    np.testing.assert_array_equal(sec["lr"], block[:, 0, :])


def _record(delta_ri, thickness_um=60.0):
    from dataclasses import asdict

    from pipeline.optics.tracer import settings_for

    return {"wood": build_params("birch").to_dict(), "seed": 2, "voxel_um": 0.5, "thickness_um": thickness_um,
            "beam_um": 40.0, "ri_polymer": 1.49, "delta_ri": delta_ri,
            "settings": asdict(settings_for("fast"))}


def test_trajectories_are_straight_in_index_matched_wood_and_bend_otherwise():
    pts, status = trajectories(_record(0.0), n_rays=5, every=1)
    assert np.all(status == 1)
    # Undeflected: every corner lies on the entry line, and the last is on the far face.
    np.testing.assert_allclose(pts[:, :, [0, 2]], pts[:, :1, [0, 2]].repeat(pts.shape[1], axis=1), atol=1e-9)
    np.testing.assert_allclose(pts[:, -1, 1], 60.0, atol=1e-9)
    pts, status = trajectories(_record(0.02), n_rays=5, every=1)
    assert np.all(status == 1)
    steps = np.diff(pts, axis=1)
    moved = np.linalg.norm(steps, axis=2) > 1e-12
    assert moved.sum() > 5 * 4  # several interfaces per ray
    # Between corners each ray is straight and moves forward (no reflection at ΔRI 0.02).
    assert np.all(steps[..., 1][moved] > 0)
    assert np.abs(pts[:, -1, [0, 2]] - pts[:, 0, [0, 2]]).max() > 0.05


# ------------------------------------------------------------------ commands
def test_figures_from_the_committed_datasets(tmp_path, capsys):
    code, out, err = run(capsys, "figures", "--results", str(RESULTS / "paper"), "--out", str(tmp_path),
                         "--only", "studies,histograms,camera")
    assert code == 0, err
    names = sorted(p.name for p in tmp_path.glob("*.png"))
    assert names == sorted([f"{n}.png" for n in TABLE1] + ["histograms.png", "camera.png"])
    assert "9 figures" in out


def test_report_and_figures_name_what_is_missing(tmp_path, capsys):
    code, _, err = run(capsys, "report", "--results", str(tmp_path), "--out", str(tmp_path / "R.md"))
    assert code == 2
    assert err.strip().count("\n") == 0
    assert "`results` must hold study-1.zarr (run `make table1 SCALE=paper` first)" in err
    assert not (tmp_path / "R.md").exists()
    code, _, err = run(capsys, "figures", "--results", str(tmp_path), "--out", str(tmp_path / "f"))
    assert code == 2 and "`results` must hold study-1.zarr" in err
    code, _, err = run(capsys, "figures", "--only", "studies,bars", "--out", str(tmp_path / "f"))
    assert code == 2 and "`only` must name some of" in err and "'studies,bars'" in err
    assert not (tmp_path / "f").exists()


def test_the_committed_datasets_are_the_paper_scale_table1_over_five_woods_by_both_methods():
    for name in TABLE1:
        with xr.open_zarr(RESULTS / "paper" / f"{name}.zarr") as ds:
            assert ds.attrs["scale"] == "paper" and ds.attrs["rays"] == 1000
            assert json.loads(ds.attrs["trace_settings"])["method"] == "accurate"
            assert ds.sizes["realisation"] == 5 and list(ds.seed_of_realisation.values) == [1, 2, 3, 4, 5]
            # Pooled intervals hold the woods: never narrower than the ray sampling's by much,
            # and wider for most values.
            both = (ds.FWHM_R_ci_upper - ds.FWHM_R_ci_lower).values
            rays = (ds.FWHM_R_ray_ci_upper - ds.FWHM_R_ray_ci_lower).values
            assert np.all(both > 0.6 * rays)
        with xr.open_zarr(RESULTS / "paper" / "paper-method" / f"{name}.zarr") as pm:
            assert pm.attrs["rays"] == 500 and json.loads(pm.attrs["trace_settings"])["method"] == "paper"
            assert list(pm.seed_of_realisation.values) == [1, 2, 3, 4, 5]
            assert json.loads(pm.attrs["scenes"])[0]["wood"] == json.loads(ds.attrs["scenes"])[0]["wood"]


def test_flat_fibre_ends_in_the_fibre_tip_studies_are_the_table1_woods_ray_for_ray():
    """λ = 0 is the wood of Table 1 (the same cache key): its rays are those of study 5-1,
    with and without ray cells, bit for bit; every tipped value is traced on the same seeds."""
    with xr.open_zarr(RESULTS / "paper" / "study-5-1.zarr") as ref:
        for name, ray_cells in zip(FIBRE_TIPS, (True, False)):
            with xr.open_zarr(RESULTS / "paper" / "fibre-tips" / f"{name}.zarr") as ds:
                assert list(ds.fibre_tip.values) == [0, 75, 150, 300]
                assert list(ds.seed_of_realisation.values) == [1, 2, 3, 4, 5]
                flat, same = ds.sel(fibre_tip=0), ref.sel(ray_cells=ray_cells)
                for var in ("theta_r", "theta_l", "status"):
                    np.testing.assert_array_equal(flat[var].values, same[var].values)
                # The tips change the wood: the rays of λ = 150 µm are not those of flat ends.
                assert not np.array_equal(ds.sel(fibre_tip=150).theta_l.values, flat.theta_l.values)


def test_every_fibre_tip_number_in_the_report_is_its_dataset_value(report_text):
    rows = fibre_tip_rows(RESULTS / "paper", n_boot=20)
    assert len(rows) == 8
    lines = [_cells(line) for line in report_text.splitlines()
             if line.startswith("| yes |") or line.startswith("| no |")]
    assert len(lines) == 8
    for cells, r in zip(lines, rows):
        assert cells[0] == ("yes" if r["ray_cells"] else "no") and _numbers(cells[1])[0] == r["tip_um"]
        for cell, key, nd in ((cells[3], "FWHM_R", 2), (cells[4], "FWHM_L", 2), (cells[5], "haze", 1)):
            np.testing.assert_allclose(_numbers(cell), [r[key], *r[f"{key}_ci"]], atol=0.51 * 10 ** -nd)
        assert (cells[6] == "reference") == (r["tip_um"] == 0)


def test_tip_wall_angle_is_the_lumen_half_width_over_the_tip_length():
    assert tip_wall_angle_deg(build_params("birch")) == 0.0
    # Lumen semi-axes 6.25 and 7.25 µm: a mean half-width of ~6.74 µm.
    for lam in (75.0, 150.0, 300.0):
        angle = tip_wall_angle_deg(build_params("birch", overrides={"fibre_tip_um": lam}))
        assert 6.6 / lam < np.radians(angle) < 6.9 / lam


def test_the_fine_voxel_run_is_study_5_1_wood_1_on_a_quarter_of_the_study_voxel():
    """The 0.125 µm run the report's convergence line reads: the same wood (seed 1) and beam as
    study 5-1's realisation 0, with only the traced voxel changed."""
    with xr.open_zarr(RESULTS / "paper" / "convergence" / "study-5-1-0.125um.zarr") as fine, \
            xr.open_zarr(RESULTS / "paper" / "study-5-1.zarr") as ref:
        assert json.loads(fine.attrs["trace_settings"])["refine"] == 4
        assert json.loads(ref.attrs["trace_settings"])["refine"] == 2
        assert list(fine.seed_of_realisation.values) == [1] and fine.sizes["ray"] == ref.sizes["ray"]
        for a, b in zip(json.loads(fine.attrs["scenes"]), json.loads(ref.attrs["scenes"])):
            assert {k: v for k, v in a["wood"].items() if k != "fibre_tip_um"} == b["wood"]
            assert (a["seed"], a["beam_um"], a["thickness_um"], a["delta_ri"]) == \
                (b["seed"], b["beam_um"], b["thickness_um"], b["delta_ri"])
