"""The tracer interface (pipeline.optics.trace): one call for every medium, in µm; the rules
that live once (methods, indices, the traced voxel, random-stream kinds, method versions)."""

import dataclasses
import math

import numpy as np
import pytest

from pipeline import rng, versions
from pipeline.optics.interface import TRANSMITTED
from pipeline.optics.lattice import honeycomb, tube_lattice
from pipeline.optics.media import wood_medium
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import METHODS, Optics, TraceSettings, settings_for, traced_voxel_um
from pipeline.optics.sources import ArraySource, WoodSource
from pipeline.optics.trace import next_rays, trace
from pipeline.optics.wood_surface import WoodSurface
from pipeline.params import ParameterError, build_params, check_voxel

BIRCH = build_params("birch")


@pytest.mark.parametrize("method", ["paper", "fast", "accurate"])
@pytest.mark.parametrize("voxel_um", [0.5, 0.3])
def test_a_clear_volume_is_crossed_straight_with_positions_and_paths_in_um(method, voxel_um):
    """Polymer only: every ray leaves at origin + thickness · d / d_T, after thickness / d_T of path,
    whatever the voxel size (the interface converts µm both ways)."""
    n_t = 40
    medium = ArraySource(np.zeros((200, n_t, 200), np.uint8), voxel_um=voxel_um)
    side = 200 * voxel_um
    d = np.array([0.1, 1.0, -0.05])
    beam = square_beam(30, side / 4, (side / 2, side / 2), seed=2, direction=d)
    res = trace(medium, beam, Optics(1.55, 1.49), settings_for(method, refine=1))
    u = d / np.linalg.norm(d)
    thickness = n_t * voxel_um
    assert np.all(res.status == TRANSMITTED) and np.all(res.events == 0)
    np.testing.assert_allclose(res.position, beam.origins + thickness * u / u[1], atol=1e-9)
    np.testing.assert_allclose(res.path, thickness / u[1], rtol=1e-12)
    assert res.diagnostics["traced_voxel_um"] == voxel_um


def test_index_matched_exact_lattice_counts_every_phase_change_of_the_straight_line():
    """At ΔRI = 0 the surface medium's rays go straight, and each meets exactly the phase changes
    of its line, counted independently by sampling the lattice's phase every 1/64 µm."""
    lat = tube_lattice(14.5, 6.5, 2.0, jitter=0.15, seed=3)
    thickness = 60.0
    d = np.array([0.3, 1.0, 0.2])
    u = d / np.linalg.norm(d)
    beam = square_beam(40, 100.0, seed=5, direction=d)
    res = trace(lat.slab(thickness), beam, Optics(1.5, 1.5), settings_for("exact"))
    np.testing.assert_allclose(res.position, beam.origins + thickness * u / u[1], atol=1e-6)
    np.testing.assert_allclose(res.path, thickness / u[1], rtol=1e-9, atol=1e-6)
    s = np.arange(0.0, thickness / u[1], 1.0 / 64)
    for k in range(len(beam.ray_ids)):
        r = beam.origins[k, 0] + s * u[0]
        t = s * u[1]
        phases = np.array([lat.phase([ri], [ti])[0, 0] for ri, ti in zip(r, t)])
        assert res.events[k] == np.count_nonzero(np.diff(phases.astype(int))), k


@pytest.mark.parametrize("medium_kind", ["surfaces", "voxels"])
def test_a_method_that_does_not_trace_the_medium_is_one_line_naming_what_does(medium_kind):
    lat = honeycomb(14.0, 2.0)
    medium = lat.slab(20.0) if medium_kind == "surfaces" else lat.source(thickness_um=20.0, voxel_um=0.5)
    wrong = "fast" if medium_kind == "surfaces" else "exact"
    with pytest.raises(ParameterError, match=f"`method` '{wrong}' traces .* this medium offers {medium_kind}: use"):
        trace(medium, square_beam(3, 10.0, seed=1), Optics(1.5, 1.49), settings_for(wrong))


