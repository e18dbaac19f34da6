"""Cost estimates checked before any work starts (pipeline/limits.py): what a trace or study needs,
in CPU, memory and disk; a refusal in one line that says what to do; readable sizes and times;
the CPU threshold from TWRAY_CONFIRM_CPU_HOURS."""

import dataclasses
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import limits
from pipeline.analysis import Target
from pipeline.limits import (CONFIRM_ENV, Estimate, camera_estimate, check, confirm_hours, free_disk, hours,
                             machine_memory, size, study_estimate, trace_estimate, wood_voxels)
from pipeline.optics.settings import settings_for
from pipeline.params import ParameterError, build_params
from pipeline.study.spec import Scene

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_estimates as E  # noqa: E402

BIRCH = build_params("birch")  # fibre pitch 14.5 µm
FIT = "use fewer rays or a thinner sample"


@pytest.fixture(autouse=True)
def default_threshold(monkeypatch):
    monkeypatch.delenv(CONFIRM_ENV, raising=False)


# ------------------------------------------------------------------ words
@pytest.mark.parametrize("n, text", [(0, "0 B"), (999, "999 B"), (1000, "1 kB"), (1536, "1.54 kB"),
                                     (2 ** 30, "1.07 GB"), (5e12, "5 TB"), (5e15, "5 PB"), (2e18, "2e+03 PB")])
def test_sizes_are_decimal_units_to_three_figures(n, text):
    assert size(n) == text


@pytest.mark.parametrize("cpu_s, text", [(0, "0 CPU-s"), (119.4, "119 CPU-s"), (120, "2 CPU-min"),
                                         (7199, "120 CPU-min"), (7200, "2 CPU-h"), (3600 * 1234.5, "1.23e+03 CPU-h")])
def test_cpu_times_are_seconds_minutes_or_hours(cpu_s, text):
    assert hours(cpu_s) == text


def test_estimates_add_time_and_disk_and_keep_the_larger_memory():
    """Steps run one after the other: their times and disks add, the peak memory is the larger."""
    total = Estimate(30.0, 2e9, 1e6) + Estimate(90.0, 5e8, 4e6)
    assert (total.cpu_s, total.memory, total.disk) == (120.0, 2e9, 5e6)
    assert total.text() == "~2 CPU-min of CPU, 2 GB of memory, 5 MB of disk"
    assert Estimate(90, 2 ** 30, 0).text() == "~90 CPU-s of CPU, 1.07 GB of memory, 0 B of disk"


def test_machine_memory_is_the_physical_memory_the_kernel_reports():
    with open("/proc/meminfo") as f:
        total_kb = next(int(line.split()[1]) for line in f if line.startswith("MemTotal:"))
    assert machine_memory() == pytest.approx(total_kb * 1024, rel=0.01)


def test_free_disk_of_a_path_not_made_yet_is_that_of_its_nearest_folder(tmp_path):
    deep = tmp_path / "not" / "made" / "yet.zarr"
    assert free_disk(deep) == pytest.approx(shutil.disk_usage(tmp_path).free, rel=0.01)
    assert not (tmp_path / "not").exists()


# ------------------------------------------------------------------ the threshold
@pytest.mark.parametrize("text, value", [(None, 2.0), ("0.5", 0.5), ("0", 0.0), ("24", 24.0)])
def test_the_cpu_threshold_is_two_hours_unless_the_environment_says(monkeypatch, text, value):
    if text is not None:
        monkeypatch.setenv(CONFIRM_ENV, text)
    assert confirm_hours() == value


@pytest.mark.parametrize("text", ["lots", "-1", "nan", "inf", ""])
def test_a_threshold_that_is_not_a_number_of_hours_is_refused_by_name(monkeypatch, text):
    monkeypatch.setenv(CONFIRM_ENV, text)
    with pytest.raises(ParameterError) as err:
        confirm_hours()
    assert str(err.value) == f"`TWRAY_CONFIRM_CPU_HOURS` must be a number of CPU-hours >= 0, got {text!r}"


