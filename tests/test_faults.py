"""Faults a run must survive with one line and nothing half-written: a full disk at every stage, a
worker killed mid-task, a worker over its memory limit.  After each, a rerun gives the same numbers."""

import os
import signal
import threading
import time

import numpy as np
import pytest
import xarray as xr

from pipeline.cache import FAULT_ENV
from pipeline.cli import main
from pipeline.runlog import FAULT_MEMORY_ENV

STUDY = """\
title: faults
preset: birch
seed: 4
realisations: 2
rays: 400
beam_um: 100
thickness_mm: 0.4
trace: {method: %s}
vary: {parameter: delta_ri, values: [0.01, -0.02]}
"""


def study(tmp_path, method="exact"):
    path = tmp_path / "faults.yaml"
    path.write_text(STUDY % method)
    return path


def args(path, tmp_path, *more):
    return ["study", str(path), "--scale", "small", "--cache", str(tmp_path / "c"), "--results",
            str(tmp_path / "r"), "--workers", "1", *more]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The study's numbers from runs that met no fault, per method."""
    out = {}
    for method in ("exact", "fast"):
        tmp = tmp_path_factory.mktemp(f"clean-{method}")
        assert main(args(study(tmp, method), tmp)) == 0
        out[method] = xr.open_zarr(tmp / "r" / "faults.zarr", consolidated=False).load()
    return out


def assert_one_line(err: str, *needles):
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("twray study: ")]
    assert len(lines) == 1, err
    assert lines[0].startswith("twray: error: ") and "traceback in " in lines[0], lines[0]
    for n in needles:
        assert n in lines[0], lines[0]
    assert "Traceback" not in err and "distributed." not in err


def assert_nothing_half_written(tmp_path, capsys):
    assert main(["cache", "verify", "--cache", str(tmp_path / "c")]) == 0  # no damaged entry, no leftover
    capsys.readouterr()
    assert not (tmp_path / "r" / "faults.zarr").exists()
    assert not [p for p in (tmp_path / "r").rglob("*") if p.name.startswith(".")] if (tmp_path / "r").exists() else True


def assert_same(tmp_path, ds_clean):
    ds = xr.open_zarr(tmp_path / "r" / "faults.zarr", consolidated=False)
    for name in ("theta_r", "theta_l", "status", "FWHM_R", "haze_ci_lower"):
        np.testing.assert_array_equal(ds[name].values, ds_clean[name].values)


@pytest.mark.parametrize("stage, method, needle", [
    ("micro", "fast", "/c/micro/"),  # generating the wood's chunks
    ("rays", "exact", "/c/rays/"),
    ("summary", "exact", "/c/summary/"),
    ("pool", "exact", "/c/pool/"),
    ("dataset", "exact", "/r/faults.zarr"),
])
def test_a_full_disk_is_one_line_naming_the_path_and_the_fix_and_the_rerun_is_whole(
        tmp_path, monkeypatch, capsys, clean, stage, method, needle):
    path = study(tmp_path, method)
    monkeypatch.setenv(FAULT_ENV, f"{stage}:0")
    assert main(args(path, tmp_path)) == 1
    err = capsys.readouterr().err
    assert_one_line(err, "no space left writing", needle, "free space on its disk")
    if stage == "micro":  # a task's line names what it computes
        assert "[wood chunks of " in err
    elif stage != "dataset":
        assert "[faults delta_ri=" in err
    log = err.split("traceback in ")[-1].strip()
    assert os.path.isfile(log) and "No space left on device" in open(log).read()
    assert_nothing_half_written(tmp_path, capsys)
    monkeypatch.delenv(FAULT_ENV)
    assert main(args(path, tmp_path)) == 0
    assert_same(tmp_path, clean[method])


def test_a_log_on_a_full_disk_prints_nothing_of_its_own_and_is_named_once(tmp_path, capsys):
    """A log handler whose disk is full (/dev/full: every write fails with ENOSPC) drops its records
    without a word on the terminal (Python's logging prints a traceback for each); the error line
    names the log once, and the traceback goes to the temporary folder's log."""
    import logging

    from pipeline import runlog

    runlog.start(tmp_path / "c")
    runlog.log_file().parent.mkdir(parents=True)
    runlog.log_file().symlink_to("/dev/full")
    runlog.route_dask_logs(runlog.log_file())
    for _ in range(10):
        logging.getLogger("distributed.worker").warning("a record the full disk cannot take")
    assert capsys.readouterr().err == ""
    try:
        raise OSError(28, "No space left on device", str(tmp_path / "c" / "rays" / "x.npz"))
    except OSError as exc:
        note = runlog.traceback_note(exc)
    assert note.startswith(f"traceback in {runlog._temp_log()}; the log {runlog.log_file()} could not be written "
                           "(No space left on device)"), note
    runlog.start()