def test_generated_wood_is_the_medium_the_method_traces():
    s = settings_for("accurate")
    wood = wood_medium(BIRCH, seed=2, thickness_um=30.0, voxel_um=0.5, settings=s)
    assert isinstance(wood, WoodSource) and wood.voxel_um == traced_voxel_um(0.5, s) == 0.25
    surfaces = wood_medium(BIRCH, seed=2, thickness_um=30.0, voxel_um=0.5, settings=settings_for("exact"))
    assert isinstance(surfaces, WoodSurface) and surfaces.thickness_um == 30.0


def test_voxel_settings_belong_to_voxel_methods_and_old_flat_records_still_read():
    assert settings_for("fast", refine=3, step_vox=1.0).voxel.refine == 3
    assert settings_for("exact").voxel is None and settings_for("exact").refine == 1
    with pytest.raises(ParameterError, match="`refine` applies to the voxel methods"):
        settings_for("exact", refine=2)
    with pytest.raises(ParameterError, match="`refine` must be an integer in \\[1, 8\\]"):
        settings_for("accurate", refine=0)
    with pytest.raises(ParameterError, match="`method` must be one of paper, fast, accurate, exact"):
        settings_for("best")
    flat = {"method": "accurate", "step_vox": 2.0, "svm_box": 6, "sigma_vox": 2.0, "radius_vox": 6.0,
            "newton": 3, "refit": 1, "fresnel": False, "max_events": 2000, "exit": "internal", "refine": 2}
    assert TraceSettings.from_dict(flat) == settings_for("accurate")
    assert TraceSettings.from_dict(settings_for("paper").to_dict()) == settings_for("paper")


def test_the_committed_datasets_read_back_the_voxel_they_were_traced_on():
    import json

    import xarray as xr

    from pipeline.result_sets import traced_voxel_um_of

    with xr.open_zarr("results/paper/accurate/study-1.zarr") as ds:
        scenes = json.loads(ds.attrs["scenes"])
    assert {traced_voxel_um_of(s) for s in scenes} == {0.25}  # accurate: 0.5 µm scenes on 0.25 µm voxels
    with xr.open_zarr("results/paper/study-1.zarr") as ds:
        assert json.loads(ds.attrs["trace_settings"])["method"] == "exact"
        assert all(s["settings"]["voxel"] is None for s in json.loads(ds.attrs["scenes"]))


@pytest.mark.parametrize("n_wall, n_poly", [(3.2, 1.49), (1.49, 0.9), (float("nan"), 1.5)])
def test_refractive_indices_have_one_rule(n_wall, n_poly):
    with pytest.raises(ParameterError, match="refractive indices must be finite|must give indices in \\[1, 3\\]"):
        Optics(n_wall, n_poly).validate()
    assert Optics.of_delta(1.49, 0.01).n_wall == 1.49 + 0.01


def test_voxel_must_be_at_most_half_the_wall():
    assert check_voxel(1.0, BIRCH) == 1.0
    with pytest.raises(ParameterError, match="`voxel_um` must be <= wall_thickness_um/2 = 1 µm"):
        check_voxel(1.01, BIRCH)


def test_every_random_stream_kind_is_registered_once():
    kinds = rng.kinds()
    assert len(set(kinds.values())) == len(kinds)
    assert {"BEAM", "FRESNEL", "APERTURE", "LATTICE_SITE", "NODE_R"} <= set(kinds)


def test_every_method_has_its_own_version_in_the_keys_of_its_rays(tmp_path, monkeypatch):
    from pipeline.study.plan import plan_study
    from pipeline.study.spec import load_study

    text = ("preset: birch\nseed: 1\nrealisations: 1\nrays: 20\nbeam_um: 20\nthickness_mm: 0.02\n"
            "trace: {{method: {m}}}\nvary: {{parameter: delta_ri, values: [0.01]}}\n")
    keys = {}
    for m in ("fast", "accurate"):
        (tmp_path / f"{m}.yaml").write_text(text.format(m=m))
        keys[m] = lambda m=m: {s.key for s in plan_study(load_study(tmp_path / f"{m}.yaml"), tmp_path).shards}
    before = {m: f() for m, f in keys.items()}
    monkeypatch.setitem(versions.TRACERS, "fast", "changed")
    after = {m: f() for m, f in keys.items()}
    assert after["accurate"] == before["accurate"] and after["fast"].isdisjoint(before["fast"])