# ------------------------------------------------------------------ check
def _refusal(est, **kw) -> str:
    with pytest.raises(ParameterError) as err:
        check(est, what="`trace`", fit=FIT, **kw)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"`trace` needs {est.text()}") and msg.endswith(f"; {FIT}")
    return msg


def test_more_cpu_than_the_threshold_needs_yes(monkeypatch):
    check(Estimate(cpu_s=7200.0), what="`trace`", yes=False)  # exactly 2 CPU-hours: runs
    msg = _refusal(Estimate(cpu_s=7201.0), yes=False)
    assert "above TWRAY_CONFIRM_CPU_HOURS=2 CPU-hours: add --yes (with make: YES=1) to run it" in msg
    check(Estimate(cpu_s=1e9), what="`trace`", yes=True)  # asked for: a month runs
    monkeypatch.setenv(CONFIRM_ENV, "0.5")
    check(Estimate(cpu_s=1800.0), what="`trace`", yes=False)
    assert "above TWRAY_CONFIRM_CPU_HOURS=0.5 CPU-hours" in _refusal(Estimate(cpu_s=1801.0), yes=False)
    monkeypatch.setenv(CONFIRM_ENV, "0")
    check(Estimate(cpu_s=0.0), what="`trace`", yes=False)
    assert "add --yes" in _refusal(Estimate(cpu_s=1.0), yes=False)


def test_what_clearly_cannot_fit_the_memory_is_refused_even_with_yes(caplog):
    """Refused when even 1/1.5 of the estimate is more than 80 % of the memory; between that and the
    estimate itself, a warning and the run goes on."""
    ram = machine_memory()
    check(Estimate(memory=0.8 * ram), what="`trace`", yes=True)
    assert not caplog.records
    check(Estimate(memory=1.19 * ram), what="`trace`", yes=True)  # may not fit: runs, warned
    assert [r.getMessage() for r in caplog.records] == [
        f"`trace` may need more memory than this machine's {size(ram)} (estimated {size(1.19 * ram)}, good to "
        f"1.5x); it runs"]
    msg = _refusal(Estimate(cpu_s=1e9, memory=1.21 * ram), yes=True)
    assert f"more memory than this machine's {size(ram)}" in msg
    assert "--yes" not in msg  # memory first: --yes would not help


def test_what_clearly_cannot_fit_the_free_disk_is_refused_where_it_would_be_written(tmp_path, caplog):
    free = free_disk(tmp_path)
    check(Estimate(disk=free / 2), what="`trace`", yes=True, disk_path=tmp_path)
    check(Estimate(disk=10 * free), what="`trace`", yes=True)  # no disk to write: not checked
    assert not caplog.records
    check(Estimate(disk=1.4 * free), what="`trace`", yes=True, disk_path=tmp_path)
    assert "may need more disk than the " in caplog.records[0].getMessage()
    target = tmp_path / "cache"
    msg = _refusal(Estimate(disk=10 * free), yes=True, disk_path=target)
    assert "more disk than the " in msg and f" free under {target}" in msg
    assert not target.exists()


# ------------------------------------------------------------------ estimates
def test_the_wood_a_beam_generates_is_whole_chunks_around_it_and_a_quarter_more():
    # 40 µm beam on 0.5 µm voxels: 80 + 16 voxels across -> 2 chunks of 64; 100 µm deep -> 200 -> 4 chunks.
    assert limits.SPREAD == 1.25
    assert wood_voxels(40.0, 100.0, 0.5) == 1.25 * 128 * 128 * 256
    assert wood_voxels(40.0, 100.0, 0.25) == 1.25 * 192 * 192 * 448  # 176 across -> 3 chunks, 400 deep -> 7
    assert wood_voxels(1.0, 1.0, 0.5) == 1.25 * 64 * 64 * 64  # never less than a chunk


