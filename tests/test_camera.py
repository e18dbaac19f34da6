"""Virtual camera (docs/methods.md#virtual-camera): thin-lens optics, sheets, objects, cached rendering on a LocalCluster."""

import numpy as np
import pytest
import xarray as xr
from PIL import Image

from pipeline.camera.lens import Camera, Sheet, aperture_samples, ideal_image, render_rows, strata
from pipeline.camera.dataset import edge_widths, write_outputs
from pipeline.camera.graph import compute
from pipeline.camera.plan import plan_camera
from pipeline.camera.tasks import load_entry
from pipeline.camera.scene import load_camera
from pipeline.camera.targets import make_target
from pipeline.cli import main
from pipeline.optics.media import wood_medium
from pipeline.optics.settings import settings_for
from pipeline.params import ParameterError, build_params

BIRCH = build_params("birch")


def sheet(**kw) -> Sheet:
    base = dict(wood=BIRCH, seed=1, voxel_um=0.5, thickness_um=50.0, width_um=1500.0,
                length_um=1000.0, ri_polymer=1.53, delta_ri=0.01, gap_um=2.0, r_axis="x")
    base.update(kw)
    return Sheet(**base).validate()


def render(camera, sh, target, method="fast"):
    settings = settings_for(method)
    medium = None if sh is None else wood_medium(sh.wood, seed=sh.seed, thickness_um=sh.thickness_um,
                                                 voxel_um=sh.voxel_um, settings=settings)
    return render_rows(camera, sh, target, np.arange(camera.pixels[0]), settings=settings, medium=medium)


# ---------------------------------------------------------------------- optics of the camera
def test_thin_lens_of_the_three_figure_5_configurations():
    c1 = Camera(6.25, 162.5, 1.0).validate()
    c3 = Camera(12.5, 137.5, 1.0).validate()
    assert c1.image_mm == pytest.approx(6.5) and c1.magnification == pytest.approx(0.04)
    assert c3.image_mm == pytest.approx(13.75) and c3.magnification == pytest.approx(0.1)
    # Pixel centres 25 pitches from the axis look 25 × 12.5 µm away at m = 0.04.
    x, y = c1.object_points(np.array([0, 50]))
    assert x[0, 0] == pytest.approx(-0.3125) and x[0, -1] == pytest.approx(0.3125)
    assert y[0, 0] == pytest.approx(0.3125) and y[1, 0] == pytest.approx(-0.3125)  # row 0 at the top
    with pytest.raises(ParameterError, match="objective_mm` must be > focal_mm"):
        Camera(10.0, 8.0, 1.0).validate()


def test_aperture_samples_fill_equal_area_strata_and_rotate_per_pixel():
    assert strata(200) == (10, 20) and strata(16) == (2, 8) and strata(7) == (1, 7)
    pts = aperture_samples(np.arange(50), 200, seed=3)
    assert pts.shape == (50, 200, 2)
    r2 = np.sum(pts**2, axis=-1)
    assert r2.max() < 1.0
    # Sample s lies in ring s // 20: r² in [ring/10, (ring+1)/10).
    ring = np.arange(200) // 20
    assert np.all((r2 >= ring / 10) & (r2 < (ring + 1) / 10))
    # Stratified: the mean point of 200 samples is much closer to the centre than random sampling's.
    assert np.abs(pts.mean(axis=1)).max() < 0.02
    # Each pixel has its own rotation; the same ids give the same points.
    assert not np.allclose(pts[0], pts[1])
    assert np.array_equal(pts, aperture_samples(np.arange(50), 200, seed=3))
    assert np.array_equal(pts[7], aperture_samples(np.array([7]), 200, seed=3)[0])