def test_a_surface_methods_rays_are_keyed_without_voxels():
    from pipeline.study.plan import rays_record
    from pipeline.study.spec import load_study

    scene = load_study("studies/table1/study-2.yaml").scenes[0]
    voxel = rays_record(dataclasses.replace(scene, settings=settings_for("accurate")), "somekey")
    surface = rays_record(dataclasses.replace(scene, settings=settings_for("exact")), None)

    def names(d):
        return {k for k, v in d.items()} | {n for v in d.values() if isinstance(v, dict) for n in names(v)}

    assert {"thickness_vox", "width_vox", "micro"} <= names(voxel)
    assert not any(n.endswith("_vox") or n in ("voxel_um", "micro") for n in names(surface))
    assert surface["settings"]["voxel"] is None and surface["thickness_um"] == scene.thickness_um
    assert surface["tracer"] == versions.tracer("exact") and "micro" not in surface


def test_trace_to_target_doubles_up_to_the_cap():
    from pipeline.analysis import Target

    t = Target(haze=0.01, max_rays=1000)
    wide = {"haze_ci": [0.1, 0.3], "fwhm_r_ci_deg": [1, 2], "fwhm_l_ci_deg": [1, 2]}
    narrow = {"haze_ci": [0.199, 0.201], "fwhm_r_ci_deg": [1, 2], "fwhm_l_ci_deg": [1, 2]}
    assert next_rays(t, 300, wide) == 600 and next_rays(t, 600, wide) == 1000
    assert next_rays(t, 1000, wide) is None and next_rays(t, 300, narrow) is None and next_rays(None, 5, wide) is None


def test_methods_name_their_medium():
    assert set(METHODS.values()) == {"voxels", "surfaces", "fields"} and METHODS["exact"] == "surfaces"
    assert METHODS["iso"] == "fields"
    assert math.isfinite(traced_voxel_um(0.5, settings_for("exact")))


@pytest.mark.parametrize("method", ["exact", "fast"])
def test_the_faces_are_the_same_for_every_medium(method):
    """The faces are handled once (optics/faces.py), whatever marches the interior: through
    index-matched birch a beam from air leaves into air along its own direction; a ray that meets
    the exit face beyond the critical angle is totally reflected there; a ray in a wall leaves with
    the wall's index (its `incident` too), and a ray entering outside a finite volume leaves
    through a side."""
    from pipeline.optics.interface import SIDE, TIR_EXIT

    s = dataclasses.replace(settings_for(method), exit="air")
    wood = wood_medium(BIRCH, seed=2, thickness_um=20.0, voxel_um=0.5, settings=s)
    air = np.array([0.4, 1.0, -0.3]) / np.linalg.norm([0.4, 1.0, -0.3])
    beam = square_beam(40, 30.0, seed=3, direction=air)
    res = trace(wood, beam, Optics(1.5, 1.5, n_outside=1.0), s)
    assert np.all(res.status == TRANSMITTED)
    np.testing.assert_allclose(res.exit_direction, np.broadcast_to(air, (40, 3)), atol=1e-12)
    np.testing.assert_allclose(res.incident, res.exit_direction, atol=1e-12)
    steep = np.array([math.tan(math.radians(50.0)), 1.0, 0.0])  # 50° inside n = 1.5: sin 0.77 · 1.5 > 1
    res = trace(wood, square_beam(10, 30.0, seed=3, direction=steep), Optics(1.5, 1.5), s)
    assert np.all(res.status == TIR_EXIT) and np.all(np.isnan(res.incident))
    if method == "fast":  # a finite volume: a ray entering beside it leaves through a side
        vol = ArraySource(np.zeros((20, 10, 20), np.uint8), voxel_um=1.0)
        res = trace(vol, square_beam(10, 5.0, (40.0, 10.0), seed=1), Optics(1.5, 1.5), s)
        assert np.all(res.status == SIDE) and np.all(res.events == 0)