def test_a_trace_costs_its_interfaces_at_the_methods_rate_and_the_wood_it_generates():
    # 1000 rays through 145 µm of 14.5 µm fibres: 10 pitches, INTERFACES_PER_PITCH interfaces each.
    rates = limits.INTERFACE_CPU_S
    n = 1000 * 10 * limits.INTERFACES_PER_PITCH
    kw = {"rays": 1000, "beam_um": 40.0, "thickness_um": 145.0, "voxel_um": 0.5, "pitch_um": 14.5}
    for method in ("accurate", "fast", "paper"):
        bare = trace_estimate(method=method, wood=False, **kw)
        assert bare.cpu_s == pytest.approx(n * rates[method])
        assert bare.memory == limits.BASE_MEMORY + 1000 * limits.RAY_BYTES and bare.disk == 0
    assert trace_estimate(method="new", wood=False, **kw) == trace_estimate(method="accurate", wood=False, **kw)
    voxels = wood_voxels(40.0, 145.0, 0.5)
    held = trace_estimate(method="fast", **kw)
    assert held.cpu_s == pytest.approx(n * rates["fast"] + voxels / limits.GENERATE_VOXELS_PER_CPU_S["ellipse"])
    assert held.memory == pytest.approx(limits.BASE_MEMORY + 1000 * limits.RAY_BYTES
                                        + voxels * limits.MEMORY_BYTES_PER_WOOD_VOXEL) and held.disk == 0
    stored = trace_estimate(method="fast", store=True, **kw)  # the wood on disk, not in memory
    assert stored.cpu_s == held.cpu_s and stored.memory == limits.BASE_MEMORY + 1000 * limits.RAY_BYTES
    assert stored.disk == pytest.approx(voxels * limits.DISK_BYTES_PER_VOXEL)
    balsa = trace_estimate(method="fast", store=True, params=build_params("balsa"), **kw)
    assert balsa.cpu_s - n * rates["fast"] == pytest.approx(voxels / limits.GENERATE_VOXELS_PER_CPU_S["polygon"])
    # Twice the thickness: twice the interfaces.
    thick = trace_estimate(method="fast", wood=False, **{**kw, "thickness_um": 290.0})
    assert thick.cpu_s == pytest.approx(2 * trace_estimate(method="fast", wood=False, **kw).cpu_s)


@pytest.mark.parametrize("preset, overrides, thickness_um", [
    ("birch", {}, 300.0), ("balsa", {}, 1000.0), ("birch", {"laminate": [0, -45, 90, 45, 0]}, 500.0)])
def test_exact_holds_the_region_it_builds_and_its_estimate_covers_it(preset, overrides, thickness_um):
    """What ``exact`` keeps for generated wood (distortion grid, bounds, vessels), measured on the
    region it builds around a 150 µm beam, is within the estimate, and the estimate within 4× of it."""
    from pipeline.microstructure.region import region_context
    from pipeline.optics.wood_surface import FIRST_MARGIN_UM

    p = build_params(preset, overrides=overrides)
    half = 75.0 + FIRST_MARGIN_UM + 0.05 * thickness_um
    ctx = region_context(p, 1, thickness_um, (-half, half), (-half, half))
    held = sum(v.nbytes for v in ctx.values() if isinstance(v, np.ndarray))
    est = limits.surface_region_bytes(150.0, thickness_um, p.fibre_diameter_um)
    assert held <= est <= 4 * held
    kw = {"rays": 100, "beam_um": 150.0, "thickness_um": thickness_um, "voxel_um": 0.5,
          "pitch_um": p.fibre_diameter_um, "method": "exact"}
    assert trace_estimate(**kw).memory == limits.BASE_MEMORY + 100 * limits.RAY_BYTES + limits.REGION_MEMORY_FACTOR * est
    assert trace_estimate(**kw, generated=False).memory == limits.BASE_MEMORY + 100 * limits.RAY_BYTES  # a lattice


