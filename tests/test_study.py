"""Studies: YAML schema, cached incremental Dask graphs on a real LocalCluster, Datasets."""

import dataclasses
import json
import re
import os
import time
from pathlib import Path

import numpy as np
import zarr
import pytest
import xarray as xr

from pipeline.cli import main
from pipeline.microstructure.store import WoodChunkStore
from pipeline.optics.sources import WoodSource
from pipeline.params import ParameterError, build_params
from pipeline.cache import atomic_write as _atomic_write
from pipeline.study.dataset import study_dataset, write_dataset
from pipeline.study.graph import compute
from pipeline.study.plan import plan_study, report_table
from pipeline.study.summaries import resummarized
from pipeline.study.spec import load_study

TABLE1 = Path(__file__).resolve().parent.parent / "studies" / "table1"

# A quick study: at --scale small this is 40 rays through 30 µm of birch.
TINY = """\
title: tiny
preset: birch
seed: 3
realisations: 1
rays: 400
beam_um: 100
thickness_mm: 0.3
delta_ri: 0.01
trace: {method: fast}
vary:
  parameter: delta_ri
  values: {values}
"""


def tiny(tmp_path, values, name="tiny.yaml"):
    path = tmp_path / name
    path.write_text(TINY.replace("{values}", json.dumps(values)))
    return path


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as c:
        yield c


def run(path, cache, results, client, *, shard_rays=250, method=None):
    study = load_study(path, scale="small", method=method)
    plan = plan_study(study, cache, shard_rays=shard_rays)
    report = compute([plan], client)
    plan = plan_study(study, cache, shard_rays=shard_rays)
    return write_dataset(plan, results), report, plan


def stored_chunks(cache: Path) -> list:
    return [p for p in (cache / "micro").rglob("*") if p.is_file() and p.parent.parent.parent.name == "c"]


# ---------------------------------------------------------------------- schema
def test_table1_files_expand_to_the_papers_values():
    expected = {
        "study-1": ("thickness", [0.25, 0.5, 0.75, 1.0, 1.25, 1.5]),
        "study-2": ("delta_ri", [-0.03, -0.02, -0.01, 0.01, 0.02, 0.03]),
        "study-3": ("fibre_diameter", [14.5, 29.0]),
        "study-4": ("wall_thickness", [2.0, 4.0]),
        "study-5-1": ("ray_cells", [True, False]),
        "study-5-2": ("vessels", [True, False]),
        "study-6": ("laminate", ["none", "0/-45/90/45/0"]),
    }
    for name, (dim, values) in expected.items():
        st = load_study(TABLE1 / f"{name}.yaml")
        assert (st.dimension, st.coordinate()) == (dim, values), name
        assert all(s.rays == 1000 and s.voxel_um == 0.5 and s.beam_um == 150 for s in st.scenes)
    s3 = load_study(TABLE1 / "study-3.yaml").scenes
    assert not any(s.wood.vessels for s in s3)
    s4 = load_study(TABLE1 / "study-4.yaml").scenes
    assert all(s.wood.fibre_diameter_um == 29 for s in s4)
    s6 = load_study(TABLE1 / "study-6.yaml").scenes
    assert all(s.thickness_um == 500 for s in s6)
    assert s6[1].wood.laminate == (0, -45, 90, 45, 0) and s6[1].wood.ply_thickness_um == 100
    small = load_study(TABLE1 / "study-1.yaml", scale="small").scenes
    assert [s.thickness_um for s in small] == pytest.approx([25, 50, 75, 100, 125, 150])
    assert small[0].rays == 100