def test_a_full_disk_under_the_cache_and_its_log_is_at_most_three_lines(tmp_path, monkeypatch, capsys, clean):
    """The cache's disk fills mid-run and the log (in the cache) sits on the same full disk: at most
    three lines on stderr, the cache path and the log named, nothing half-written, and the rerun
    after space is freed equals an undisturbed run."""
    import time as _time

    path = study(tmp_path)
    log = tmp_path / "c" / "logs" / f"twray-{_time.strftime('%Y%m%d')}.log"
    log.parent.mkdir(parents=True)
    log.symlink_to("/dev/full")
    monkeypatch.setenv(FAULT_ENV, "rays:0")
    assert main(args(path, tmp_path, "--quiet")) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) <= 3 and "Logging error" not in err and "Traceback" not in err, err
    assert "dashboard" not in err  # --quiet: no dashboard line either
    line = err.strip().splitlines()[-1]
    assert line.startswith("twray: error: no space left writing ") and "/c/rays/" in line
    assert f"the log {log} could not be written (No space left on device)" in line, line
    log.unlink()
    assert_nothing_half_written(tmp_path, capsys)
    monkeypatch.delenv(FAULT_ENV)
    assert main(args(path, tmp_path)) == 0
    assert_same(tmp_path, clean["exact"])


def test_a_worker_killed_mid_task_is_replaced_and_the_numbers_are_the_same(tmp_path, capsys, clean):
    from distributed import Client, LocalCluster

    from pipeline.study.dataset import write_dataset
    from pipeline.study.graph import compute
    from pipeline.study.plan import plan_study
    from pipeline.study.spec import load_study

    st = load_study(study(tmp_path), scale="small")
    killed = []
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        pids = list(client.run(os.getpid).values())

        def kill():
            # Mid-run: as soon as the worker holds one of the study's tasks (a fixed delay is not
            # mid-run on a host where the study takes less).
            deadline = time.monotonic() + 60.0
            while not any(client.processing().values()) and time.monotonic() < deadline:
                time.sleep(0.01)
            killed.append(pids[0])
            os.kill(pids[0], signal.SIGKILL)

        timer = threading.Thread(target=kill)
        timer.start()
        compute([plan_study(st, tmp_path / "c")], client)
        timer.join()
        assert killed and set(client.run(os.getpid).values()).isdisjoint(killed)  # a new worker took over
    write_dataset(plan_study(st, tmp_path / "c"), tmp_path / "r")
    assert main(["cache", "verify", "--cache", str(tmp_path / "c")]) == 0
    assert_same(tmp_path, clean["exact"])


def test_a_worker_over_its_memory_limit_is_one_line_and_the_rerun_is_whole(tmp_path, monkeypatch, capsys, clean):
    import dask
    import distributed  # noqa: F401  (its configuration loaded before a part of it is set)

    path = study(tmp_path)
    monkeypatch.setenv(FAULT_MEMORY_ENV, "1500")
    # One death gives up on a task (Dask's default retries it on three more workers): the line is
    # the same, with a quarter of the restarts.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        assert main(args(path, tmp_path, "--memory-limit", "1GB")) == 1
    err = capsys.readouterr().err
    assert_one_line(err, "a worker died running faults delta_ri=", "over its memory limit", "--memory-limit")
    assert_nothing_half_written(tmp_path, capsys)
    monkeypatch.delenv(FAULT_MEMORY_ENV)
    assert main(args(path, tmp_path, "--memory-limit", "1GB")) == 0
    assert_same(tmp_path, clean["exact"])


def test_a_local_cluster_left_without_workers_fails_in_one_line_instead_of_waiting(tmp_path, capsys):
    import dask
    import distributed  # noqa: F401  (its configuration loaded before a part of it is set)

    from pipeline.cluster import graph_client
    from pipeline.runlog import RunFailed
    from pipeline.study.graph import compute
    from pipeline.study.plan import plan_study
    from pipeline.study.spec import load_study

    st = load_study(study(tmp_path), scale="small")
    with dask.config.set({"distributed.scheduler.no-workers-timeout": "1s"}):
        client, cluster = graph_client("study", workers=1, threads=1)
    with cluster, client:
        cluster.scale(0)  # the last worker gone, none to take its place (as when a nanny cannot restart it)
        deadline = time.monotonic() + 30
        while client.scheduler_info()["workers"] and time.monotonic() < deadline:
            time.sleep(0.1)
        t0 = time.monotonic()
        with pytest.raises(RunFailed) as failed:
            compute([plan_study(st, tmp_path / "c")], client, progress="lines")
        assert time.monotonic() - t0 < 30
    line = str(failed.value)
    assert line.startswith("no worker was left to run faults delta_ri=") and "within 1 s" in line, line
    assert "--memory-limit" in line and "traceback in " in line and "\n" not in line
    assert not [p for p in tmp_path.joinpath("c").rglob("*") if p.is_file() and "logs" not in p.parts]  # nothing ran