def _scene(**changes) -> Scene:
    base = Scene(value=0.01, wood=BIRCH, seed=1, voxel_um=0.5, thickness_um=100.0, ri_polymer=1.49,
                 delta_ri=0.01, rays=1000, beam_um=40.0, settings=settings_for("fast"))
    return dataclasses.replace(base, **changes)


def test_a_study_generates_each_wood_once_and_traces_every_scene_by_shards():
    one = _scene()
    other_value = _scene(value=0.02, delta_ri=0.02)  # the same wood
    other_seed = _scene(seed=2)
    voxels = wood_voxels(40.0, 100.0, 0.5)
    shard = trace_estimate(rays=500, beam_um=40.0, thickness_um=100.0, voxel_um=0.5, pitch_um=14.5,
                           method="fast", wood=False, store=True)
    two_values = study_estimate([one, other_value], shard_rays=500)
    rays_written = two_values.disk - voxels * limits.DISK_BYTES_PER_VOXEL  # one wood, then the rays' entries
    assert rays_written > 0  # how much: test_a_studys_disk_estimate_is_within_1_5x_of_what_it_writes
    pool = limits.pool_cpu_s(1, 1000)  # a value's pool of its one wood's 1000 rays
    assert two_values.cpu_s == pytest.approx(4 * shard.cpu_s + voxels / limits.GENERATE_VOXELS_PER_CPU_S["ellipse"]
                                             + 2 * (limits.SCENE_CPU_S + pool) + limits.DATASET_CPU_S)
    # Peak memory: one value's rays read back at once, for every scene's Dataset.
    assert two_values.memory == limits.BASE_MEMORY + 1000 * (limits.RAY_BYTES + 2 * limits.DATASET_RAY_BYTES)
    two_woods = study_estimate([one, other_seed], shard_rays=500)
    assert two_woods.disk == pytest.approx(two_values.disk + voxels * limits.DISK_BYTES_PER_VOXEL)
    # A thicker sample of the same wood generates it deeper, not again.
    deeper = study_estimate([one, _scene(thickness_um=300.0)], shard_rays=500)
    assert deeper.disk == pytest.approx(wood_voxels(40.0, 300.0, 0.5) * limits.DISK_BYTES_PER_VOXEL + rays_written)
    # `accurate` generates and traces the wood on half the scene's voxel.
    fine = study_estimate([_scene(settings=settings_for("accurate"))], shard_rays=500)
    assert fine.disk - study_estimate([one], shard_rays=500).disk == pytest.approx(
        (wood_voxels(40.0, 100.0, 0.25) * 0.5 ** 0.5 - voxels) * limits.DISK_BYTES_PER_VOXEL)


def test_an_exact_woods_region_is_costed_once_however_its_rays_are_sharded_and_its_scenes_vary():
    # Its shards, and the scenes of the same wood (other values of ΔRI), share the worker's
    # distortion tiles, nearly all of a region's cost; another seed is another wood.
    scene = _scene(settings=settings_for("exact"), thickness_um=1000.0)
    one_shard = study_estimate([scene], shard_rays=1000)
    four = study_estimate([scene], shard_rays=250)
    assert four.cpu_s == pytest.approx(one_shard.cpu_s)
    region = limits.surface_region_bytes(40.0, 1000.0, 14.5) * limits.REGION_CPU_S_PER_BYTE
    bare = trace_estimate(rays=1000, beam_um=40.0, thickness_um=1000.0, voxel_um=0.5, pitch_um=14.5,
                          method="exact", wood=False, store=True, generated=False)
    pool = limits.pool_cpu_s(1, 1000)  # a value's pool of its one wood's 1000 rays

    def guided(dri):  # the tiles of rays guided along R: per ray, not per region
        return 1000 * limits.guided_tiles_per_ray(1000.0, dri) * limits.GUIDED_TILE_CPU_S

    assert one_shard.cpu_s == pytest.approx(bare.cpu_s + region + guided(0.01) + limits.SCENE_CPU_S + pool
                                            + limits.DATASET_CPU_S)
    two_values = study_estimate([scene, dataclasses.replace(scene, value=0.02, delta_ri=0.02)], shard_rays=1000)
    assert two_values.cpu_s == pytest.approx(2 * (bare.cpu_s + limits.SCENE_CPU_S + pool) + region
                                             + guided(0.01) + guided(0.02) + limits.DATASET_CPU_S)
    two_woods = study_estimate([scene, dataclasses.replace(scene, seed=2, realisation=1)], shard_rays=1000)
    # Another wood of the same value: its region again, and its rays in the value's one pool.
    assert two_woods.cpu_s == pytest.approx(two_values.cpu_s + region - 2 * pool + limits.pool_cpu_s(2, 2000)
                                            - guided(0.02) + guided(0.01))