def test_studies_share_the_wood_and_scenes_they_have_in_common(tmp_path):
    names = ("study-1", "study-2", "study-3", "study-5-1", "study-5-2", "study-6")
    exact = {n: plan_study(load_study(TABLE1 / f"{n}.yaml", scale="small"), tmp_path) for n in names}
    assert all(p.study.scenes[0].settings.method == "exact" and not p.micros for p in exact.values())
    # The woods are shared as voxel chunks by a voxel method, and as scenes by every method.
    plans = {n: plan_study(load_study(TABLE1 / f"{n}.yaml", scale="small", method="accurate"), tmp_path)
             for n in names}
    assert all(p.study.realisations == 2 for p in plans.values())  # at most 2 at scale small
    base = set(plans["study-1"].micros)
    assert len(base) == 2  # every thickness reads the same two woods (common random numbers)
    assert set(plans["study-2"].micros) == base  # and so does every ΔRI
    by_real = [[s.micro for s in plans["study-2"].shards if s.realisation == r] for r in (0, 1)]
    assert by_real[0] == by_real[0][:1] * 6 and by_real[1] == by_real[1][:1] * 6 and by_real[0][0] != by_real[1][0]
    # The base scene (1 mm, ΔRI 0.01, birch) is one cache entry in studies 1, 2 and 5-1, on each wood.
    key = {n: {(s.scene_index, s.realisation): s.key for s in plans[n].summaries} for n in plans}
    pool = {n: [p.key for p in plans[n].pools] for n in plans}
    for r in (0, 1):
        assert key["study-1"][3, r] == key["study-2"][3, r] == key["study-5-1"][0, r] == key["study-5-2"][0, r]
        assert key["study-5-2"][1, r] == key["study-3"][0, r]  # no vessels at 14.5 µm
        assert key["study-6"][0, r] == key["study-1"][1, r]  # 0.5 mm of birch
    assert key["study-1"][3, 0] != key["study-1"][3, 1]
    assert pool["study-1"][3] == pool["study-2"][3] == pool["study-5-1"][0]
    assert key["study-5-1"][1, 0] not in key["study-2"].values()
    ex = {n: {(s.scene_index, s.realisation): s.key for s in exact[n].summaries} for n in exact}
    for r in (0, 1):
        assert ex["study-1"][3, r] == ex["study-2"][3, r] == ex["study-5-1"][0, r] != key["study-1"][3, r]
        assert ex["study-6"][0, r] == ex["study-1"][1, r]


