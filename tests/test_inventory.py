"""`twray cache` underneath (pipeline/inventory.py): a cache folder's entries listed by stage with
their size and provenance, each verified (damaged files named, foreign entries recognised), what
interrupted runs left found, and entries removed."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline import __version__
from pipeline.cache import HOST, cache_key, write_json, write_npz
from pipeline.inventory import STAGES, keys_in_use, remove, scan, verify
from pipeline.microstructure.store import wood_record, wood_store
from pipeline.params import build_params
from pipeline.study.spec import load_study

RAYS = {"stage": "rays", "range": [0, 500], "micro": "abcdef0123456789abcdef01", "settings": {"method": "fast"},
        "n_wall": 1.5, "thickness_vox": 200, "tracer": 7}
SUMMARY = {"stage": "summary", "rays": ["k1", "k2"], "n_boot": 200}
POOL = {"stage": "pool", "summaries": ["s1", "s2", "s3"], "n_boot": 100}
CAMERA = {"stage": "camera", "camera": {"pixels": [51, 51]}, "sheet": {"thickness_um": 500}, "tracer": 7}
ROWS = {"image": CAMERA, "rows": [0, 3]}  # a block of rows of an image not yet whole
OLD = 0  # an mtime long past: what another host left is a leftover only once it is a day old


def _files_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


@pytest.fixture(scope="module")
def wood(tmp_path_factory):
    """A wood store of one generated chunk (birch, seed 3, 0.5 µm), made once; tests copy it."""
    cache = tmp_path_factory.mktemp("wood")
    store = wood_store(cache, build_params("birch"), 3, 0.5)
    store.get((0, 0, 0))
    return store.path


@pytest.fixture
def cache(tmp_path, wood):
    """A cache with one sound entry of every stage."""
    c = tmp_path / "cache"
    shutil.copytree(wood, c / "micro" / wood.name)
    write_npz(c / "rays" / f"{cache_key(RAYS)}.npz", RAYS, {"theta_r": np.linspace(-3, 3, 500)})
    write_json(c / "summary" / f"{cache_key(SUMMARY)}.json", SUMMARY, {"fwhm_r_deg": 5.52})
    write_json(c / "pool" / f"{cache_key(POOL)}.json", POOL, {"haze": 0.8})
    write_npz(c / "camera" / f"{cache_key(CAMERA)}.npz", CAMERA, {"image": np.ones((51, 51), np.float32)})
    write_npz(c / "camera-rows" / f"{cache_key(ROWS)}.npz", ROWS, {"image": np.ones((3, 51))})
    return c


def _by_stage(entries):
    return {e.stage: e for e in entries}


def test_entries_are_listed_by_stage_with_their_size_and_provenance(cache, wood):
    entries = scan(cache)
    assert [e.stage for e in entries] == list(STAGES)  # one of each, in stage order
    e = _by_stage(entries)
    assert e["micro"].key == wood.name[:-len(".zarr")]
    assert e["micro"].about == f"birch wood, seed 3, 0.5 um voxels, 1 chunks, twray {__version__}"
    assert e["rays"].key == cache_key(RAYS)
    assert e["rays"].about == "rays 0-500 of wood abcdef01, fast, n_wall 1.5, 200 voxels thick, tracer 7"
    assert e["summary"].about == "summary of 2 ray shards, FWHM lorentz-mle"  # a record before estimators
    assert e["pool"].about == "3 wood realisations pooled, FWHM lorentz-mle, 100 bootstrap draws"
    assert e["camera"].about == "image [51, 51] px, with sheet, tracer 7"
    assert e["camera-rows"].about == f"rows 0-3 of camera image {cache_key(CAMERA)[:12]}"
    # A file's size is its bytes; a wood store's, all the files in it.
    assert e["micro"].size == _files_size(e["micro"].path) > 2000
    for stage in ("rays", "summary", "pool", "camera", "camera-rows"):
        assert e[stage].size == e[stage].path.stat().st_size > 0
    assert all(verify(x) == [] for x in entries)


def test_an_empty_or_missing_cache_holds_nothing(tmp_path):
    assert scan(tmp_path / "nowhere") == []
    for stage in STAGES:
        (tmp_path / stage).mkdir()
    assert scan(tmp_path) == []


def test_leftovers_of_ended_runs_are_found_but_a_live_runs_work_and_hidden_files_are_not(cache):
    old = cache / "rays" / ".x.npz.tmp-elsewhere-1-0123abcd"  # another host's, a day old
    old.write_bytes(b"half")
    os.utime(old, (OLD, OLD))
    young = cache / "rays" / ".y.npz.tmp-elsewhere-1-0123abcd"  # another host's, just written
    young.write_bytes(b"half")
    mine = cache / "summary" / f".z.json.tmp-{HOST}-{os.getpid()}-0123abcd"  # this live process's
    mine.write_text("{")
    (cache / "pool" / ".DS_Store").write_bytes(b"\0")
    chunk_dir = next((cache / "micro").rglob("c/160/0"))
    half_chunk = chunk_dir / ".161.partial-elsewhere-7-89abcdef"  # inside a wood store
    half_chunk.write_bytes(b"12345")
    os.utime(half_chunk, (OLD, OLD))
    leftovers = [e for e in scan(cache) if e.stage == "leftover"]
    assert sorted(e.path for e in leftovers) == sorted([old, half_chunk])
    assert {e.path: e.size for e in leftovers} == {old: 4, half_chunk: 5}
    assert all(verify(e) == [(e.path, "left by an interrupted run")] for e in leftovers)


def test_a_file_not_named_as_an_entry_is_unknown_and_left_unjudged(cache):
    notes = cache / "rays" / "notes.txt"
    notes.write_text("mine")
    (cache / "summary" / "x.npz").write_bytes(b"PK")  # a rays file in the summary folder
    unknown = [e for e in scan(cache) if e.stage == "unknown"]
    assert sorted(e.path.name for e in unknown) == ["notes.txt", "x.npz"]
    assert all(e.key == "" and verify(e) == [] for e in unknown)


def test_damaged_entries_are_named_with_what_is_wrong(cache):
    e = _by_stage(scan(cache))
    ray = e["rays"].path
    ray.write_bytes(ray.read_bytes()[:-5])  # cut short
    summary = e["summary"].path
    summary.write_text(summary.read_text().replace("5.52", "5.75"))  # a number edited
    pool = e["pool"].path
    pool.write_text(pool.read_text().replace('"n_boot": 100', '"n_boot": 99'))  # its provenance edited
    e = _by_stage(scan(cache))
    [(path, why)] = verify(e["rays"])
    assert path == ray and why.startswith("unreadable: ")
    assert verify(e["summary"]) == [(summary, "content does not match its digest")]
    assert verify(e["pool"]) == [(pool, "its record does not hash to its key")]
    assert e["pool"].about == "3 wood realisations pooled, FWHM lorentz-mle, 99 bootstrap draws"  # what it now says it is
    assert verify(e["camera"]) == []  # the others are sound


def test_an_entry_under_another_entrys_name_is_foreign(cache):
    """A sound file of one key, copied to another key's name, is not that entry."""
    other = {**RAYS, "range": [500, 1000]}
    src = cache / "rays" / f"{cache_key(RAYS)}.npz"
    dst = cache / "rays" / f"{cache_key(other)}.npz"
    shutil.copy(src, dst)
    found = {x.key: x for x in scan(cache) if x.stage == "rays"}
    assert verify(found[cache_key(RAYS)]) == []
    why = f"computed for key {cache_key(RAYS)!r}, expected {cache_key(other)!r}"
    assert verify(found[cache_key(other)]) == [(dst, why)]