def test_the_tiles_of_rays_guided_along_r_are_costed_in_thick_sheets_at_high_contrast_only():
    """Rays guided along R by total reflection at the walls build tiles along their strips: measured
    on birch into air (500 rays, one wood), 0.6 tiles a ray at 1 mm and |ΔRI| 0.02, 2.4 at 1.5 mm,
    10 at 2 mm, and 23 at 2 mm and ±0.03; little in Table 1's sheets at ΔRI 0.01."""
    g = limits.guided_tiles_per_ray
    assert g(2000.0, 0.03) == g(2000.0, -0.03) == pytest.approx(limits.GUIDED_TILES_PER_RAY)
    for t_um, dri, measured in ((1000.0, 0.02, 0.6), (1000.0, 0.03, 2.2), (1500.0, 0.02, 2.4), (1500.0, 0.03, 13.6),
                                (1500.0, -0.03, 12.0), (2000.0, 0.01, 0.8), (2000.0, 0.02, 10.0), (2000.0, 0.03, 24.4),
                                (2000.0, -0.03, 21.6)):  # results/guided_tiles.json
        assert measured / 1.3 <= g(t_um, dri) <= measured * 1.3, (t_um, dri)
    assert g(5000.0, 0.05) == limits.GUIDED_TILES_MAX  # beyond what was measured: at most a quarter of a strip a ray
    kw = dict(rays=1000, beam_um=150.0, voxel_um=0.5, pitch_um=14.5, method="exact", wood=False)
    thick = trace_estimate(thickness_um=2000.0, delta_ri=0.03, **kw).cpu_s
    assert thick - trace_estimate(thickness_um=2000.0, **kw).cpu_s == pytest.approx(
        1000 * limits.GUIDED_TILES_PER_RAY * limits.GUIDED_TILE_CPU_S)
    assert trace_estimate(thickness_um=2000.0, delta_ri=0.03, generated=False, **kw).cpu_s == \
        trace_estimate(thickness_um=2000.0, generated=False, **kw).cpu_s  # a lattice has no tiles
    table1 = trace_estimate(thickness_um=1500.0, delta_ri=0.01, **kw).cpu_s
    assert table1 < 1.15 * trace_estimate(thickness_um=1500.0, **kw).cpu_s  # measured: 3 %, fitted 11 %


def test_a_study_traced_to_a_precision_is_costed_at_its_cap_of_rays():
    capped = _scene(rays=1000, target=Target(haze=0.01, max_rays=4000))
    assert study_estimate([capped], shard_rays=500).cpu_s == \
        pytest.approx(study_estimate([_scene(rays=4000)], shard_rays=500).cpu_s)
    assert study_estimate([capped], shard_rays=500).cpu_s > study_estimate([_scene()], shard_rays=500).cpu_s