def test_the_convergence_benchmark_varies_accurates_rays_and_voxel_alone():
    """`make convergence` measures the voxel method Table 1 used before `exact`: 4× the rays, or
    the study voxel traced as it is (refine 1) instead of halved, everything else the same."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("convergence", TABLE1.parent.parent / "benchmarks" / "convergence.py")
    conv = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conv)
    for name, st in conv.studies_of("small").items():
        base, more, coarse = (conv.variant(st, v) for v in conv.VARIANTS)
        assert st.realisations == 1 and all(s.settings.method == "accurate" for s in st.scenes), name
        for b, m, c in zip(base.scenes, more.scenes, coarse.scenes):
            assert (b.traced_voxel_um, c.traced_voxel_um) == (0.25, 0.5) and m.rays == 4 * b.rays
            assert dataclasses.replace(c, settings=b.settings) == b and dataclasses.replace(m, rays=b.rays) == b


def test_scale_quick_traces_the_papers_samples_and_woods_with_a_twentieth_of_the_rays():
    for name in ("study-1", "study-6"):
        paper, quick = (load_study(TABLE1 / f"{name}.yaml", scale=s) for s in ("paper", "quick"))
        assert quick.realisations == paper.realisations == 5
        for p, q in zip(paper.scenes, quick.scenes):
            assert (q.thickness_um, q.beam_um, q.wood, q.settings) == (p.thickness_um, p.beam_um, p.wood, p.settings)
            assert (p.rays, q.rays) == (1000, 50)


@pytest.mark.parametrize("text, needle", [
    ("rayz: 10\n", "line 1: unknown key `rayz`"),
    ("wood:\n  walls: 3\n", "line 2: unknown microstructure parameter `wood.walls`"),
    ("trace:\n  method: quick\n", "line 2: `trace.method` must be one of paper, fast, accurate"),
    ("rays: -4\n", "line 1: `rays` must be a positive integer"),
    ("thickness_mm: thick\n", "line 1: `thickness_mm` must be a number"),
    ("wood:\n  wall_thickness_um: 12\n", "`wall_thickness_um` must be < "),
    ("trace:\n  method: accurate\n  refine: 0\n", "line 3: `trace.refine` must be an integer in [1, 8]"),
    ("trace:\n  method: accurate\n  refine: 2.5\n", "line 3: `trace.refine` must be an integer in [1, 8]"),
    ("trace:\n  refine: 2\n", "line 2: `trace.refine` applies to the voxel methods, not to method 'exact'"),
])
def test_bad_study_files_name_file_line_and_field(tmp_path, text, needle, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(text + "vary: {parameter: delta_ri, values: [0.01]}\n")
    with pytest.raises(ParameterError, match="bad.yaml") as err:
        load_study(path)
    assert needle in str(err.value)
    assert main(["study", str(path), "--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r")]) == 2
    msg = capsys.readouterr().err.strip()
    assert msg.count("\n") == 0 and "bad.yaml" in msg
    assert not (tmp_path / "c").exists() and not (tmp_path / "r").exists()


def test_bad_varied_values_are_refused(tmp_path):
    path = tmp_path / "v.yaml"
    path.write_text("vary:\n  parameter: vessels\n  values: [yes_please]\n")
    with pytest.raises(ParameterError, match=r"v.yaml line 3: `vary.values`: `vessels` must be true or false"):
        load_study(path)
    path.write_text("vary:\n  parameter: colour\n  values: [1]\n")
    with pytest.raises(ParameterError, match=r"line 2: `vary.parameter` must be one of"):
        load_study(path)
    path.write_text("vary:\n  parameter: delta_ri\n  values: [0.01, 0.01]\n")
    with pytest.raises(ParameterError, match="must not repeat"):
        load_study(path)


# ---------------------------------------------------------------------- wood chunk store
def test_stored_chunks_equal_generated_ones_whatever_the_thickness(tmp_path):
    params = build_params("birch")
    store = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5)
    plain = WoodSource(params, thickness_um=40.0, seed=5)  # 80 voxels: chunk T=1 is cut
    cached = WoodSource(params, thickness_um=40.0, seed=5, store=store)
    for idx in [(0, 0, 0), (-2, 1, 3), (1, 1, -1)]:
        assert np.array_equal(cached.get(idx), plain.get(idx))
    assert store.generated == 3 and store.stored((-2, 1, 3))
    reread = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5)
    thick = WoodSource(params, thickness_um=100.0, seed=5, store=reread)
    assert np.array_equal(thick.get((-2, 1, 3)), WoodSource(params, thickness_um=100.0, seed=5).get((-2, 1, 3)))
    assert reread.generated == 0  # a thicker sample of the same wood reuses the chunk


def test_get_many_makes_free_chunks_while_another_thread_holds_one(tmp_path):
    import threading

    from pipeline.microstructure import store as store_module

    params = build_params("birch")
    store = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
    held = store_module._lock_for((str(store.path), (0, 0, 0)))
    held.acquire()  # another thread is "generating" chunk (0, 0, 0)
    result = {}
    worker = threading.Thread(target=lambda: result.update(store.get_many([(0, 0, 0), (1, 0, 0)])))
    worker.start()
    try:
        deadline = time.monotonic() + 120  # generous: the first call may compile the kernels
        while not store.stored((1, 0, 0)) and time.monotonic() < deadline:
            worker.join(0.01)  # the free chunk is made without waiting for the held one
        assert store.stored((1, 0, 0)) and not store.stored((0, 0, 0)) and worker.is_alive()
    finally:
        held.release()
    worker.join(30)
    plain = WoodSource(params, thickness_um=64.0, seed=5, chunks=(16, 16, 16))
    assert sorted(result) == [(0, 0, 0), (1, 0, 0)]
    for idx in result:
        assert np.array_equal(result[idx], plain.get(idx))
    assert store.generated == 2


def test_chunk_files_are_the_zarr_arrays_chunks(tmp_path):
    """The store writes chunk files itself; zarr must read them, and it must read zarr's."""
    from pipeline.microstructure.store import OFFSET

    params = build_params("birch")
    store = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
    assert store._files is not None  # the direct path is the one under test
    mine = store.get((-1, 2, 0))
    array = zarr.open_array(tmp_path / "w.zarr" / "0", mode="r+")
    at = (slice((OFFSET - 1) * 16, OFFSET * 16), slice(32, 48), slice(OFFSET * 16, (OFFSET + 1) * 16))
    assert np.array_equal(array[at], mine)
    # A chunk written behind twray's back (here by zarr: zeros, not what the wood holds)
    # lacks the digest of the wood at that index: it is not trusted but generated again.
    theirs = (slice(OFFSET * 16, (OFFSET + 1) * 16), slice(0, 16), slice(OFFSET * 16, (OFFSET + 1) * 16))
    array[theirs] = np.zeros((16, 16, 16), np.uint8)
    assert not array[theirs].any()
    again = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
    from pipeline.microstructure.store import _memory
    _memory.clear()
    wood = again.get((0, 0, 0))
    assert wood.any() and again.read == 0 and again.generated == 1
    assert np.array_equal(array[theirs], wood)
    assert not list((tmp_path / "w.zarr").rglob(".*.*"))  # no temporary files left