def test_a_wood_stores_damaged_chunk_is_named_and_the_rest_of_the_store_is_sound(cache):
    store = next((cache / "micro").iterdir())
    [chunk] = [f for f in store.rglob("*") if f.is_file() and f.name.isdigit()]
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    chunk.write_bytes(bytes(raw))
    assert verify(_by_stage(scan(cache))["micro"]) == [(chunk, "content does not match its digest")]
    chunk.write_bytes(chunk.read_bytes()[:-24])  # its digest frame cut off
    assert verify(_by_stage(scan(cache))["micro"]) == [(chunk, "no digest")]
    remove(chunk)
    e = _by_stage(scan(cache))["micro"]
    assert verify(e) == [] and e.about.endswith(f"0 chunks, twray {__version__}")  # generated again when needed


def test_a_wood_store_under_another_key_or_not_twrays_is_recognised(cache, tmp_path):
    store = next((cache / "micro").iterdir())
    other_key = cache_key(wood_record(build_params("birch"), 4, 0.5))  # seed 4's name on seed 3's wood
    moved = store.with_name(f"{other_key}.zarr")
    store.rename(moved)
    foreign = cache / "micro" / "0123456789abcdef01234567.zarr"  # a Zarr group that is not a wood store
    foreign.mkdir()
    (foreign / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {}}))
    found = {x.path: x for x in scan(cache) if x.stage == "micro"}
    assert verify(found[moved]) == [(moved, "not the wood its key names (or made by an older twray)")]
    assert found[foreign].about == "not a wood store"
    assert verify(found[foreign]) == [(foreign, "not a twray wood store")]


def test_removing_entries_takes_files_and_whole_stores_and_tolerates_what_is_gone(cache):
    entries = _by_stage(scan(cache))
    remove(entries["micro"].path)
    remove(entries["rays"].path)
    remove(entries["rays"].path)  # already gone: nothing to do
    assert not entries["micro"].path.exists() and not entries["rays"].path.exists()
    assert [e.stage for e in scan(cache)] == ["summary", "pool", "camera", "camera-rows"]
    assert list((cache / "micro").iterdir()) == []


STUDY = """\
title: inventory
preset: birch
seed: 3
realisations: 1
rays: 400
beam_um: 100
thickness_mm: 0.3
trace: {method: fast}
vary:
  parameter: delta_ri
  values: [0.01, 0.02]
"""


def test_the_keys_in_use_are_the_studys_wood_and_its_stages_not_another_seeds(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text(STUDY)
    keys = keys_in_use([study], ["small"], tmp_path / "cache")
    scenes = load_study(study, scale="small").all_scenes()
    woods = {cache_key(wood_record(s.wood, s.seed, s.traced_voxel_um)) for s in scenes}
    assert len(woods) == 1 and woods <= keys  # both ΔRI values trace the one wood
    other = {cache_key(wood_record(s.wood, s.seed + 1, s.traced_voxel_um)) for s in scenes}
    assert not other & keys
    # Besides the wood, per value (400 rays: one shard) its rays, a summary and a pool.
    assert len(keys) == 1 + 2 * 3 and all(len(k) == 24 for k in keys)
    again = study.with_name("again.yaml")
    again.write_text(STUDY.replace("seed: 3", "seed: 4"))
    assert keys_in_use([study], ["small"], tmp_path / "cache").isdisjoint(
        keys_in_use([again], ["small"], tmp_path / "cache"))