def test_a_study_too_large_for_the_machine_is_refused_before_it_starts(tmp_path):
    """What `twray study` checks first: a beam of ten billion rays cannot fit, even with --yes."""
    est = study_estimate([_scene(rays=10 ** 10)], shard_rays=10 ** 10)
    assert est.memory > machine_memory()
    with pytest.raises(ParameterError, match=r"^`study` needs ~.*more memory than this machine's .*; use fewer rays"):
        check(est, what="`study`", yes=True, disk_path=tmp_path, fit="use fewer rays")


def test_the_camera_generates_the_part_of_the_sheet_its_rays_reach_once():
    """Figure 5 at small scale: four 51 × 51 images of 20 samples a pixel through one 1.5 × 1 mm
    sheet, 100 µm thick, of the same wood (0.5 µm voxels, `fast`).  The rays reach the object
    field (51 pixels of 12.5 µm: 0.64 mm) through an aperture cone a few µm wide at the sheet,
    plus 1 % of the thickness and a chunk (32 µm) each side."""
    from pipeline.camera.scene import load_camera
    from pipeline.limits import camera_footprint_um

    images = load_camera(Path(__file__).resolve().parents[1] / "studies" / "camera" / "figure5.yaml",
                         scale="small", method="fast").images
    assert len(images) == 4
    r_um, l_um = camera_footprint_um(images[0].camera, images[0].sheet)
    assert r_um == pytest.approx(l_um, rel=1e-3) and 637.5 + 2 + 64 < r_um < 637.5 + 2 + 64 + 2
    wide = dataclasses.replace(images[0].sheet, width_um=300.0)  # a sheet narrower than the field: all of it
    assert camera_footprint_um(images[0].camera, wide)[0] == 300.0
    voxels = max(math.prod(camera_footprint_um(i.camera, i.sheet)) for i in images) * 100 / 0.5 ** 3
    interfaces = 51 * 51 * 20 * limits.INTERFACES_PER_PITCH * 100 / 14.5  # per image
    est = camera_estimate(images)
    assert est.disk == pytest.approx(voxels * limits.DISK_BYTES_PER_VOXEL)  # one wood for all four
    assert est.cpu_s == pytest.approx(4 * interfaces * limits.INTERFACE_CPU_S["fast"]
                                      + voxels / limits.GENERATE_VOXELS_PER_CPU_S["ellipse"])
    assert est.memory == pytest.approx(limits.BASE_MEMORY + limits.CAMERA_MEMORY
                                       + voxels * limits.CAMERA_BYTES_PER_WOOD_VOXEL)
    assert est.disk == max(camera_estimate([i]).disk for i in images)  # the widest footprint, once
    assert camera_estimate([]) == Estimate()


# ---------------------------------------------------------------------- estimates against measurements
SMALL_CASES = [name for name, (scale, _, _) in E.CASES.items() if scale == "small"]
HOST_SPREAD = 2.5  # how far this project's hosts may be from the one the CPU constants were fitted on


def _off(r: dict, host: float) -> list:
    """What of run ``r`` is more than 1.5x from its estimate (CPU: once divided by ``host``)."""
    out = []
    for what, q in r["ratio"].items():
        if q is None:  # nothing written, nothing estimated
            assert r["estimate"]["disk"] == 0
            continue
        q = q / host if what == "cpu" else q
        if not 1 / 1.5 <= q <= 1.5:
            out.append((what, round(q, 2)))
    return out