def test_a_failed_cache_write_leaves_no_entry(tmp_path):
    target = tmp_path / "rays" / "x.npz"

    def crash(tmp):
        tmp.write_bytes(b"half an entry")
        raise OSError("disk full")

    with pytest.raises(OSError):
        _atomic_write(target, crash)
    assert list((tmp_path / "rays").iterdir()) == []


# ---------------------------------------------------------------------- pipeline on a LocalCluster
def test_study_2_small_gives_six_finite_values_on_two_woods(tmp_path, client):
    cache = tmp_path / "cache"
    out, report, plan = run(TABLE1 / "study-2.yaml", cache, tmp_path / "results", client, method="accurate")
    assert out == tmp_path / "results" / "study-2.zarr"
    ds = xr.open_zarr(out, consolidated=False).load()
    # What was traced, not the study's numbers: 1 mm at scale small is 0.1 mm.
    assert np.all(ds.thickness_traced.values == 0.1) and ds.thickness_traced.attrs["units"] == "mm"
    assert ds.attrs["beam_traced_um"] == 37.5
    table = report_table([plan]).splitlines()
    assert table[0].startswith("| study | parameter | value | thickness traced (mm) |")
    assert all(row.split(" | ")[3] == "0.1" for row in table[2:8])
    assert any(line.startswith("Scale small is not the paper's") for line in table)
    assert ds.sizes == {"delta_ri": 6, "realisation": 2, "ray": 100}
    assert list(ds.seed_of_realisation.values) == [1, 2] and ds.attrs["realisations"] == 2
    for name in ("FWHM_R", "FWHM_L", "haze", "FWHM_R_ci_lower", "FWHM_R_ci_upper",
                 "FWHM_L_ci_lower", "FWHM_L_ci_upper", "n_transmitted", "n_lost"):
        assert np.all(np.isfinite(ds[name].values)), name
    assert list(ds.delta_ri.values) == [-0.03, -0.02, -0.01, 0.01, 0.02, 0.03]
    assert ds.delta_ri.attrs["units"] == "1" and ds.FWHM_R.attrs["units"] == "degree"
    assert ds.haze.attrs["units"] == "1"
    assert np.all(ds.FWHM_R_ci_lower <= ds.FWHM_R) and np.all(ds.FWHM_R <= ds.FWHM_R_ci_upper)
    assert np.all(ds.n_transmitted + ds.n_lost == 200)
    assert np.all(ds.n_transmitted == ds.n_transmitted_per_realisation.sum("realisation"))
    assert np.all(np.isfinite(ds.FWHM_R_per_realisation.values))
    # The scattering grows with |ΔRI| and is (nearly) even in its sign.
    f = ds.FWHM_R.values
    assert f[0] > f[2] and f[5] > f[3]
    assert ds.attrs["study_yaml"] == (TABLE1 / "study-2.yaml").read_text()
    assert ds.attrs["source"].startswith("twray ") and ds.attrs["seed"] == 1
    assert json.loads(ds.attrs["trace_settings"])["method"] == "accurate"
    keys = json.loads(ds.attrs["cache_keys"])
    # One microstructure per realisation for the six values, generated once: every chunk on
    # disk was generated exactly one time (one worker process, two threads).
    assert len({r["micro"] for k in keys for r in k["realisations"]}) == 2
    assert len(list((cache / "micro").iterdir())) == 2
    assert report["chunks_generated"] == len(stored_chunks(cache)) > 0
    assert report["trace_tasks"] == 12 and report["summary_tasks"] == 12 and report["pool_tasks"] == 6
    # The per-ray angles are there for re-analysis and agree with the fits' inputs.
    t = ds.status.values == 1
    assert np.all(np.isfinite(ds.theta_r.values[t]))
    # Every estimator is there, FWHM_R is the default's, and re-summarising the Dataset from its own
    # rays (twray resummarize) gives the study's summaries bit for bit.
    assert ds.attrs["fwhm_estimator"] == "half-max" and np.array_equal(ds.FWHM_R.values, ds.FWHM_R_half_max.values)
    again, _ = resummarized(ds)
    summary_vars = [v for v in again.data_vars if v not in ("theta_r", "theta_l", "status", "n_interfaces")]
    assert len(summary_vars) > 50
    for v in summary_vars:
        np.testing.assert_array_equal(again[v].values, ds[v].values, err_msg=v)


