"""The verified cache: damaged entries are found, logged and recomputed to the same numbers;
leftovers of interrupted runs are swept; runs publishing one output at once all succeed."""

import json
import logging
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import xarray as xr
import zarr

from pipeline.cache import (cache_key, check_json, check_npz, entry_record, is_leftover, sweep_leftovers,
                            temp_name, write_json, write_npz)
from pipeline.cli import main
from pipeline.microstructure.store import WoodChunkStore
from pipeline.microstructure.volume import WoodVolume
from pipeline.publish import publish
from pipeline.params import build_params, make_grid
from pipeline.study.plan import plan_study
from pipeline.study.spec import load_study

STUDY = """\
title: damage
preset: birch
seed: 3
realisations: 1
rays: 400
beam_um: 100
thickness_mm: 0.3
trace: {method: fast}
vary:
  parameter: delta_ri
  values: [-0.02, 0.02]
"""
VALUES = ("FWHM_R", "FWHM_L", "haze", "FWHM_R_ci_lower", "FWHM_L_ci_upper", "theta_r", "theta_l", "status")


# ---------------------------------------------------------------------- entries
def test_an_entry_is_sound_only_for_its_own_key_and_content(tmp_path):
    arrays = {"a": np.arange(5.0), "b": np.int64(3)}
    k1, k2 = cache_key({"stage": "x", "n": 1}), cache_key({"stage": "x", "n": 2})
    write_npz(tmp_path / "x.npz", {"stage": "x", "n": 1}, arrays)
    got, why = check_npz(tmp_path / "x.npz", k1)
    assert why is None and np.array_equal(got["a"], arrays["a"]) and set(got) == {"a", "b"}
    assert entry_record(tmp_path / "x.npz") == {"stage": "x", "n": 1}  # its provenance
    assert f"expected '{k2}'" in check_npz(tmp_path / "x.npz", k2)[1]  # a file under another key
    assert check_npz(tmp_path / "none.npz", k1) == (None, None)  # absent, not damaged
    raw = (tmp_path / "x.npz").read_bytes()
    (tmp_path / "x.npz").write_bytes(raw[: len(raw) // 2])
    assert "unreadable" in check_npz(tmp_path / "x.npz", k1)[1]

    write_json(tmp_path / "s.json", {"stage": "x", "n": 1}, {"fwhm": 5.52})
    assert check_json(tmp_path / "s.json", k1) == ({"fwhm": 5.52}, None)
    text = (tmp_path / "s.json").read_text()
    (tmp_path / "s.json").write_text(text.replace("5.52", "5.75"))
    assert check_json(tmp_path / "s.json", k1) == (None, "content does not match its digest")
    (tmp_path / "s.json").write_text(text.replace('"n": 1', '"n": 2'))  # provenance edited
    assert check_json(tmp_path / "s.json", k1) == (None, "its record does not hash to its key")
    (tmp_path / "s.json").write_bytes(b"\xff\xfe binary")
    assert "unreadable" in check_json(tmp_path / "s.json", k1)[1]


def test_a_damaged_or_misplaced_wood_chunk_is_generated_again(tmp_path, caplog):
    params = build_params("birch")
    store = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
    a, b = store.get((0, 1, 0)).copy(), store.get((1, 1, 0)).copy()
    assert not np.array_equal(a, b)
    fa, fb = store._files.path((160, 1, 160)), store._files.path((161, 1, 160))
    # zarr reads the chunk files, digest frame and all
    assert np.array_equal(zarr.open_array(tmp_path / "w.zarr" / "0")[160 * 16:161 * 16, 16:32, 160 * 16:161 * 16], a)
    damages = {
        "content does not match its digest": lambda: shutil.copy(fb, fa),  # b's file at a's index
        "no digest": lambda: fa.write_bytes(fa.read_bytes()[:-24]),
    }
    for why, damage in damages.items():
        store.get((0, 1, 0))
        damage()
        fresh = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
        with caplog.at_level(logging.WARNING, logger="twray.cache"):
            from pipeline.microstructure.store import _memory
            _memory.clear()
            got = fresh.get((0, 1, 0))
        assert np.array_equal(got, a) and fresh.generated == 1, why
        assert why in caplog.text and str(fa) in caplog.text
        caplog.clear()
    # A flipped byte inside the compressed frame.
    raw = bytearray(fa.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    fa.write_bytes(bytes(raw))
    fresh = WoodChunkStore(tmp_path / "w.zarr", params, seed=5, voxel_um=0.5, chunks=(16, 16, 16))
    from pipeline.microstructure.store import _memory
    _memory.clear()
    assert np.array_equal(fresh.get((0, 1, 0)), a) and fresh.generated == 1
    # The same wood with another seed fails every chunk of the first.
    other = WoodChunkStore(tmp_path / "w.zarr", params, seed=6, voxel_um=0.5, chunks=(16, 16, 16))
    _memory.clear()
    assert other._files.check((160, 1, 160))[1] == "content does not match its digest"


def test_a_volumes_damaged_chunk_is_generated_again(tmp_path):
    params = build_params("birch")
    grid = make_grid((40.0, 40.0, 40.0), 0.5, (0.0, 0.0, 0.0), params)
    vol = WoodVolume.create(tmp_path / "v.zarr", params, grid, seed=2, chunks=(32, 32, 32))
    whole = vol[:, :, :].copy()
    f0, f1 = vol._files.path((0, 0, 0)), vol._files.path((1, 0, 0))
    shutil.copy(f1, f0)
    again = WoodVolume.open(tmp_path / "v.zarr")
    assert np.array_equal(again[:, :, :], whole)


# ---------------------------------------------------------------------- a study, damaged
def _values(path):
    with xr.open_zarr(path, consolidated=False) as ds:
        return {k: ds[k].values.copy() for k in VALUES}


def test_a_damaged_cache_gives_the_numbers_of_an_undamaged_run(tmp_path, capfd):
    study = tmp_path / "damage.yaml"
    study.write_text(STUDY)
    cache, results = tmp_path / "c", tmp_path / "r"
    args = ["study", str(study), "--scale", "small", "--cache", str(cache), "--results", str(results),
            "--workers", "1"]
    assert main(args) == 0
    before = _values(results / "damage.zarr")
    plan = plan_study(load_study(study, scale="small"), cache)
    rays = [s.path for s in plan.shards]
    summaries = [s.path for s in plan.summaries]
    chunks = sorted((cache / "micro").rglob("c/*/*/*"))
    assert len(rays) == 2 and len(chunks) >= 2

    # Two ray files swapped (both decode), a summary edited (still valid JSON), two wood
    # chunks under the beam swapped too: the swapped rays are traced again through them.
    a, b = rays[0].read_bytes(), rays[1].read_bytes()
    rays[0].write_bytes(b)
    rays[1].write_bytes(a)
    record = json.loads(summaries[0].read_text())
    record["value"]["fwhm_r_deg"] = 99.0
    summaries[0].write_text(json.dumps(record))
    c0, c1 = chunks[0].read_bytes(), chunks[1].read_bytes()
    chunks[0].write_bytes(c1)
    chunks[1].write_bytes(c0)
    # The result dataset's values changed on disk behind its attributes' back.
    arr = zarr.open_array(results / "damage.zarr" / "FWHM_R", mode="r+")
    arr[0] = 42.0
    capfd.readouterr()
    assert main(args) == 0
    err = capfd.readouterr().err
    assert err.count("is damaged") >= 4, err  # each damaged entry named, on one line each
    assert str(rays[0]) in err and str(summaries[0]) in err
    after = _values(results / "damage.zarr")
    for k in VALUES:
        assert np.array_equal(before[k], after[k], equal_nan=True), k
    # Everything is sound again: a third run computes and rewrites nothing.
    stamp = {p: p.stat().st_mtime_ns for p in cache.rglob("*") if p.is_file() and p.parent.name != "logs"}
    assert main(args) == 0
    assert "damaged" not in capfd.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in cache.rglob("*") if p.is_file() and p.parent.name != "logs"} == stamp

    # An entry that no longer decodes at all is recomputed, not a traceback on every rerun.
    rays[1].write_bytes(b"\x00" * 100)
    summaries[1].write_bytes(b"\xff\xfe\x00")
    assert main(args) == 0
    assert "Traceback" not in capfd.readouterr().err
    for k, v in _values(results / "damage.zarr").items():
        assert np.array_equal(before[k], v, equal_nan=True), k


# ---------------------------------------------------------------------- leftovers and concurrency
def test_leftovers_of_ended_runs_are_swept_and_live_ones_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    live = temp_name(tmp_path / "x.zarr", "partial")  # this process: alive
    live.mkdir()
    gone = Path(str(temp_name(tmp_path / "x.zarr", "partial")).replace(f"-{os.getpid()}-", f"-{dead}-"))
    gone.mkdir()
    (gone / "zarr.json").write_text("{}")
    tmp = Path(str(temp_name(tmp_path / "y.npz", "tmp")).replace(f"-{os.getpid()}-", f"-{dead}-"))
    tmp.write_bytes(b"half")
    foreign_old = tmp_path / ".z.zarr.old-elsewhere-123-0123abcd"
    foreign_old.mkdir()
    os.utime(foreign_old, (0, 0))  # another host's, a day old: gone too
    foreign_new = tmp_path / ".z.zarr.old-elsewhere-124-0123abcd"
    foreign_new.mkdir()
    keep = tmp_path / ".hidden-but-mine"
    keep.write_text("x")
    assert is_leftover(gone) and not is_leftover(live)
    removed = sweep_leftovers(tmp_path)
    assert sorted(removed) == sorted([gone, tmp, foreign_old])
    assert live.exists() and foreign_new.exists() and keep.exists()


def test_runs_publishing_one_store_at_once_all_succeed(tmp_path):
    out = tmp_path / "result.zarr"
    errors = []

    def one(i):
        staged = temp_name(out, "partial")
        staged.mkdir()
        (staged / "zarr.json").write_text(json.dumps({"attributes": {"source": f"twray {chr(65 + i)}"}}))
        (staged / "payload").write_text(chr(65 + i) * 1000)
        try:
            publish(staged, out, overwrite=True)
        except Exception as exc:  # noqa: BLE001 - collected for the assertion
            errors.append(exc)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    payload = (out / "payload").read_text()
    assert len(set(payload)) == 1 and json.loads((out / "zarr.json").read_text())["attributes"]["source"] == \
        f"twray {payload[0]}"
    assert [p.name for p in tmp_path.iterdir()] == ["result.zarr"]  # nothing set aside is left


# ---------------------------------------------------------------------- twray cache ls | verify | gc
def test_cache_ls_verify_and_gc(tmp_path, capsys):
    study = tmp_path / "damage.yaml"
    study.write_text(STUDY.replace("[-0.02, 0.02]", "[0.02]"))
    cache = tmp_path / "c"
    assert main(["study", str(study), "--scale", "small", "--cache", str(cache), "--results",
                 str(tmp_path / "r"), "--workers", "1"]) == 0
    capsys.readouterr()
    assert main(["cache", "ls", "--cache", str(cache), "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert sorted(r["stage"] for r in rows) == ["micro", "pool", "rays", "summary"]
    about = {r["stage"]: r["about"] for r in rows}
    assert "birch wood, seed 3, 0.5 um voxels" in about["micro"] and "fast" in about["rays"]
    assert about["pool"] == "1 wood realisations pooled, FWHM half-max, 2000 bootstrap draws"
    assert about["summary"].endswith("FWHM half-max")
    assert all(r["bytes"] > 0 for r in rows)

    assert main(["cache", "verify", "--cache", str(cache)]) == 0
    assert "4 entries verified, 0 damaged" in capsys.readouterr().err
    ray = next(Path(r["path"]) for r in rows if r["stage"] == "rays")
    chunk = next((cache / "micro").rglob("c/*/*/*"))
    raw = bytearray(chunk.read_bytes())
    raw[10] ^= 1
    chunk.write_bytes(bytes(raw))
    ray.write_bytes(ray.read_bytes()[:-5])
    assert main(["cache", "verify", "--cache", str(cache)]) == 1
    out = capsys.readouterr().out
    assert f"{ray}: unreadable" in out and "content does not match its digest" in out
    assert main(["cache", "verify", "--cache", str(cache), "--remove"]) == 1
    capsys.readouterr()
    assert not ray.exists() and not chunk.exists()
    assert main(["cache", "verify", "--cache", str(cache)]) == 0

    # gc keeps what the study uses, removes what another seed's study would not use.
    leftover = cache / "rays" / ".x.npz.tmp-elsewhere-1-0123abcd"
    leftover.write_bytes(b"half")
    os.utime(leftover, (0, 0))
    stranger = cache / "rays" / "notes.txt"
    stranger.write_text("mine")
    assert main(["cache", "gc", str(study), "--scale", "small", "--cache", str(cache)]) == 0
    out = capsys.readouterr().out
    assert f"removed {leftover}" in out and "left alone" in out and stranger.exists()
    assert len(list((cache / "summary").iterdir())) == 1 and len(list((cache / "micro").iterdir())) == 1
    other = tmp_path / "other.yaml"
    other.write_text(STUDY.replace("seed: 3", "seed: 4"))
    assert main(["cache", "gc", str(other), "--scale", "small", "--cache", str(cache), "--dry-run"]) == 0
    assert capsys.readouterr().out.count("would remove") == 3  # the wood, the summary and the pool
    assert len(list((cache / "micro").iterdir())) == 1
    assert main(["cache", "gc", str(other), "--scale", "small", "--cache", str(cache)]) == 0
    assert list((cache / "micro").iterdir()) == [] and list((cache / "summary").iterdir()) == []
    assert list((cache / "pool").iterdir()) == []
    assert main(["cache", "verify", "--cache", str(tmp_path / "nowhere")]) == 2
    # A flag of another action is named, not ignored.
    assert main(["cache", "ls", "--cache", str(cache), "--remove"]) == 2
    assert main(["cache", "verify", "--cache", str(cache), "--dry-run"]) == 2


def test_two_studies_run_at_once_on_one_cache_and_results_folder_both_succeed(tmp_path):
    study = tmp_path / "damage.yaml"
    study.write_text(STUDY)
    args = [sys.executable, "-m", "pipeline", "study", str(study), "--scale", "small", "--cache",
            str(tmp_path / "c"), "--results", str(tmp_path / "r"), "--workers", "1", "--threads", "1"]
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0 and "Traceback" not in err, err
    assert outs[0][0].splitlines()[1:3] == outs[1][0].splitlines()[1:3]  # the same numbers
    assert main(["cache", "verify", "--cache", str(tmp_path / "c")]) == 0
    assert [p.name for p in (tmp_path / "r").iterdir()] == ["damage.zarr"]
    with xr.open_zarr(tmp_path / "r" / "damage.zarr", consolidated=False) as ds:
        assert np.all(np.isfinite(ds.FWHM_R.values))