def test_each_commands_estimate_is_within_1_5x_of_what_it_uses():
    """Each command run as a user runs it (in fresh folders, through `python -m pipeline`), its CPU
    (the process tree's, Dask workers included), largest resident memory and disk measured here,
    against the estimate it checked before running (TWRAY_ESTIMATES): memory and disk no more than
    1.5x apart either way.  CPU depends on the host, alike for every command (this project's hosts
    differ by up to 2x from session to session), so each command's CPU ratio is held within 1.5x of
    the median ratio of all, and that median within HOST_SPREAD of 1.  The cases are
    benchmarks/bench_estimates.py's small ones (`make bench-estimates` runs them and the
    paper-scale ones into results/estimates.md)."""
    runs = {case: E.run_case(case) for case in SMALL_CASES}
    host = float(np.median([r["ratio"]["cpu"] for r in runs.values()]))
    for case, r in runs.items():
        if _off(r, host):
            runs[case] = E.run_case(case)  # a fresh checkout compiles the kernels in its first run
    host = float(np.median([r["ratio"]["cpu"] for r in runs.values()]))
    assert 1 / HOST_SPREAD <= host <= HOST_SPREAD, {c: r["ratio"] for c, r in runs.items()}
    off = {case: _off(r, host) for case, r in runs.items()}
    assert not any(off.values()), (host, {c: (o, runs[c]["estimate"], runs[c]["used"]) for c, o in off.items() if o})


def test_a_pools_distinct_resamples_of_woods_are_as_many_as_the_multinomial_draws_give():
    """Each distinct resample of woods is fitted once, so a pool's cost follows their number:
    against its expectation over every resample of R woods (a multiset of R draws of R, drawn with
    the multinomial probability R!/(Π c!)/R^R) in 2000 draws."""
    import itertools

    for woods in (2, 3, 4, 5, 6):
        mean = var = 0.0
        for c in itertools.product(range(woods + 1), repeat=woods):
            if sum(c) == woods:
                p = math.factorial(woods) / math.prod(math.factorial(k) for k in c) / woods ** woods
                q = 1.0 - (1.0 - p) ** 2000
                mean, var = mean + q, var + q * (1.0 - q)
        assert abs(limits.distinct_resamples(woods) - mean) <= 3.0 * math.sqrt(var) + 0.5, woods
    assert limits.distinct_resamples(40) == 2000  # 40 woods: every resample differs
    assert limits.pool_cpu_s(5, 5000) < limits.pool_cpu_s(40, 5000) / 5


def test_a_first_run_of_these_sources_counts_compiling_the_kernels_and_says_so(tmp_path, monkeypatch, capsys):
    # A machine that has not compiled this checkout's kernels: each process compiles them at first
    # use, which the estimate counts and a study says (a dry run: nothing is compiled here).
    import subprocess

    from pipeline.cli import main

    kernels = tmp_path / "kernels"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(kernels))
    assert not limits.compiled(*limits.FIRST_KERNEL["surfaces"])
    assert limits.compiling({"surfaces", "voxels", "fields"}, 2).cpu_s == pytest.approx(
        2 * (limits.COMPILE_CPU_S["surfaces"] + limits.COMPILE_CPU_S["voxels"]))
    study = Path(__file__).resolve().parent.parent / "studies" / "table1" / "study-1.yaml"
    assert main(["study", str(study), "--scale", "small", "--workers", "2", "--dry-run", "--cache",
                 str(tmp_path / "c"), "--results", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert "each of the 2 workers compiles the tracer's kernels before its first trace (4 CPU-min in all, once)" in err
    # `twray trace` says it too, before it would compile; refused (here for its CPU), in the refusal's
    # one line.
    monkeypatch.setenv(CONFIRM_ENV, "0.001")
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.1", "--delta-ri", "0.01", "--rays", "20"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "; first run of these sources here: it compiles the tracer's kernels before its first trace " \
           "(2 CPU-min in all, once)" in err and "add --yes" in err
    # A kernel of this checkout that a fresh process compiles into that cache is found there.
    assert not limits.compiled("rng", "uniform_table")
    subprocess.run([sys.executable, "-c", "from pipeline.optics.rays import square_beam; square_beam(3, 5.0, seed=1)"],
                   check=True)
    assert limits.compiled("rng", "uniform_table") and not limits.compiled("rng", "no_such_kernel")