def test_unchanged_rerun_computes_nothing_and_a_new_value_traces_only_itself(tmp_path, capsys):
    study = tiny(tmp_path, [0.01, 0.03])
    args = ["study", str(study), "--scale", "small", "--cache", str(tmp_path / "c"),
            "--results", str(tmp_path / "r"), "--workers", "1"]
    assert main(args) == 0
    out = tmp_path / "r" / "tiny.zarr"
    stamp = os.stat(out / "zarr.json").st_mtime_ns
    entries = {p: p.stat().st_mtime_ns for p in (tmp_path / "c").rglob("*") if p.is_file() and p.parent.name != "logs"}
    # Nothing is computed or written again (how much faster that is: make bench, table1_small).
    assert main(args) == 0
    assert os.stat(out / "zarr.json").st_mtime_ns == stamp
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "c").rglob("*") if p.is_file() and p.parent.name != "logs"} == entries
    capsys.readouterr()
    assert main(args + ["--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and all("1/1 shards cached; summary cached" in ln for ln in lines[:2])
    assert all(ln.endswith("1 realisations pooled cached") for ln in lines[2:])

    # Add a value: only it is traced; the wood and the other value are reused.
    tiny(tmp_path, [0.01, 0.02, 0.03])
    st = load_study(study, scale="small")
    plan = plan_study(st, tmp_path / "c")
    assert [s.cached for s in plan.summaries] == [True, False, True]
    assert [s.cached for s in plan.shards] == [True, False, True]
    assert main(args + ["--dry-run"]) == 0
    assert "delta_ri=0.02 realisation 0: micro" in capsys.readouterr().out
    assert main(args) == 0
    for p, t in entries.items():
        assert p.stat().st_mtime_ns == t, p  # nothing recomputed or rewritten
    ds = xr.open_zarr(out, consolidated=False)
    assert list(ds.delta_ri.values) == [0.01, 0.02, 0.03]
    assert np.all(np.isfinite(ds.FWHM_R.values))


def test_same_numbers_with_one_or_two_workers_and_any_shard_size(tmp_path):
    from distributed import Client, LocalCluster

    study = tiny(tmp_path, [-0.02, 0.02])
    sets = []
    for workers, shard in [(1, 40), (2, 7)]:
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as c:
            out, _, _ = run(study, tmp_path / f"c{workers}", tmp_path / f"r{workers}", c, shard_rays=shard)
        sets.append(xr.open_zarr(out, consolidated=False).load())
    a, b = sets
    for name in ("theta_r", "theta_l", "status", "n_interfaces", "FWHM_R", "FWHM_L", "haze",
                 "FWHM_R_ci_lower", "FWHM_L_ci_upper"):
        assert np.array_equal(a[name].values, b[name].values), name
    assert a.attrs["cache_keys"] != b.attrs["cache_keys"]  # different shards, same numbers


def test_a_study_equals_the_trace_command_for_the_same_scene(tmp_path, client, capsys):
    study = tiny(tmp_path, [0.02])
    out, _, _ = run(study, tmp_path / "c", tmp_path / "r", client)
    ds = xr.open_zarr(out, consolidated=False)
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.03", "--delta-ri", "0.02",
                 "--rays", "40", "--beam-um", "25", "--method", "fast", "--seed", "3", "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert cli["fwhm_r_deg"] == float(ds.FWHM_R[0]) and cli["haze"] == float(ds.haze[0])


def test_dataset_coordinates_for_booleans_and_laminates(tmp_path, client):
    path = tmp_path / "lam.yaml"
    path.write_text("rays: 200\nbeam_um: 60\nthickness_mm: 0.2\ntrace: {method: fast}\nrealisations: 1\n"
                    "vary:\n  parameter: laminate\n  values: [none, '[0/90]']\n")
    out, _, plan = run(path, tmp_path / "c", tmp_path / "r", client)
    ds = xr.open_zarr(out, consolidated=False)
    assert list(ds.laminate.values) == ["none", "0/90"]
    assert plan.study.scenes[1].wood.ply_thickness_um == 10.0  # two equal plies in 20 µm
    assert len(plan.micros) == 2
    ds2 = study_dataset(plan)
    assert ds2.laminate.attrs["units"] == "degree"


def test_accurate_models_the_wood_on_voxels_half_the_studys_and_refine_is_a_setting(tmp_path):
    """The wood is a function of position: `accurate` generates and traces it on voxels
    ``refine`` (2) times smaller than the study's, the same physical wood, cached as its own
    microstructure; a study may set trace.refine for any method."""
    path = tiny(tmp_path, [0.01])
    fast = load_study(path).scenes[0]
    assert fast.settings.refine == 1 and fast.traced_voxel_um == fast.voxel_um == 0.5
    path.write_text(path.read_text().replace("trace: {method: fast}", "trace: {method: accurate}"))
    acc = load_study(path).scenes[0]
    assert acc.settings.refine == 2 and acc.traced_voxel_um == 0.25 and acc.voxel_um == 0.5
    path.write_text(path.read_text().replace("trace: {method: accurate}", "trace: {method: fast, refine: 3}"))
    three = load_study(path).scenes[0]
    assert three.settings.method == "fast" and three.traced_voxel_um == pytest.approx(0.5 / 3)
    plans = {s.settings.refine: plan_study(load_study(p), tmp_path / "c") for s, p in
             ((fast, tiny(tmp_path, [0.01], "a.yaml")), (three, path))}
    m1, m3 = (next(iter(plans[k].micros.values())) for k in (1, 3))
    assert m1.key != m3.key
    assert m3.store().voxel_um == pytest.approx(0.5 / 3) and m1.store().voxel_um == 0.5


def test_a_refined_study_equals_the_trace_command_for_the_same_scene(tmp_path, client, capsys):
    study = tiny(tmp_path, [0.02])
    study.write_text(study.read_text().replace("trace: {method: fast}", "trace: {method: fast, refine: 2}"))
    out, _, _ = run(study, tmp_path / "c", tmp_path / "r", client)
    ds = xr.open_zarr(out, consolidated=False)
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.03", "--delta-ri", "0.02",
                 "--rays", "40", "--beam-um", "25", "--method", "fast", "--refine", "2", "--seed", "3",
                 "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert cli["refine"] == 2 and cli["traced_voxel_um"] == 0.25
    assert cli["fwhm_r_deg"] == float(ds.FWHM_R[0]) and cli["haze"] == float(ds.haze[0])
    # The same beam on the study's own voxels is another model of the same wood.
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.03", "--delta-ri", "0.02",
                 "--rays", "40", "--beam-um", "25", "--method", "fast", "--seed", "3", "--json"]) == 0
    coarse = json.loads(capsys.readouterr().out)
    assert coarse["refine"] == 1 and coarse["fwhm_r_deg"] != cli["fwhm_r_deg"]