def test_target_lookup_is_bilinear_and_background_beyond_the_card():
    t = make_target({"kind": "square", "size_mm": 0.2, "fraction": 0.5})
    n = t.raster.shape[0]
    centres = (np.arange(n) + 0.5) / n * 0.2 - 0.1
    assert np.allclose(t.lookup(centres, np.full(n, centres[n // 2])), t.raster[n // 2 - 1])
    mid = 0.5 * (centres[10] + centres[11])
    assert t.lookup(np.array([mid]), np.array([0.0]))[0] == pytest.approx(
        0.5 * (t.raster[n // 2, 10] + t.raster[n // 2, 11]))
    assert np.all(t.lookup(np.array([0.5, -0.3, 0.0]), np.array([0.0, 0.0, 0.2])) == 1.0)
    assert t.lookup(np.array([0.0]), np.array([0.0]))[0] == 0.0  # the dark square's centre
    g = make_target({"kind": "char", "char": "T", "size_mm": 0.5, "background": 0.3})
    assert g.lookup(np.array([0.3]), np.array([0.3]))[0] == pytest.approx(0.3)


def test_png_objects_keep_their_pixels_and_physical_size(tmp_path):
    raster = np.zeros((20, 40), np.uint8)
    raster[:, 20:] = 255
    Image.fromarray(raster).save(tmp_path / "half.png")
    t = make_target({"kind": "png", "path": "half.png", "size_mm": [0.4, 0.2]}, base=tmp_path)
    assert t.raster.shape == (20, 40) and t.width_mm == 0.4 and t.height_mm == 0.2
    assert t.lookup(np.array([-0.1, 0.1]), np.array([0.0, 0.0])).tolist() == [0.0, 1.0]
    with pytest.raises(ParameterError, match="object.path` must be a readable PNG"):
        make_target({"kind": "png", "path": "missing.png", "size_mm": 0.1}, base=tmp_path)


def test_without_a_sheet_the_image_is_the_object_scaled_by_the_magnification():
    # A 0.25 mm dark square at m = 0.04 is 10 µm on the sensor: 20 pixels of 0.5 µm.
    for focal, objective, side in [(6.25, 162.5, 0.25), (12.5, 137.5, 0.1)]:
        cam = Camera(focal, objective, 1.0, (41, 41), 0.5, 8).validate()
        t = make_target({"kind": "square", "size_mm": side * 2, "fraction": 0.5})
        img = render(cam, None, t).image
        dark = 1.0 - img
        expected = side * cam.magnification / 0.5e-3
        assert expected == pytest.approx(20.0)
        assert dark[20].sum() == pytest.approx(expected, abs=0.05)
        assert dark[:, 20].sum() == pytest.approx(expected, abs=0.05)
        assert np.allclose(img, ideal_image(cam, t), rtol=0, atol=1e-9)
    # Upright: the bar of the T is in the top rows.
    cam = Camera(6.25, 162.5, 1.0, (51, 51), 0.5, 4).validate()
    img = render(cam, None, make_target({"kind": "char", "char": "T", "size_mm": 0.5})).image
    assert (1 - img[12]).sum() > 3 * (1 - img[38]).sum() > 0


def test_index_matched_sheet_gives_the_ideal_thin_lens_image():
    """ΔRI = 0: the sheet is a plain slab of index 1.53, which at these apertures
    (half-angle 3 mrad) only shifts the focus by 0.17 mm·3 mrad ≈ 0.5 µm on the
    object, a twentieth of an object-plane pixel; tolerance 0.02 of the grey range."""
    cam = Camera(6.25, 162.5, 1.0, (31, 31), 0.5, 16).validate()
    t = make_target({"kind": "char", "char": "F", "size_mm": 0.35})
    matched = render(cam, sheet(delta_ri=0.0, thickness_um=100.0), t)
    ideal = ideal_image(cam, t)
    assert matched.interfaces > 10 * matched.image.size * cam.samples  # it did cross the cell walls
    assert matched.lost.sum() == 0
    assert np.abs(matched.image - ideal).max() < 0.02
    # Not a test that cannot fail: the same sheet at ΔRI = 0.03 departs from the ideal image.
    scattering = render(cam, sheet(delta_ri=0.03, thickness_um=100.0), t)
    assert np.abs(scattering.image - ideal).max() > 0.2


def test_blur_is_anisotropic_and_wider_along_the_woods_R():
    """Edge-spread widths (25-75 %) of a dark quadrant seen through the Figure 5 sheet
    material (1.54 / 1.53, 0.1 mm, 30 µm gap) at m = 0.5 (1 µm per pixel on the object).
    Measured: 5 µm along R against 1 µm (the ideal image's) along L, both orientations."""
    cam = Camera(10.0, 30.0, 1.0, (41, 41), 0.5, 16).validate()
    t = make_target({"kind": "quadrant", "size_mm": 0.2})
    sharp = edge_widths(ideal_image(cam, t), 1.0)
    assert sharp == {"x": 1.0, "y": 1.0}
    widths = {}
    for axis in ("x", "y"):
        sh = sheet(thickness_um=100.0, gap_um=30.0, r_axis=axis)
        widths[axis] = edge_widths(render(cam, sh, t).image, 1.0)
    print("edge widths (µm on the object):", {"ideal": sharp, **widths})
    # R along x: the x edge blurs, the y edge stays as sharp as the ideal image's.
    assert widths["x"]["x"] >= 3.0 * widths["x"]["y"] and widths["x"]["y"] <= sharp["y"] + 1.0
    # Turn the sheet a quarter turn (R along y): the wide blur follows R.
    assert widths["y"]["y"] >= 3.0 * widths["y"]["x"] and widths["y"]["x"] <= sharp["x"] + 1.0


# ---------------------------------------------------------------------- camera files and the pipeline
CAMERA_FILE = """\
title: test camera
sheet: {thickness_mm: 0.1, ri_polymer: 1.53, delta_ri: 0.03}
camera: {sensor_px: [9, 11], samples: 40, seed: 2}
trace: {method: fast}
images:
  near:
    focal_mm: 10
    objective_mm: 30
    aperture_mm: 1
    gap_um: 5
    object: {kind: star, n: 8, size_mm: 0.012}
  open:
    focal_mm: 10
    objective_mm: 30
    aperture_mm: 1
    object: {kind: bars, n: 3, size_mm: 0.012}
    sheet: none
"""


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as c:
        yield c


def test_camera_file_renders_on_a_cluster_and_caches_its_images(tmp_path, client):
    path = tmp_path / "cam.yaml"
    path.write_text(CAMERA_FILE)
    study = load_camera(path, scale="small")  # small: 4 samples per pixel, 20 µm sheet
    assert study.images[0].camera.samples == 4 and study.images[0].sheet.thickness_um == 20.0
    study = load_camera(path)
    assert study.images[1].sheet is None and study.images[0].sheet.gap_um == 5.0
    cache = tmp_path / "cache"
    entries = plan_camera(study, cache)
    report = compute(entries, client, cache, rows_per_task=2)
    assert report == {"images": 2, "row_tasks": 10, "rows_cached": 0, "rays": 2 * 9 * 11 * 40}
    assert not list((cache / "camera-rows").glob("*"))  # the images hold their rows now
    entries = plan_camera(study, cache)
    assert all(e.cached for e in entries)
    assert compute(entries, client, cache)["images"] == 0
    # The sheet's wood went to the shared chunk store; the images equal a direct render.
    assert list((cache / "micro").glob("*.zarr"))
    near = load_entry(entries[0])
    direct = render(study.images[0].camera, study.images[0].sheet, study.images[0].target)
    assert np.array_equal(near["image"], direct.image) and np.array_equal(near["lost"], direct.lost)
    # Row blocks of another size give the same image.
    other = plan_camera(study, tmp_path / "cache2")
    compute(other, client, tmp_path / "cache2", rows_per_task=4)
    assert np.array_equal(load_entry(other[0])["image"], near["image"])

    results = tmp_path / "results"
    paths = write_outputs(study, entries, results)
    ds = xr.open_zarr(paths[0], consolidated=False)
    assert ds["image"].dims == ("config", "row", "col") and ds["image"].shape == (2, 9, 11)
    assert list(ds["config"].values) == ["near", "open"]
    assert ds["magnification"].values.tolist() == pytest.approx([0.5, 0.5])
    assert np.isnan(ds["delta_ri"].values[1]) and ds["delta_ri"].values[0] == pytest.approx(0.03)
    assert np.allclose(ds["image"].values[1], ds["ideal"].values[1], atol=1e-6)
    assert "images:" in ds.attrs["camera_yaml"] and ds["gap_um"].attrs["units"] == "um"
    with Image.open(results / "cam-near.png") as im:
        assert im.size == (11, 9)
    assert (results / "cam-open-object.png").exists() and (results / "cam.png").exists()


def test_an_image_that_stopped_part_way_keeps_its_row_blocks_and_the_rerun_renders_only_the_rest(
        tmp_path, client):
    import os

    from pipeline.cache import FAULT_ENV
    from pipeline.camera.plan import plan_blocks
    from pipeline.runlog import RunFailed

    path = tmp_path / "cam.yaml"
    path.write_text(CAMERA_FILE)
    study = load_camera(path)
    cache = tmp_path / "cache"
    client.run(lambda: os.environ.update({FAULT_ENV: "camera:0"}))  # the image's own entry cannot be written
    try:
        with pytest.raises(RunFailed) as failed:
            compute(plan_camera(study, cache)[:1], client, cache)  # blocks of 3 rows
    finally:
        client.run(lambda: os.environ.pop(FAULT_ENV, None))
    assert "no space left writing" in str(failed.value) and "/camera/" in str(failed.value)
    entry = plan_camera(study, cache)[0]
    assert not entry.cached and not entry.path.exists()
    blocks = plan_blocks(entry, cache)
    assert [(b.lo, b.hi) for b in blocks] == [(0, 3), (3, 6), (6, 9)]
    assert all(b.cached for b in blocks)
    from pipeline.inventory import keys_in_use
    assert {b.key for b in blocks} <= keys_in_use([path], ["paper"], cache)  # `cache gc` keeps them
    blocks[1].path.write_bytes(blocks[1].path.read_bytes()[:-40])  # one damaged: rendered again
    report = compute([entry], client, cache)
    assert report == {"images": 1, "row_tasks": 1, "rows_cached": 2, "rays": 3 * 11 * 40}
    image = load_entry(plan_camera(study, cache)[0])
    direct = render(study.images[0].camera, study.images[0].sheet, study.images[0].target)
    assert np.array_equal(image["image"], direct.image) and np.array_equal(image["lost"], direct.lost)
    assert not list((cache / "camera-rows").glob("*"))


@pytest.mark.parametrize("text, needle", [
    ("lens: 3\n", "line 1: unknown key `lens`"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 5\n    aperture_mm: 1\n    object: {kind: square, size_mm: 1}\n",
     "line 2: `images.a`: `objective_mm` must be > focal_mm"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n    gap_um: 3\n"
     "    zoom: 2\n    object: {kind: square, size_mm: 1}\n", "line 7: unknown key `images.a.zoom`"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n"
     "    object: {kind: glyph, size_mm: 1}\n", "line 6: `images.a.object.kind` must be one of"),
    ("sheet:\n  r_axis: z\nimages:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n"
     "    object: {kind: square, size_mm: 1}\n", "line 2: `sheet.r_axis` must be x or y"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n"
     "    sheet: {delta_ri: high}\n    object: {kind: square, size_mm: 1}\n",
     "line 6: `images.a.sheet.delta_ri` must be a number"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n"
     "    sheet: {delta_ri: 2}\n    object: {kind: square, size_mm: 1}\n",
     "line 6: `delta_ri` and `ri_polymer` must give indices in [1, 3]"),
    ("images:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n    aperture_mm: 1\n"
     "    sheet: {ri_wall: 1.54}\n    object: {kind: square, size_mm: 1}\n",
     "line 6: `images.a.sheet.ri_wall` is given as `delta_ri`"),
    ("images:\n  a:\n    focal_mm: 0.2\n    objective_mm: 0.4\n    aperture_mm: 0.1\n"
     "    object: {kind: square, size_mm: 1}\n", "line 2: `images.a`: the sheet must lie between the lens"),
    ("trace:\n  method: fast\n  refine: 0\nimages:\n  a:\n    focal_mm: 10\n    objective_mm: 30\n"
     "    aperture_mm: 1\n    object: {kind: square, size_mm: 1}\n", "line 3: `trace.refine` must be"),
])
def test_bad_camera_files_name_file_line_and_field(tmp_path, text, needle, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(text if "images" in text else text + CAMERA_FILE.split("title: test camera\n")[1])
    with pytest.raises(ParameterError, match="bad.yaml") as err:
        load_camera(path)
    assert needle in str(err.value)
    assert main(["camera", str(path), "--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r")]) == 2
    msg = capsys.readouterr().err.strip()
    assert msg.count("\n") == 0 and "bad.yaml" in msg
    assert not (tmp_path / "c").exists() and not (tmp_path / "r").exists()


def test_figure_5_file_holds_the_papers_three_configurations_and_a_control():
    study = load_camera("studies/camera/figure5.yaml")
    got = {c.name: (c.camera.focal_mm, c.camera.objective_mm, c.camera.aperture_mm, c.sheet.gap_um,
                    c.target.width_mm) for c in study.images}
    assert got == {"image-1": (6.25, 162.5, 1.0, 2.0, 0.5), "image-2": (6.25, 162.5, 1.0, 100.0, 0.5),
                   "image-3": (12.5, 137.5, 1.0, 2.0, 0.167), "control-dri0": (6.25, 162.5, 1.0, 2.0, 0.5)}
    for c in study.images:
        assert c.camera.pixels == (51, 51) and c.camera.pitch_um == 0.5 and c.camera.samples == 200
        assert (c.sheet.thickness_um, c.sheet.width_um, c.sheet.length_um) == (500.0, 1500.0, 1000.0)
        assert c.sheet.ri_polymer == 1.53
    assert [c.sheet.optics.n_wall for c in study.images] == [1.54, 1.54, 1.54, 1.53]


def test_method_replaces_the_files_trace_method_and_a_bad_one_is_one_line(tmp_path, capsys):
    """`--method` traces every image's sheet with another method (its images are other cache
    entries); a method that is not one is refused before anything is made."""
    for method in ("fast", "accurate"):
        study = load_camera("studies/camera/figure5.yaml", method=method)
        assert {c.settings.method for c in study.images} == {method}
        assert all(c.settings.exit == "air" for c in study.images)
    assert {c.settings.method for c in load_camera("studies/camera/figure5.yaml").images} == {"exact"}
    keys = {m: [e.key for e in plan_camera(load_camera("studies/camera/figure5.yaml", method=m), tmp_path / "c")]
            for m in ("fast", "exact")}
    assert not set(keys["fast"]) & set(keys["exact"])
    assert main(["camera", "studies/camera/figure5.yaml", "--method", "voxels", "--cache", str(tmp_path / "c"),
                 "--results", str(tmp_path / "r")]) == 2
    msg = capsys.readouterr().err.strip()
    assert msg.count("\n") == 0 and "`method` must be one of" in msg and "'voxels'" in msg
    assert not (tmp_path / "r").exists()


def test_camera_command_writes_results_and_a_rerun_renders_nothing(tmp_path, capsys):
    path = tmp_path / "cam.yaml"
    path.write_text(CAMERA_FILE)
    args = ["camera", str(path), "--scale", "small", "--threads", "2", "--cache", str(tmp_path / "c"),
            "--results", str(tmp_path / "r")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "near: f 10 mm, m 0.5, ΔRI 0.03, gap 5 µm" in out and "open: f 10 mm, m 0.5, no sheet" in out
    assert main(args + ["--dry-run"]) == 0
    assert capsys.readouterr().out.count(": cached (") == 2
    before = (tmp_path / "r" / "cam.zarr" / "zarr.json").stat().st_mtime_ns
    assert main(args) == 0
    assert "dashboard" not in capsys.readouterr().err  # no cluster was started
    ds = xr.open_zarr(tmp_path / "r" / "cam.zarr", consolidated=False)
    assert ds.attrs["scale"] == "small" and ds["image"].shape == (2, 9, 11)
    assert (tmp_path / "r" / "cam.zarr" / "zarr.json").stat().st_mtime_ns == before  # kept as it was


def test_exact_renders_through_the_woods_own_surfaces():
    """`exact` behind the camera: index matched, the ideal image; at ΔRI = 0.03, blurred."""
    cam = Camera(6.25, 162.5, 1.0, (9, 9), 1.7, 4).validate()
    t = make_target({"kind": "char", "char": "F", "size_mm": 0.35})
    matched = render(cam, sheet(delta_ri=0.0, thickness_um=60.0), t, method="exact")
    assert matched.interfaces > 5 * matched.image.size * cam.samples and matched.lost.sum() == 0
    assert np.abs(matched.image - ideal_image(cam, t)).max() < 0.02
    scattering = render(cam, sheet(delta_ri=0.03, thickness_um=60.0), t, method="exact")
    assert np.abs(scattering.image - ideal_image(cam, t)).max() > 0.1