def test_an_unreachable_scheduler_is_one_line_within_seconds_and_nothing_is_written(tmp_path, capsys):
    path = tiny(tmp_path, [0.01])
    t0 = time.perf_counter()
    code = main(["study", str(path), "--scale", "small", "--scheduler", "tcp://127.0.0.1:9",
                 "--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and time.perf_counter() - t0 < 15
    assert err.count("\n") == 0 and "`scheduler` must be a Dask scheduler that answers within" in err
    assert not (tmp_path / "c").exists() and not (tmp_path / "r").exists()


def test_relative_cache_and_results_are_the_clients_on_a_scheduler_whose_workers_live_elsewhere(
        tmp_path, monkeypatch, capsys):
    from distributed import Client, LocalCluster

    elsewhere = tmp_path / "worker-home"
    elsewhere.mkdir()
    here = tmp_path / "me"
    here.mkdir()
    tiny(here, [0.01])  # writes tiny.yaml, run by its relative name
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as c:
        c.run(os.chdir, str(elsewhere))  # the workers' working folder is not the client's
        monkeypatch.chdir(here)
        code = main(["study", "tiny.yaml", "--scale", "small", "--scheduler", cluster.scheduler_address,
                     "--cache", "cache", "--results", "out"])
    assert code == 0, capsys.readouterr().err
    assert (here / "cache" / "rays").is_dir() and (here / "out" / "tiny.zarr").is_dir()
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("line, rule", [
    ("rays: 1000000000000", "more memory than this machine's"),
    ("beam_um: 1000000000", "more disk than the"),  # the wood under a 1 km beam
])
def test_absurd_sizes_are_refused_before_planning_even_in_a_dry_run(tmp_path, capsys, line, rule):
    study = tmp_path / "big.yaml"
    key = line.split(":")[0]
    text = TINY.replace("{values}", "[0.01]")
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith(key + ":")) + f"\n{line}\n"
    study.write_text(text)
    t0 = time.perf_counter()
    code = main(["study", str(study), "--scale", "paper", "--cache", str(tmp_path / "c"),
                 "--results", str(tmp_path / "r"), "--dry-run"])
    err = capsys.readouterr().err
    assert code == 2 and rule in err and "`study` needs ~" in err and err.count("\n") == 1, err
    assert time.perf_counter() - t0 < 1 and sorted(p.name for p in tmp_path.iterdir()) == ["big.yaml"]


def test_a_study_prints_its_estimate_and_asks_for_yes_above_the_threshold(tmp_path, capsys, monkeypatch):
    study = tiny(tmp_path, [0.01])
    args = ["study", str(study), "--scale", "small", "--cache", str(tmp_path / "c"),
            "--results", str(tmp_path / "r"), "--workers", "1"]
    monkeypatch.setenv("TWRAY_CONFIRM_CPU_HOURS", "0")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "`study` needs ~" in err and "CPU-s of CPU" in err and "add --yes (with make: YES=1) to run it" in err
    assert not (tmp_path / "r").exists()


def test_an_exact_study_equals_the_trace_command_and_generates_no_wood(tmp_path, client, capsys):
    """`exact` in a study: no wood-chunk stage, rays keyed without a voxel, the same numbers as
    `twray trace --method exact` for the same scene."""
    study = tmp_path / "exact.yaml"
    study.write_text(tiny(tmp_path, [0.02]).read_text().replace("method: fast", "method: exact"))
    out, _, plan = run(study, tmp_path / "c", tmp_path / "r", client)
    assert not plan.micros
    ds = xr.open_zarr(out, consolidated=False)
    assert main(["trace", "--preset", "birch", "--thickness-mm", "0.03", "--delta-ri", "0.02",
                 "--rays", "40", "--beam-um", "25", "--method", "exact", "--seed", "3", "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert cli["fwhm_r_deg"] == float(ds.FWHM_R[0]) and cli["haze"] == float(ds.haze[0])
    assert "voxels_generated" not in cli and "degenerate_normals" not in cli


def test_a_reference_lattice_study_traces_each_method_on_the_same_lattice(tmp_path, client, capsys):
    """A study of a reference lattice (``reference:`` instead of ``preset``): `exact` equals
    `twray trace --reference` of the same scene and reads no voxels; a voxel method traces the
    lattice's voxelisation and stores no wood; varying the wall changes the lattice."""
    text = REFERENCE_STUDY
    study = tmp_path / "ref.yaml"
    study.write_text(text)
    out, _, plan = run(study, tmp_path / "c", tmp_path / "r", client)
    assert not plan.micros
    ds = xr.open_zarr(out, consolidated=False)
    assert list(ds.wall.values) == [1.0, 3.0] and ds.wall.attrs["units"] == "um"
    assert main(["trace", "--reference", "cells-hex", "--pitch-um", "14", "--wall-um", "3", "--jitter", "0.1",
                 "--thickness-mm", "0.02", "--delta-ri", "0.02", "--rays", "40", "--beam-um", "25",
                 "--method", "exact", "--seed", "3", "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert cli["fwhm_r_deg"] == float(ds.FWHM_R[1]) and cli["haze"] == float(ds.haze[1])
    assert float(ds.haze[1]) > float(ds.haze[0])  # thicker walls, more scattering
    voxel = tmp_path / "ref-fast.yaml"
    voxel.write_text(text.replace("method: exact", "method: fast"))
    out, _, plan = run(voxel, tmp_path / "c", tmp_path / "r", client)
    assert not plan.micros and not (tmp_path / "c" / "micro").exists()
    fast = xr.open_zarr(out, consolidated=False)
    assert fast.FWHM_R.shape == (2,) and not np.array_equal(fast.FWHM_R.values, ds.FWHM_R.values)


@pytest.mark.parametrize("edit, message", [
    (("seed: 3", "seed: 3\npreset: birch"), "`preset` and `reference` exclude each other"),
    (("jitter: 0.1", "jitter: 0.1, wal_um: 2"), "unknown key `reference.wal_um`"),
    (("parameter: wall_um", "parameter: vessels"), "`vary.parameter` of a reference scene must be one of"),
    (("values: [1.0, 3.0]", "values: [1.0, 8.0]"), "value 8.0: `reference.wall_um` must be in (0, pitch_um / 2"),
])
def test_a_bad_reference_study_is_one_line_naming_the_field(tmp_path, edit, message):
    study = tmp_path / "ref.yaml"
    study.write_text(REFERENCE_STUDY.replace(*edit))
    with pytest.raises(ParameterError, match=re.escape(message)):
        load_study(study, scale="small")


REFERENCE_STUDY = """\
title: reference
reference: {name: cells-hex, pitch_um: 14, wall_um: 2, jitter: 0.1}
seed: 3
realisations: 1
rays: 400
beam_um: 100
voxel_um: 0.5
delta_ri: 0.02
thickness_mm: 0.2
trace: {method: exact}
vary: {parameter: wall_um, values: [1.0, 3.0]}
"""


@pytest.mark.parametrize("method", ["fast", "exact"])
def test_a_voxel_outside_its_range_is_refused_whichever_method_and_an_unused_one_is_named(tmp_path, capsys, method):
    """A voxel of 1e-6 µm is a typo whatever the method (with `exact`, which uses none, it once ran
    without a word); a valid voxel given to `exact` is named as unused, in one line."""
    study = tmp_path / "v.yaml"
    text = TINY.replace("{values}", "[0.01]").replace("trace: {method: fast}", f"trace: {{method: {method}}}")
    study.write_text(text + "voxel_um: 0.000001\n")
    argv = ["study", str(study), "--scale", "small", "--cache", str(tmp_path / "c"), "--results", str(tmp_path / "r"),
            "--dry-run"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "line 13: `voxel_um` must be >= 0.01 µm, got voxel_um=1e-06" in err, err
    study.write_text(text + "voxel_um: 0.25\n")
    assert main(argv) == 0
    notes = [ln for ln in capsys.readouterr().err.splitlines() if "unused" in ln]
    assert notes == ([] if method == "fast" else [
        "twray study: `voxel_um` is unused in v: method exact traces the model's own surfaces, no voxels (it "
        "applies with --method fast, accurate or paper)"])
